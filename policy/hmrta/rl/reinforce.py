"""REINFORCE with a shared mean baseline and the constrained flashforward mechanism (SPEC §5),
with optional self-imitation.

One iteration: draw ``instances_per_iter`` instances (``ma-at``: one size from the
curriculum-narrowed training distribution; ``broad``: a mission family each, so sizes and time
scales mix), ``rollouts`` (beta) sampled rollouts of each, all
advanced together under ``torch.inference_mode``; then a single re-scoring forward (with gradient,
in chunks) over the recorded decisions gives the log-probabilities of the actions taken.
advantage = own return - mean of the instance's beta returns (``train.advantage: relative``:
divided by the instance's mean cost); loss = -mean(advantage * log p).
With ``rescore_fraction`` < 1 a random share of the decisions is re-scored, weighted by the
inverse inclusion probability (an unbiased gradient at a fraction of the cost).

Self-imitation (``train.sil``, project choice): the best of each instance's beta rollouts (by
return) is also imitated with a cross-entropy term of weight ``coef`` in the same re-scoring
pass, and its decisions enter a small replay buffer (the last ``buffer`` iterations) on which
``steps`` extra cross-entropy minibatch steps are taken per iteration. This distils the
best-of-beta sample into the argmax policy (Oh et al. 2018, self-imitation learning).
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..core import MissionState
from .features import concat_batches
from .rollout import returns, rollout

if TYPE_CHECKING:
    from .train import Trainer


class Reinforce:
    def __init__(self, run: "Trainer"):
        self.run = run
        self.sil_buffer: list[dict[str, torch.Tensor]] = []  # best-rollout decisions, not checkpointed

    def lr(self) -> float:
        t = self.run.cfg.train
        return t.lr * t.lr_decay ** (self.run.iteration // t.lr_decay_every)

    def step(self) -> dict:
        run, lr_ = self.run, self.run.learner
        t = run.cfg.train
        beta = t.rollouts
        insts = run._instances(t.instances_per_iter)
        states = [MissionState(inst, seed=int(lr_.np_rng.integers(2**31)), rules=run.train_rules)
                  for inst in insts for _ in range(beta)]
        t0 = time.perf_counter()
        lr_.model.eval()
        traj = rollout(lr_.model, states, sample=True, generator=lr_.torch_gen, record=True,
                       amp=lr_.amp, temperature=t.temperature)
        t_collect = time.perf_counter() - t0
        R = returns(states, t.t_max)  # [E]
        Rm = R.reshape(len(insts), beta)
        adv = Rm - Rm.mean(1, keepdims=True)  # [I, beta]
        if t.advantage == "relative":  # in units of the instance's mean cost (R = -T - W < 0)
            adv = adv / np.maximum(-Rm.mean(1, keepdims=True), 1e-9)
        adv = adv.reshape(-1)  # [E]
        adv_t = torch.tensor(adv, dtype=torch.float32, device=lr_.device)
        n_ep = len(states)
        # one re-scoring forward (with gradient) over all recorded decisions, in chunks
        lr_.set_lr(self.lr())
        lr_.model.train()
        lr_.opt.zero_grad(set_to_none=True)
        allobs = concat_batches(traj.obs)  # steps of missions of different sizes, padded to the widest
        acts = torch.cat(traj.actions)  # [D]
        eps = torch.cat(traj.episode)  # [D]
        D = len(acts)
        sil = t.sil
        best_ep = torch.as_tensor(Rm.argmax(1) + beta * np.arange(len(insts)))  # [I] best rollout per instance
        is_best = torch.isin(eps, best_ep)  # [D]
        n_best = max(int(is_best.sum()), 1)
        # re-score a random fraction of the decisions (the best rollouts' always), weighted by the
        # inverse inclusion probability: an unbiased REINFORCE gradient at a fraction of the cost
        frac = float(t.rescore_fraction)
        keep = is_best | torch.as_tensor(lr_.np_rng.random(D) < frac)  # [D]
        weight = torch.where(is_best, 1.0, 1.0 / frac)[keep]  # [D']
        sub = {k: v[keep] for k, v in allobs.items()}
        sub_acts, sub_eps, sub_best = acts[keep], eps[keep], is_best[keep]  # [D']
        ent_sum, loss_sum = 0.0, 0.0
        for lo in range(0, len(sub_acts), t.rescore_chunk):
            sl = slice(lo, lo + t.rescore_chunk)
            batch = {k: v[sl].to(lr_.device) for k, v in sub.items()}
            with torch.autocast(lr_.device.type, dtype=torch.bfloat16, enabled=lr_.amp):
                logits = lr_.model(**batch).float()  # [c, T]
            logp_all = torch.log_softmax(logits / t.temperature, dim=-1)  # [c, T]
            a = sub_acts[sl].to(lr_.device)
            logp = logp_all.gather(1, a[:, None])[:, 0]  # [c]
            safe = logp_all.masked_fill(~batch["action_mask"], 0.0)  # [c, T] (no 0 * -inf in the gradient)
            ent = -(safe.exp() * safe).masked_fill(~batch["action_mask"], 0.0).sum(-1)  # [c]
            wt = weight[sl].to(lr_.device)  # [c]
            loss = (-(wt * adv_t[sub_eps[sl].to(lr_.device)] * logp).sum()
                    - t.entropy_coef * (wt * ent).sum()) / n_ep
            if sil.coef:
                b = sub_best[sl].to(lr_.device)  # [c]
                ce = torch.nn.functional.cross_entropy(logits[b], a[b], reduction="sum")
                loss = loss + sil.coef * ce / n_best
            loss.backward()
            ent_sum += float((wt * ent).detach().sum())
            loss_sum += float(loss.detach())
        where = f"iteration {run.iteration + 1}"
        lr_.clipped_step(t.grad_clip, where)
        sil_loss = math.nan
        if sil.steps:
            self.sil_buffer.append({k: v[is_best] for k, v in {**allobs, "target": acts}.items()})
            del self.sil_buffer[:-sil.buffer]
            sil_loss = lr_.replay_steps(self.sil_buffer, sil.steps, sil.batch, t.grad_clip, where)
        dt = time.perf_counter() - t0
        run.iteration += 1
        run.episodes += n_ep
        run.decisions += D
        ok = np.array([s.success for s in states])
        mk = np.array([s.makespan for s in states if s.success])
        return {
            "iteration": run.iteration, "episodes": run.episodes, "reward": float(R.mean()),
            "makespan": float(mk.mean()) if len(mk) else math.nan, "success": float(ok.mean()),
            "entropy": ent_sum / max(D, 1), "loss": loss_sum, "lr": self.lr(), "sil_loss": sil_loss,
            "best_makespan": float(np.mean([states[i].makespan for i in best_ep.tolist()])),
            "decisions_per_s": D / max(t_collect, 1e-9), "episodes_per_s": n_ep / dt,
            "tasks": insts[0].n_tasks, "agents": insts[0].n_agents, "seconds": dt,
        }
