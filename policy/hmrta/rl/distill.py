"""Lookahead distillation (``distill``, project choice): policy improvement by one-step lookahead.

From random decisions of the current policy's greedy rollouts, every admissible action is tried
and the mission completed by the same policy; the action with the lowest cost T + W (ties: the
policy's own choice) becomes a cross-entropy target (``tau`` > 0: a soft target
softmax(-(cost - best) / tau)), replayed from a buffer of recent rounds. Each round imitates the
rollout algorithm of the current policy, which is never worse than the policy itself (Bertsekas'
cost-improvement property). With ``distill.teacher`` set to a baseline (``greedy``,
``greedy-coalition``) the branches are finished by that baseline instead: much cheaper labels, the
rollout algorithm over the baseline.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..core import MissionState
from .config import TEACHERS
from .rollout import action_costs, best_action, rollout

if TYPE_CHECKING:
    from .train import Trainer


class Distill:
    def __init__(self, run: "Trainer"):
        self.run = run
        self.buffer: list[dict[str, torch.Tensor]] = []  # lookahead targets, not checkpointed

    def step(self) -> dict:
        run, lr_ = self.run, self.run.learner
        d, t = run.cfg.distill, run.cfg.train
        amp = lr_.amp
        insts = run._instances(d.instances_per_iter, tuple(d.tasks) if d.tasks else None)
        states = [MissionState(inst, seed=int(lr_.np_rng.integers(2**31)), rules=run.train_rules)
                  for inst in insts]
        t0 = time.perf_counter()
        lr_.model.eval()
        rows: list[dict[str, torch.Tensor]] = []  # observation of each branched decision
        base: list[int] = []  # the policy's own action row there
        decisions: list[tuple[MissionState, np.ndarray, np.ndarray]] = []  # (state copy, nodes, mask)

        def branch(idx, obs, nodes, act):  # snapshot some decisions with more than one admissible action
            n_adm = obs["action_mask"].sum(1)  # [b]
            for j, i in enumerate(idx):
                if n_adm[j] > 1 and lr_.np_rng.random() < d.snapshot_prob:
                    rows.append({k: v[j] for k, v in obs.items()})
                    base.append(int(act[j]))
                    decisions.append((states[i].clone(), nodes[j], obs["action_mask"][j].numpy()))

        rollout(lr_.model, states, sample=False, amp=amp, before_step=branch)
        finisher = lr_.model if d.teacher == "policy" else TEACHERS[d.teacher]()
        costs, branches = action_costs(finisher, decisions, t.t_max, amp=amp)  # [T] per branched decision
        target, gain, changed = [], [], 0
        for c, own in zip(costs, base):
            best_r = best_action(c, own)
            changed += best_r != own
            if d.tau > 0:  # [T] target distribution over action rows (0 where inadmissible)
                q = torch.softmax(torch.as_tensor(-(c - c.min()) / d.tau), 0).float()
            else:
                q = torch.zeros(len(c))
                q[best_r] = 1.0
            target.append(q)
            gain.append((c[own] - c.min()) / c[own])
        t_collect = time.perf_counter() - t0
        loss = math.nan
        if rows:
            entry = {k: torch.stack([r_[k] for r_ in rows]) for k in rows[0]}
            entry["target"] = torch.stack(target)  # [n, T] probabilities
            self.buffer.append(entry)
            del self.buffer[:-d.buffer]
            lr_.set_lr(d.lr)
            loss = lr_.replay_steps(self.buffer, d.steps, d.batch, t.grad_clip, f"iteration {run.iteration + 1}")
        run.distill_done += 1
        n_dec = sum(s.decisions for s in states) + sum(s.decisions for s in branches)
        run.decisions += n_dec
        run.episodes += len(states) + len(branches)
        return {"iteration": run.distill_done, "makespan": float(np.mean([s.makespan for s in states])),
                "success": float(np.mean([s.success for s in states])), "loss": loss,
                "lookahead_gain": float(np.mean(gain)) if gain else math.nan,
                "changed": changed / max(len(rows), 1), "labels": len(rows),
                "decisions_per_s": n_dec / max(t_collect, 1e-9), "tasks": insts[0].n_tasks,
                "agents": insts[0].n_agents, "seconds": time.perf_counter() - t0}
