"""Batched rollouts: many MissionStates (instances x rollouts) advance together, with one forward
pass per decision step for every pending decision. The states are the core state machine itself,
so a batched rollout and ``hmrta.sim.run`` give identical schedules for identical choices.

A rollout of a few states (inference: one mission, a few samples, lookahead branches) runs its
forward passes on one intra-op thread: each pass is a millisecond of work, too small to share,
and on a busy machine the thread pool's synchronisation costs ten to a hundred times the work
itself. One thread also keeps the logits, and so the decisions, independent of the machine's
number of cores (the thread count changes the order of floating-point sums)."""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np
import torch

from ..core import DONE, MissionState
from ..solution import redundancy
from .features import batch_observations
from .model import GREEDY_DEPOT


SINGLE_THREAD_STATES = 64  # a rollout of at most this many states runs its forwards on one thread


@contextmanager
def intra_op_threads(n: int) -> Iterator[None]:
    """Run the block with at most ``n`` torch intra-op threads (the process setting is restored)."""
    old = torch.get_num_threads()
    fewer = n < old
    if fewer:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if fewer:
            torch.set_num_threads(old)


def forward_threads(n_states: int):
    """The threading of forward passes over ``n_states`` states: one thread for at most
    :data:`SINGLE_THREAD_STATES`, the process setting above."""
    return intra_op_threads(1 if n_states <= SINGLE_THREAD_STATES else torch.get_num_threads())


def model_device(model: torch.nn.Module) -> torch.device:
    """The device of ``model``'s weights (the CPU for a module or callable without any). Training
    may keep its network on a GPU; observations are built on the CPU and moved there for each
    forward pass."""
    params = getattr(model, "parameters", None)
    p = next(iter(params()), None) if callable(params) else None
    return p.device if p is not None else torch.device("cpu")


