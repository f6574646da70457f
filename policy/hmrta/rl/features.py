"""Observations of the deciding agent (SPEC §5), built from a MissionState.

Normalisation (project choice), by the network's ``scale`` option (``ModelConfig.scale``):

* ``fixed`` (the scales of the paper's generators): requirement entries / 2 (the generators draw
  0..2), capabilities as they are, times / 10 (durations / 5), positions relative to the decider in
  map units.
* ``mission`` (scale-free): the same features in units of the mission itself, so that a mission and
  the same mission with every time doubled (durations doubled, speed halved), with the map
  stretched (positions and speed doubled), or with capabilities and requirements of a skill doubled
  are observed alike. The time unit is ``T = 2.266 x (mean task duration + mean distance of the
  tasks from their centroid / velocity)`` and the length unit ``velocity x T / 2``; requirements and
  capabilities of skill k are divided by the mean non-zero capability in skill k over the robots.
  Only tasks already known are used (unreleased tasks are not), so a released task and the same
  task added live give the same observation. The constant 2.266 makes both units come out at the
  ``fixed`` ones (T = 10, length 1, capability unit 1) on the paper's missions (expected task
  duration 2.5, mean distance to the centroid of the unit square 0.383, speed 0.2), so a network
  trained with ``fixed`` scales observes paper missions almost unchanged under ``mission``.

* ``mission+coalition``: the ``mission`` observation plus one task column, greedy-coalition's
  estimate of when the task's coalition can start if the decider joins now
  (:meth:`hmrta.baselines.CoalitionGreedy.estimates`), from now, in the observation's time unit,
  clipped at ``COALITION_CAP`` (also when the coalition cannot be completed); 0 for the depot row and
  the tasks the decider cannot take. The network then has ``task_features`` 2K + 6.

Skills are zero-padded to ``K_MAX = 5``.

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
SCALES = ("fixed", "mission", "mission+coalition")
COALITION_CAP = 4.0  # the coalition-start column, in observation time units, is clipped here
PAPER_TIME = 2.5 + 0.3826 / 0.2  # mean duration + mean centroid distance / speed of paper missions
TIME_UNIT = 10.0 / PAPER_TIME  # the 2.266 of the module docstring


class Scales:
    """Units of one observation: time (T), length (map units per observation unit) and the
    capability unit of each skill [K]."""
    __slots__ = ("time", "length", "cap")

    def __init__(self, time: float, length: float, cap: np.ndarray):
        self.time, self.length, self.cap = time, length, cap


def mission_scales(state: MissionState) -> Scales:
    """The ``mission`` units of a state (module docstring), from its known tasks and its robots.
    Cached on the state until its instance, its known tasks or its robots change."""
    key = (id(state.inst), state.M - state.n_hidden, state.A)
    cached = getattr(state, "_obs_scales", None)
    if cached is not None and cached[0] == key:
        return cached[1]
    inst = state.inst
    known = state.status != UNRELEASED if state.n_hidden else slice(None)
    locs = inst.task_locations[known]  # [m, 2]
    durs = inst.durations[known]  # [m]
    if len(durs):
        spread = float(np.hypot(*(locs - locs.mean(0)).T).mean())
        base = float(durs.mean()) + spread / inst.velocity
    else:
        base = 0.0
    if not base > 1e-9:  # no known task, or all at one point with no duration: the paper's unit
        base = PAPER_TIME
    T = TIME_UNIT * base
    cap = np.asarray(state.cap, dtype=np.float64)  # [A, K]
    n = (cap > 0).sum(0)  # [K]
    unit = np.where(n > 0, cap.sum(0) / np.maximum(n, 1), 1.0)  # [K]
    sc = Scales(T, inst.velocity * T / 2.0, unit)
    state._obs_scales = (key, sc)
    return sc


def task_features(scale: str) -> int:
    """The width of a task row under ``scale``: 2K + 5, one more with the coalition-start column."""
    return TASK_FEATURES + (scale == "mission+coalition")


FIXED = Scales(1.0 / TIME_SCALE, 1.0, np.ones(K_MAX))


def observe(state: MissionState, a: int | None = None, max_tasks: int = MAX_TASKS, max_agents: int = MAX_AGENTS,
            scale: str = "fixed"):
    """Observation of decider a (default: the current one), windowed for large missions, with
    ``fixed`` or ``mission`` units (module docstring).

    Returns (task_feat [1+W, 2K+5], agent_feat [N, K+6], mask [1+W], nodes [1+W], decider row):
    ``nodes`` maps task rows to state nodes (row 0 = depot = node 0).
    """
    a = state.agent if a is None else a
    sc, cap_unit = _units(state, scale)
    mask = state.mask()  # [1+M]
    pos = state.positions()  # [A, 2]
    here = pos[a]  # [2]
    M, A = state.M, state.A
    # the window is chosen first; features are then built for its rows only (the values are those
    # of _observe_full at the same rows). Tasks not yet released are not observed at all (as if
    # they did not exist).
    tasks = np.flatnonzero(state.status != UNRELEASED) if state.n_hidden else None  # [M'] known tasks
    n_known = M if tasks is None else len(tasks)
    if n_known > max_tasks:
        loc = state.inst.task_locations if tasks is None else state.inst.task_locations[tasks]  # [M', 2]
        ok = mask[1:] if tasks is None else mask[tasks + 1]  # [M']
        keep = _nearest(loc - here, max_tasks, first=ok)  # [W] ascending: admissible first, then nearest
        tasks = keep if tasks is None else tasks[keep]
    elif tasks is None:
        tasks = np.arange(M)
    nodes = np.concatenate([[0], tasks + 1])  # [1+W]
    tf = _task_rows(state, a, here, tasks, sc, cap_unit)  # [1+W, Ft]
    if scale == "mission+coalition":
        tf = np.concatenate([tf, _coalition_column(state, tasks, sc, pos)[:, None]], axis=1)  # [1+W, Ft + 1]
    if A > max_agents:
        agents = _nearest(pos - here, max_agents, me=a)  # [N] ascending: the decider itself always
        row = int(np.flatnonzero(agents == a)[0])
    else:
        agents, row = np.arange(A), a
    af = _agent_rows(state, agents, pos[agents], here, sc, cap_unit)  # [N, Fa]
    return tf, af, mask[nodes], nodes, row


def _nearest(rel: np.ndarray, k: int, first: np.ndarray | None = None, me: int | None = None) -> np.ndarray:
    """Rows (ascending) of the window: the k smallest keys, ties to the lower row, where the key of
    row i is its distance ``np.hypot(*rel[i])`` (rel [n, 2]), plus 1e6 where ``first`` [n] is
    False, and -1 at row ``me``: ``np.sort(np.argsort(key, kind="stable")[:k])``.

    The distances of all rows are first taken as sqrt(x^2 + y^2), within a few ulps of np.hypot
    (three times faster), which leaves the k smallest and the rows within 1e-6 of them; the exact
    keys of those few rows then decide."""
    n = len(rel)
    if n <= k:
        return np.arange(n)
    x, y = rel[:, 0], rel[:, 1]
    approx = np.sqrt(x * x + y * y)  # [n]
    if first is not None:
        approx = np.where(first, approx, approx + 1e6)
    if me is not None:
        approx[me] = -1.0
    thr = np.partition(approx, k - 1)[k - 1]
    cand = np.flatnonzero(approx <= thr + (1e-6 + 1e-9 * abs(thr)))  # [C] >= k rows, the window among them
    key = np.hypot(x[cand], y[cand])  # [C]
    if first is not None:
        key = np.where(first[cand], key, key + 1e6)
    if me is not None:
        key[cand == me] = -1.0
    return cand[_smallest(key, k)]


def _smallest(key: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k smallest keys, ties to the lower index, in ascending index order: the
    same set as ``np.sort(np.argsort(key, kind="stable")[:k])``, in linear time."""
    if len(key) <= k:
        return np.arange(len(key))
    thr = np.partition(key, k - 1)[k - 1]  # the k-th smallest key
    sel = key < thr  # fewer than k
    sel[np.flatnonzero(key == thr)[:k - int(sel.sum())]] = True  # the ties, lowest indices first
    return np.flatnonzero(sel)


