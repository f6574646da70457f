"""Observations of the deciding agent (SPEC §5), built from a MissionState.

Normalisation (project choice): requirement entries / 2 (the generators draw 0..2), times / 10
(durations / 5), positions relative to the decider in map units. Skills are zero-padded to
``K_MAX = 5``.

task rows  [1 + M, 2K + 5]: remaining req (K), req (K), rel. position (2), duration, travel time
           from the decider, completed flag. Row 0 is the decider's depot: only rel. position and
           travel time are set.
agent rows [A, K + 6]: traits (K), remaining execution time, remaining travel time, waiting time
           so far, rel. position (2), current-task-in-progress flag.

Observation window (project choice, for large teams): when a mission has more than
``max_tasks`` tasks or ``max_agents`` agents, the decider observes only its ``max_tasks`` nearest
tasks (admissible ones first, so every admissible task within reach of the window stays selectable)
and its ``max_agents`` nearest agents (itself included). This keeps inputs at the training scale
(at most 50 tasks and 25 agents) and the per-decision cost constant. Missions within the window
are observed whole, exactly as without it.
"""
from __future__ import annotations

import numpy as np
import torch

from ..core import DONE, IN_PROGRESS, LOST, OPEN, TASK, UNRELEASED, MissionState

K_MAX = 5
TASK_FEATURES = 2 * K_MAX + 5
AGENT_FEATURES = K_MAX + 6
REQ_SCALE = 0.5
TIME_SCALE = 0.1


MAX_TASKS = 50
MAX_AGENTS = 25


def observe(state: MissionState, a: int | None = None, max_tasks: int = MAX_TASKS, max_agents: int = MAX_AGENTS):
    """Observation of decider a (default: the current one), windowed for large missions.

    Returns (task_feat [1+W, 2K+5], agent_feat [N, K+6], mask [1+W], nodes [1+W], decider row):
    ``nodes`` maps task rows to state nodes (row 0 = depot = node 0).
    """
    a = state.agent if a is None else a
    pos = state.positions()  # [A, 2]
    tf, af, mask = _observe_full(state, a, pos)
    M, A = state.M, state.A
    nodes = np.arange(M + 1)
    if state.n_hidden:  # tasks not yet released are not observed at all (as if they did not exist)
        nodes = np.concatenate([[0], np.flatnonzero(state.status != UNRELEASED) + 1])
        tf, mask = tf[nodes], mask[nodes]
        M = len(nodes) - 1
    if M <= max_tasks and A <= max_agents:
        return tf, af, mask, nodes, a
    here = pos[a]  # [2]
    if M > max_tasks:
        d = np.hypot(*(state.inst.task_locations[nodes[1:] - 1] - here).T)  # [M]
        key = np.where(mask[1:], d, d + 1e6)  # admissible first, then by distance
        keep = np.sort(np.argsort(key, kind="stable")[:max_tasks]) + 1  # [W] task rows (1-based)
        rows = np.concatenate([[0], keep])  # [1+W]
        tf, mask = tf[rows], mask[rows]
        nodes = nodes[rows]
    if A > max_agents:
        d = np.hypot(*(pos - here).T)  # [A]
        d[a] = -1.0  # the decider itself always
        keep = np.sort(np.argsort(d, kind="stable")[:max_agents])  # [N]
        af = af[keep]
        a = int(np.flatnonzero(keep == a)[0])
    return tf, af, mask, nodes, a


def _observe_full(state: MissionState, a: int, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(task_feat [1+M, 2K+5], agent_feat [A, K+6], action mask [1+M]) for decider a; pos [A, 2]."""
    inst, K, M = state.inst, state.K, state.M
    if K > K_MAX:
        raise ValueError(f"the policy handles at most {K_MAX} skills, instance has {K}")
    t = state.clock
    me = pos[a]  # [2]
    v = inst.velocity
    tf = np.zeros((M + 1, TASK_FEATURES), dtype=np.float32)
    rel = inst.task_locations - me  # [M, 2]
    tf[1:, :K] = state.rem * REQ_SCALE
    tf[1:, K_MAX:K_MAX + K] = state.req * REQ_SCALE
    tf[1:, 2 * K_MAX:2 * K_MAX + 2] = rel
    tf[1:, 2 * K_MAX + 2] = inst.durations * (TIME_SCALE * 2)
    tf[1:, 2 * K_MAX + 3] = np.hypot(rel[:, 0], rel[:, 1]) * (TIME_SCALE / v)
    tf[1:, 2 * K_MAX + 4] = state.status == DONE
    drel = inst.depots[a] - me  # [2]
    tf[0, 2 * K_MAX:2 * K_MAX + 2] = drel
    tf[0, 2 * K_MAX + 3] = np.hypot(drel[0], drel[1]) * (TIME_SCALE / v)

    af = np.zeros((state.A, AGENT_FEATURES), dtype=np.float32)
    af[:, :K] = state.cap
    af[state.mode == LOST, :K] = 0.0  # a lost robot contributes nothing any more
    on_task = state.mode == TASK  # [A]
    tgt = np.where(on_task, state.target, 0)  # [A]
    tstat = np.where(on_task, state.status[tgt], -1)  # [A]
    running = tstat == IN_PROGRESS  # [A]
    fin = np.where(running, state.finish[tgt], t)  # [A]
    arrived = state.arrive <= t  # [A]
    af[:, K_MAX] = np.maximum(fin - t, 0.0) * TIME_SCALE
    af[:, K_MAX + 1] = np.maximum(state.arrive - t, 0.0) * TIME_SCALE
    waiting = on_task & arrived & ((tstat == OPEN) | (running & (state.start[tgt] > t)))
    af[:, K_MAX + 2] = np.where(waiting, t - state.arrive, 0.0) * TIME_SCALE
    af[:, K_MAX + 3:K_MAX + 5] = pos - me
    af[:, K_MAX + 5] = running
    return tf, af, state.mask()


def batch_observations(states: list[MissionState], max_tasks: int = MAX_TASKS, max_agents: int = MAX_AGENTS):
    """Stack (and pad) the current observations of several states into one batch.

    Returns (batch dict of tensors, per-state node maps [1+W])."""
    obs = [observe(s, None, max_tasks, max_agents) for s in states]
    return collate([o[:3] for o in obs], [o[4] for o in obs]), [o[3] for o in obs]


def collate(obs: list[tuple[np.ndarray, np.ndarray, np.ndarray]], deciders: list[int]) -> dict[str, torch.Tensor]:
    B = len(obs)
    T = max(o[0].shape[0] for o in obs)
    N = max(o[1].shape[0] for o in obs)
    tasks = np.zeros((B, T, TASK_FEATURES), dtype=np.float32)  # [B, T, Ft]
    agents = np.zeros((B, N, AGENT_FEATURES), dtype=np.float32)  # [B, N, Fa]
    tvalid = np.zeros((B, T), dtype=bool)  # [B, T]
    avalid = np.zeros((B, N), dtype=bool)  # [B, N]
    amask = np.zeros((B, T), dtype=bool)  # [B, T]
    for i, (tf, af, m) in enumerate(obs):
        tasks[i, :len(tf)] = tf
        agents[i, :len(af)] = af
        tvalid[i, :len(tf)] = True
        avalid[i, :len(af)] = True
        amask[i, :len(m)] = m
    return {
        "tasks": torch.from_numpy(tasks),
        "agents": torch.from_numpy(agents),
        "task_valid": torch.from_numpy(tvalid),
        "agent_valid": torch.from_numpy(avalid),
        "action_mask": torch.from_numpy(amask),
        "decider": torch.tensor(deciders, dtype=torch.long),
    }
