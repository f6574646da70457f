"""Planning from a mid-mission state: the solver's schedule for the rest of a mission.

The anytime solver (:mod:`hmrta.solvers.cpsat`) plans from mission start. This module plans from
any :class:`~hmrta.core.MissionState` with a pending decision: robots part-way through their routes,
tasks in progress, open tasks partly staffed. It is the teacher of the solver-labelled DAgger
(``pretrain.dagger_teacher: solver``, docs/training.md): the policy drives a mission to some state,
this plans the rest, and the plan's routes label every decision from there on.

**The residual problem** (:class:`StateDecoder`), in the state machine's own times:

* a free or waiting robot leaves from where it stands at the time it became free (the state
  machine back-dates its departure; ``Rules.backdate``);
* a robot working on a task in progress is next free at the task's finish, at the task;
* a robot committed to an open task (travelling or waiting there) is held by it: it joins nothing
  else before that task starts, and the task's coalition is its committed members plus whoever
  the plan adds, starting when the last of them arrives;
* a robot going home or parked that is queued to decide at this instant leaves from where it is
  now; one that is not is left out of the plan and arrives home when its leg ends (the state
  machine offers it a decision again at the next completion, a time the plan itself decides);
* done, cancelled, in-progress and unreleased tasks are not planned.

A task order decodes into a schedule as in :class:`hmrta.solvers.listsched.SerialDecoder`: each
task in turn gets the earliest-assembling coalition of the robots not held elsewhere (sorted by
arrival, the smallest satisfying prefix, then unneeded added members pruned, latest first). Its
makespan is the time the last robot is home, bit for bit the state machine's arithmetic, so a
plan's routes followed in the state machine from the state reproduce its makespan exactly (tested)
wherever every planned choice is admissible.

**The search** (:func:`plan_from_state`): greedy-coalition finishes a copy of the mission (its task
start order is the first order, its makespan the incumbent), then simulated annealing over task
orders (:func:`hmrta.solvers.listsched.anneal`), a fixed number of decodes (so a plan is a
deterministic function of the state and the seed). The plan is the better of the two: never worse
than greedy-coalition from the same state.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..core import EMPTY, FREE, HOME, IN_PROGRESS, LOST, OPEN, TASK, WAIT, MissionState
from .listsched import anneal, prune_latest

INF = math.inf


@dataclass
class Plan:
    """The rest of a mission: ``routes[a]`` are the tasks robot a still commits to, in order (a
    robot held by an open task starts its route after it); None when the plan is
    greedy-coalition's own continuation (``source``). ``makespan``: when the last robot is home."""

    routes: list[list[int]] | None
    makespan: float
    source: str  # "greedy-coalition" or "anneal"
    greedy_coalition: float  # greedy-coalition's makespan from the same state