def _units(state: MissionState, scale: str) -> tuple[Scales, np.ndarray | None]:
    """(units, capability unit [K] or None for ``fixed``) of an observation of ``state``."""
    if state.K > K_MAX:
        raise ValueError(f"the policy handles at most {K_MAX} skills, instance has {state.K}")
    if scale == "fixed":
        return FIXED, None
    if scale in ("mission", "mission+coalition"):
        sc = mission_scales(state)
        return sc, sc.cap  # [K]
    raise ValueError(f"scale: expected one of {', '.join(SCALES)}, got {scale!r}")


def _task_rows(state: MissionState, a: int, me: np.ndarray, tasks: np.ndarray, sc: Scales,
               cap_unit: np.ndarray | None) -> np.ndarray:
    """task_feat [1+W, 2K+5] of decider a at ``me`` [2]: its depot row, then tasks [W] (ids)."""
    inst, K = state.inst, state.K
    inv_t, inv_l = 1.0 / sc.time, 1.0 / sc.length
    v = inst.velocity
    tf = np.zeros((len(tasks) + 1, TASK_FEATURES), dtype=np.float32)
    rel = inst.task_locations[tasks] - me  # [W, 2]
    if cap_unit is None:
        tf[1:, :K] = state.rem[tasks] * REQ_SCALE
        tf[1:, K_MAX:K_MAX + K] = state.req[tasks] * REQ_SCALE
    else:
        tf[1:, :K] = state.rem[tasks] * (REQ_SCALE / cap_unit)
        tf[1:, K_MAX:K_MAX + K] = state.req[tasks] * (REQ_SCALE / cap_unit)
    tf[1:, 2 * K_MAX:2 * K_MAX + 2] = rel * inv_l
    tf[1:, 2 * K_MAX + 2] = inst.durations[tasks] * (inv_t * 2)
    tf[1:, 2 * K_MAX + 3] = np.hypot(rel[:, 0], rel[:, 1]) * (inv_t / v)
    tf[1:, 2 * K_MAX + 4] = state.status[tasks] == DONE
    drel = inst.depots[a] - me  # [2]
    tf[0, 2 * K_MAX:2 * K_MAX + 2] = drel * inv_l
    tf[0, 2 * K_MAX + 3] = np.hypot(drel[0], drel[1]) * (inv_t / v)
    return tf