def to_device(obs: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """``obs`` on ``device`` (the same dict when that is the CPU, where observations are built)."""
    return obs if device.type == "cpu" else {k: v.to(device) for k, v in obs.items()}


def greedy_rows(logits: torch.Tensor, depot: str = "argmax") -> torch.Tensor:
    """[b] the greedy action rows of ``logits`` [b, T] (row 0 the depot, inadmissible rows -inf),
    by the rule ``depot`` (``ModelConfig.greedy_depot``): "argmax" the most likely row; "majority"
    the depot only when its probability is at least 1/2, otherwise the most likely task. Every
    greedy decision (rollouts, lookahead's own choice, live agents) goes through here."""
    act = logits.argmax(dim=-1)  # [b]
    if depot == "majority" and logits.shape[1] > 1:
        home = act == 0  # [b]
        if bool(home.any()):
            tasks = logits[:, 1:]  # [b, T-1]
            p_depot = torch.softmax(logits, dim=-1)[:, 0]  # [b]
            overrule = home & (p_depot < 0.5) & torch.isfinite(tasks).any(dim=-1)  # [b]
            act = torch.where(overrule, 1 + tasks.argmax(dim=-1), act)  # [b]
    elif depot not in GREEDY_DEPOT:
        raise ValueError(f"greedy_depot: expected one of {', '.join(GREEDY_DEPOT)}, got {depot!r}")
    return act


@dataclass
class Trajectories:
    """Recorded decisions of a batch of episodes (for the re-scoring forward of REINFORCE)."""

    obs: list[dict[str, torch.Tensor]] = field(default_factory=list)  # one batch per step
    actions: list[torch.Tensor] = field(default_factory=list)  # [n_active] per step
    episode: list[torch.Tensor] = field(default_factory=list)  # [n_active] episode index per step

    @property
    def decisions(self) -> int:
        return int(sum(len(a) for a in self.actions))


def rollout(model: torch.nn.Module, states: list[MissionState], *, sample: bool,
            generator: torch.Generator | None = None, record: bool = False,
            max_batch: int = 4096, amp: bool = False, temperature: float = 1.0,
            before_step: Callable[[list[int], dict, list, torch.Tensor], None] | None = None) -> Trajectories | None:
    """Advance every state to the end. Greedy decoding (:func:`greedy_rows` by the model's
    ``cfg.greedy_depot``) or sampled.

    ``temperature``: sampling from softmax(logits / temperature) (training exploration).
    ``amp``: bfloat16 autocast (training collection on the CPU only; inference stays float32 so
    that results are exactly reproducible).
    The forward passes run where ``model``'s weights are (a GPU in training); observations,
    logits, sampling (``generator`` is a CPU generator), recorded trajectories and actions stay on
    the CPU.
    ``before_step(idx, obs, nodes, act)``: called with each decision batch before the states step
    (e.g. to branch copies of some states)."""
    traj = Trajectories() if record else None
    device = model_device(model)
    active = [i for i, s in enumerate(states) if not s.done]
    with torch.inference_mode(), forward_threads(len(active)):
        while active:
            for lo in range(0, len(active), max_batch):
                idx = active[lo:lo + max_batch]
                obs, nodes = batch_observations([states[i] for i in idx], **model.cfg.view())
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
                    logits = model(**to_device(obs, device)).float().cpu()  # [b, T]
                if sample:
                    probs = torch.softmax(logits / temperature, dim=-1)  # [b, T]
                    act = torch.multinomial(probs, 1, generator=generator)[:, 0]  # [b]
                else:
                    act = greedy_rows(logits, model.cfg.greedy_depot)  # [b]
                if traj is not None:
                    traj.obs.append(obs)
                    traj.actions.append(act.clone())
                    traj.episode.append(torch.tensor(idx, dtype=torch.long))
                if before_step is not None:
                    before_step(idx, obs, nodes, act)
                for i, n, nm in zip(idx, act.tolist(), nodes):
                    states[i].step(int(nm[n]))
            active = [i for i in active if not states[i].done]
    return traj


def makespans(states: list[MissionState], t_max: float) -> np.ndarray:
    """[E] each episode's makespan T, ``t_max`` for a failed one (what returns and validation charge)."""
    return np.array([s.makespan if s.success else t_max for s in states], dtype=np.float64)


def returns(states: list[MissionState], t_max: float) -> np.ndarray:
    """Episode returns R = -T - W (T = T_max on failure)."""
    W = np.array([redundancy(s.inst, s.members, [bool(x == DONE) for x in s.status]) for s in states],
                 dtype=np.float64)  # [E]
    return -makespans(states, t_max) - W


def action_costs(model: torch.nn.Module | Callable[[MissionState], int],
                 decisions: list[tuple[MissionState, np.ndarray, np.ndarray]],
                 t_max: float, amp: bool = False) -> tuple[list[np.ndarray], list[MissionState]]:
    """One-step lookahead costs. ``decisions``: (state, nodes [T], action mask [T]) each. Every
    admissible action is tried on a clone and the mission finished by the model's greedy decoding
    (all branches of all decisions as one batch), or by ``model`` itself when it is a plain
    per-decision policy (``state -> node``, e.g. a baseline). Returns the costs T + W per action
    row [T] (inf where inadmissible) and the finished branches; the states themselves are not
    changed."""
    branches, owner, rows = [], [], []
    for k, (state, nodes, mask) in enumerate(decisions):
        for r in np.flatnonzero(mask):
            c = state.clone()
            c.step(int(nodes[r]))
            branches.append(c)
            owner.append(k)
            rows.append(r)
    if isinstance(model, torch.nn.Module):
        rollout(model, branches, sample=False, amp=amp)
    else:
        for c in branches:
            while not c.done:
                c.step(model(c))
    out = [np.full(len(mask), np.inf) for _, _, mask in decisions]
    for k, r, c in zip(owner, rows, -returns(branches, t_max)):
        out[k][r] = c
    return out, branches


def best_action(costs: np.ndarray, own: int) -> int:
    """The cheapest action row of ``action_costs``; ties (within 1e-6) go to the policy's own choice."""
    return own if costs.min() >= costs[own] - 1e-6 else int(np.argmin(costs))