class StateDecoder:
    """Decodes task orders from a mission state (module docstring). ``tasks``: the tasks to plan.
    :meth:`run` follows :meth:`hmrta.solvers.listsched.SerialDecoder.run`'s protocol."""

    def __init__(self, st: MissionState):
        if st.done or st.agent is None:
            raise ValueError("plan from state: the mission has no pending decision")
        inst = st.inst
        M, A, K = st.M, st.A, st.K
        self.A, self.K = A, K
        v = inst.velocity
        status = st.status
        self.tasks = [m for m in range(M) if status[m] in (EMPTY, OPEN)]
        loc = [(float(p[0]), float(p[1])) for p in inst.task_locations]
        home = [(float(p[0]), float(p[1])) for p in st.inst.depots]
        clock = float(st.clock)
        queued = set(st.queue) | {st.agent}
        # per robot: ready time, start point, the open task holding it (-1: none) and its arrival there
        ready, start, hold, arrival, ret0 = [], [], [-1] * A, [0.0] * A, [None] * A
        for a in range(A):
            mode = int(st.mode[a])
            if mode in (FREE, WAIT):
                t = float(st.free_since[a]) if st.rules.backdate else clock
                p = st.position(a)
            elif mode == TASK:
                m = int(st.target[a])
                if status[m] == IN_PROGRESS:
                    t, p = float(st.finish[m]), loc[m]
                else:  # committed to an open task: held by it
                    t, p = INF, loc[m]
                    hold[a], arrival[a] = m, float(st.arrive[a])
            elif mode == HOME:  # offered now if queued at this instant; else not planned
                t = clock if a in queued else INF
                p = st.position(a) if a in queued else home[a]
                ret0[a] = float(st.arrive[a])  # unused: its leg home ends then
            else:  # LOST: plans nothing, is waited for by nothing
                t, p = INF, home[a]
                ret0[a] = -INF
            ready.append(t)
            start.append((float(p[0]), float(p[1])))
        # nodes: tasks 0..M-1, then robot a's start point M + a; columns: tasks, then robot a's home M + a
        self.T = [[math.hypot(q[0] - s[0], q[1] - s[1]) / v for q in loc] for s in loc]  # [M][M]
        self.T_home = [[math.hypot(home[a][0] - s[0], home[a][1] - s[1]) / v for a in range(A)] for s in loc]  # [M][A]
        self.T_start = [[math.hypot(q[0] - s[0], q[1] - s[1]) / v for q in loc] for s in start]  # [A][M]
        start_home = [math.hypot(home[a][0] - start[a][0], home[a][1] - start[a][1]) / v for a in range(A)]
        self.dur = [float(d) for d in inst.durations]
        cap = st.cap.tolist()  # [A][K] (0/1 coverage for binary requirements)
        self.cap = cap
        self.need = [(st.rem[m] - st._tol).tolist() for m in range(M)]  # [M][K] what the plan must still add (less the cover tolerance)
        self.needk = [[k for k in range(K) if self.need[m][k] > 0] for m in range(M)]
        avail = [a for a in range(A) if st.mode[a] != LOST]
        self.cand = [[a for a in avail if any(cap[a][k] > 0 for k in self.needk[m])] for m in range(M)]
        self.pre = [[] for _ in range(M)]  # [M] the robots committed to each open task
        for a in range(A):
            if hold[a] >= 0:
                self.pre[hold[a]].append(a)
        self.ready0, self.hold0, self.arrival = ready, hold, arrival
        self.ret0 = [r if r is not None else (ready[a] + start_home[a] if ready[a] < INF else None)
                     for a, r in enumerate(ret0)]
        self.lost = [st.mode[a] == LOST for a in range(A)]

    def run(self, order, p: int, snap, record: bool = True, routes_out: bool = False):
        """Decode ``order[p:]`` from ``snap`` (None: the state). Returns (makespan, snapshots before
        each position p.. if ``record``, routes or None); makespan INF where a task cannot be staffed
        (the robots it needs are held by open tasks later in the order)."""
        A, T, T_start, cap, dur = self.A, self.T, self.T_start, self.cap, self.dur
        if snap is None:
            ready, pos, hold = list(self.ready0), [-1] * A, list(self.hold0)  # pos -1: the start point
        else:
            ready, pos, hold = list(snap[0]), list(snap[1]), list(snap[2])
        snaps = [] if record else None
        routes = [[] for _ in range(A)] if routes_out else None
        for idx in range(p, len(order)):
            if record:
                snaps.append((ready[:], pos[:], hold[:]))
            m = order[idx]
            need, ks = self.need[m], self.needk[m]
            arr = sorted([(ready[a] + (T_start[a][m] if pos[a] < 0 else T[pos[a]][m]), a)
                          for a in self.cand[m] if hold[a] < 0])
            have = [0.0] * self.K
            members = []
            ok = False
            for t, a in arr:
                members.append((t, a))
                ca = cap[a]
                for k in ks:
                    have[k] += ca[k]
                if all(have[k] >= need[k] for k in ks):
                    ok = True
                    break
            if not ok:
                return INF, snaps, routes
            if len(members) > 1:  # unneeded added members out, latest arrivals first
                members = prune_latest(members, have, need, ks, cap)
            t0 = max(t for t, _ in members)
            for a in self.pre[m]:
                t0 = max(t0, self.arrival[a])
                hold[a] = -1
            fin = t0 + dur[m]
            for a in self.pre[m]:
                ready[a], pos[a] = fin, m
            for _, a in members:
                ready[a], pos[a] = fin, m
                if routes_out:
                    routes[a].append(m)
        ms = -INF
        for a in range(A):
            if self.lost[a]:
                continue
            v = self.ret0[a] if pos[a] < 0 else ready[a] + self.T_home[pos[a]][a]
            if v is None or hold[a] >= 0:
                return INF, snaps, routes  # held by a task the order left out
            if v > ms:
                ms = v
        return ms, snaps, routes

    def decode(self, order, routes_out: bool = False):
        ms, _, routes = self.run(order, 0, None, record=False, routes_out=routes_out)
        return (ms, routes) if routes_out else ms


def greedy_coalition_continuation(st: MissionState) -> tuple[float, list[int]]:
    """(makespan, task start order) of greedy-coalition finishing a copy of ``st`` (INF if it fails)."""
    from ..baselines import CoalitionGreedy

    c = st.clone()
    decide = CoalitionGreedy()
    while not c.done:
        c.step(decide(c))
    todo = [m for m in range(st.M) if st.status[m] in (EMPTY, OPEN)]
    order = sorted(todo, key=lambda m: (c.start[m] if math.isfinite(c.start[m]) else INF, m))
    return (c.makespan if c.success else INF), order


def plan_from_state(st: MissionState, evals: int = 2000, seed: int = 0, seconds: float = 60.0) -> Plan:
    """The rest of ``st``'s mission (module docstring): greedy-coalition's continuation, improved by
    annealing over task orders (``evals`` decodes, at most ``seconds``) where that finds a shorter
    schedule. Within the time limit the plan is a deterministic function of (state, evals, seed)."""
    gc_ms, order = greedy_coalition_continuation(st)
    dec = StateDecoder(st)
    ms, best = dec.decode(order), order
    if len(order) >= 2 and evals > 0 and math.isfinite(ms):
        ms, best = anneal(st.inst, order, seed, seconds, max_evals=evals, decoder=dec)
    if ms < gc_ms - 1e-9:
        ms, routes = dec.decode(best, routes_out=True)
        return Plan(routes, ms, "anneal", gc_ms)
    return Plan(None, gc_ms, "greedy-coalition", gc_ms)