def _coalition_column(state: MissionState, tasks: np.ndarray, sc: Scales,
                      pos: np.ndarray | None = None) -> np.ndarray:
    """[1+W] greedy-coalition's estimate of when each task's coalition can start if the decider
    joins now, from now, in observation time units, clipped at COALITION_CAP (also a coalition that
    cannot be completed); 0 for the depot row and the tasks it cannot take. ``pos``: the robots'
    positions now [A, 2], if at hand."""
    from ..baselines import CoalitionGreedy

    col = np.zeros(len(tasks) + 1, dtype=np.float32)
    cand, start, _ = CoalitionGreedy().estimates(state, tasks, pos)  # [C]
    if len(cand):
        row = np.searchsorted(tasks, cand)  # tasks is ascending
        col[1 + row] = np.minimum((start - state.clock) / sc.time, COALITION_CAP)
    return col


def _agent_rows(state: MissionState, agents: np.ndarray, pos: np.ndarray, me: np.ndarray, sc: Scales,
                cap_unit: np.ndarray | None) -> np.ndarray:
    """agent_feat [N, K+6] of agents [N] (ids) at ``pos`` [N, 2], seen from ``me`` [2]."""
    K, t = state.K, state.clock
    inv_t, inv_l = 1.0 / sc.time, 1.0 / sc.length
    af = np.zeros((len(agents), AGENT_FEATURES), dtype=np.float32)
    cap = state.cap[agents]  # [N, K]
    mode = state.mode[agents]  # [N]
    arrive = state.arrive[agents]  # [N]
    af[:, :K] = cap if cap_unit is None else cap / cap_unit
    af[mode == LOST, :K] = 0.0  # a lost robot contributes nothing any more
    on_task = mode == TASK  # [N]
    tgt = np.where(on_task, state.target[agents], 0)  # [N]
    tstat = np.where(on_task, state.status[tgt], -1)  # [N]
    running = tstat == IN_PROGRESS  # [N]
    fin = np.where(running, state.finish[tgt], t)  # [N]
    arrived = arrive <= t  # [N]
    af[:, K_MAX] = np.maximum(fin - t, 0.0) * inv_t
    af[:, K_MAX + 1] = np.maximum(arrive - t, 0.0) * inv_t
    waiting = on_task & arrived & ((tstat == OPEN) | (running & (state.start[tgt] > t)))
    af[:, K_MAX + 2] = np.where(waiting, t - arrive, 0.0) * inv_t
    af[:, K_MAX + 3:K_MAX + 5] = (pos - me) * inv_l
    af[:, K_MAX + 5] = running
    return af


def _observe_full(state: MissionState, a: int, pos: np.ndarray,
                  scale: str = "fixed") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(task_feat [1+M, 2K+5], agent_feat [A, K+6], action mask [1+M]) for decider a; pos [A, 2]:
    every task and agent (no window)."""
    sc, cap_unit = _units(state, scale)
    tf = _task_rows(state, a, pos[a], np.arange(state.M), sc, cap_unit)
    af = _agent_rows(state, np.arange(state.A), pos, pos[a], sc, cap_unit)
    return tf, af, state.mask()


def batch_observations(states: list[MissionState], max_tasks: int = MAX_TASKS, max_agents: int = MAX_AGENTS,
                       scale: str = "fixed"):
    """Stack (and pad) the current observations of several states into one batch.

    Returns (batch dict of tensors, per-state node maps [1+W])."""
    obs = [observe(s, None, max_tasks, max_agents, scale) for s in states]
    return collate([o[:3] for o in obs], [o[4] for o in obs]), [o[3] for o in obs]


def collate(obs: list[tuple[np.ndarray, np.ndarray, np.ndarray]], deciders: list[int]) -> dict[str, torch.Tensor]:
    B = len(obs)
    T = max(o[0].shape[0] for o in obs)
    N = max(o[1].shape[0] for o in obs)
    tasks = np.zeros((B, T, obs[0][0].shape[1]), dtype=np.float32)  # [B, T, Ft]
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


def concat_batches(batches: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Batches of :func:`collate` joined along the batch dimension, each padded to the widest
    (zero features, invalid rows, inadmissible actions: the padding changes no valid row's output)."""
    T = max(b["tasks"].shape[1] for b in batches)
    N = max(b["agents"].shape[1] for b in batches)

    def pad(x: torch.Tensor, width: int) -> torch.Tensor:  # [B, L, ...] -> [B, width, ...]
        if x.shape[1] == width:
            return x
        return torch.cat([x, x.new_zeros((x.shape[0], width - x.shape[1], *x.shape[2:]))], dim=1)

    widths = {"tasks": T, "agents": N, "task_valid": T, "agent_valid": N, "action_mask": T}
    return {k: torch.cat([pad(b[k], widths[k]) if k in widths else b[k] for b in batches])
            for k in batches[0]}
