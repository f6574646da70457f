"""The mission state machine (SPEC §3) shared by the simulator, the training environment and the
ROS task board.

Event driven, no time step. The machine holds one *current decider* at a time; a driver (a
policy, the batched trainer, the task board) reads :meth:`MissionState.mask` and calls
:meth:`MissionState.step` with the chosen node (0 = own depot, 1 + m = task m). ``step`` applies
one commitment and then advances: later deciders of the same instant, then task completions in
time order, until a decider with an admissible task exists or the episode ends.

The environment owns feasibility. Besides the SPEC's ability mask it applies (see
docs/semantics.md):

* **max-open-task rule** (``Rules.max_open``): with that many open tasks, empty tasks are masked.
  ``max_open="team"`` scales the cap with the mission (:func:`team_cap`): about half the number of
  coalitions the team can field at once.
* **deadlock-avoidance mask** (``Rules.safety``, default on; project choice): a commitment is
  admissible only if afterwards the open tasks can still all be completed, one after another, by
  the agents not waiting at open tasks (a banker's-algorithm check). Together with the stall rule
  below this guarantees that every feasible instance is completed whatever the policy picks.
* **postponement** (flashforward): a decider with no admissible task is moved behind the other
  deciders of its instant; still blocked, it waits in place and is retried after the deciders of
  later instants. With ``Rules.backdate`` (default) its departure is back-dated to the instant it
  first became free, so the schedule is exactly what route evaluation of its routes gives (it
  never idles where leaving at once is as good). Set it False for real-time execution, where a
  departure cannot lie in the past.
* an agent with no empty/open task left to join goes home; agents parked at their depot (or on
  the way there) are offered a decision again after every completion event. When nothing is
  pending any more (a *stall*), parked and waiting agents are offered the tasks with the depot
  masked; if none of them can move, the episode ends in deadlock.
"""
from __future__ import annotations

import copy
import heapq
import math
import numbers
import random
from dataclasses import dataclass
from typing import Any

import numpy as np

from .instance import Instance

# agent modes (LOST: removed from the mission by drop_agent, e.g. a robot that stopped reporting)
FREE, TASK, HOME, WAIT, LOST = 0, 1, 2, 3, 4
MODE_NAMES = ("free", "task", "home", "wait", "lost")
# task status (CANCELLED: no longer satisfiable after drop_agent)
EMPTY, OPEN, IN_PROGRESS, DONE, CANCELLED = 0, 1, 2, 3, 4
STATUS_NAMES = ("empty", "open", "in_progress", "done", "cancelled")


def team_cap(inst: Instance) -> int:
    """The ``max_open="team"`` cap of a mission: max(1, round(A / 2c)), where c, the mean coalition
    size, is the mean over tasks of (requirement sum) / (mean over agents of trait sum). A / c is
    about how many coalitions the team can field at once. Measured with greedy-coalition
    (docs/semantics.md): the best fixed cap grows with A / c, from 1 on SA-AT (A / c ~ 3) to 6 on
    MA-AT (50,5,50,5) (A / c ~ 26), and this rule is within 2.5% of the best fixed cap on every
    row tried."""
    req = np.asarray(inst.requirements, dtype=np.float64)  # [M, K]
    traits = np.asarray(inst.traits, dtype=np.float64)  # [A, K]
    c = float((req.sum(1) / max(traits.sum(1).mean(), 1e-9)).mean()) if len(req) else 0.0
    return max(1, int(round(inst.n_agents / (2 * c)))) if c > 0 else 1


@dataclass(frozen=True)
class Rules:
    max_open: int | str | None = None  # max-open-task rule (None: no limit; "team": team_cap per mission)
    safety: bool = True  # deadlock-avoidance mask
    backdate: bool = True  # flashforward: a postponed agent's departure is back-dated (see module doc)
    t_max: float = math.inf  # episode fails when an event lies beyond this time

    def __post_init__(self):
        m = self.max_open
        if not (m is None or m == "team" or (isinstance(m, numbers.Integral) and not isinstance(m, bool) and m >= 1)):
            raise ValueError(f"max_open: expected a positive integer, null (no limit) or 'team', got {m!r}")

    def open_cap(self, inst: Instance) -> int | None:
        """The max-open-task cap this mission runs under (None: no limit)."""
        return team_cap(inst) if self.max_open == "team" else self.max_open

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Rules":
        """Inverse of :meth:`to_dict`; missing keys take their defaults (configs name only max_open
        and safety). Raises ValueError for an invalid max_open."""
        t_max = d.get("t_max")
        return cls(max_open=d.get("max_open"), safety=d.get("safety", True), backdate=d.get("backdate", True),
                   t_max=math.inf if t_max is None else t_max)

    def to_dict(self) -> dict[str, Any]:
        return {"max_open": self.max_open, "safety": self.safety, "backdate": self.backdate,
                "t_max": None if math.isinf(self.t_max) else self.t_max}


# ---------------------------------------------------------------------------------------------
# the hmrta-state/1 format (MissionState.snapshot; docs/schemas/hmrta-state-1.schema.json)
# ---------------------------------------------------------------------------------------------
STATE_FORMAT = "hmrta-state/1"
RULE_KEYS = ("max_open", "safety", "backdate", "t_max")


class SnapshotError(ValueError):
    """A state snapshot that cannot be restored: unknown format or version, or a field that is
    missing, mistyped or does not fit the instance (one line, names the field)."""


def parse_rules(d: Any, where: str = "rules") -> Rules:
    """Strict reading of a :meth:`Rules.to_dict` mapping received from outside (a snapshot, a
    mission message). All four rules must be present; an unknown rule, a mistyped value or an
    invalid ``max_open`` is a ValueError naming the field (``where.key``). Unknown rules are
    refused rather than ignored: a rule this build does not implement would change the semantics."""
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a mapping with keys {list(RULE_KEYS)}, got {_short(d)}")
    unknown = sorted(str(k) for k in d if k not in RULE_KEYS)
    if unknown:
        raise ValueError(f"{where}.{unknown[0]}: unknown rule (expected {', '.join(RULE_KEYS)})")
    missing = [k for k in RULE_KEYS if k not in d]
    if missing:
        raise ValueError(f"{where}: missing rule {missing[0]!r}")
    for k in ("safety", "backdate"):
        if not isinstance(d[k], bool):
            raise ValueError(f"{where}.{k}: expected true or false, got {_short(d[k])}")
    t = d["t_max"]
    if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float)) or math.isnan(t)):
        raise ValueError(f"{where}.t_max: expected a number or null (no limit), got {_short(t)}")
    try:
        return Rules.from_dict(d)
    except ValueError as e:
        raise ValueError(f"{where}.{e}") from None


def _short(v: Any, n: int = 60) -> str:
    r = repr(v)
    return r if len(r) <= n else r[: n - 3] + "..."


class MissionState:
    """Exact event-driven state of one mission (SPEC §3). See the module docstring."""

    def __init__(self, inst: Instance, seed: int = 0, rules: Rules = Rules()):
        self.inst = inst
        self.rules = rules
        self.open_cap = rules.open_cap(inst)  # max-open-task cap of this mission (None: no limit)
        self.rng = random.Random(seed)
        self.seed = seed
        A, M, K = inst.n_agents, inst.n_tasks, inst.skills
        self.A, self.M, self.K = A, M, K
        self.additive = inst.additive
        # capability used for requirement arithmetic: AT traits, BT skill coverage (0/1)
        self.cap = np.array(inst.traits if self.additive else inst.traits > 0, dtype=np.float64)  # [A, K]
        self.req = np.array(inst.requirements if self.additive else inst.requirements > 0, dtype=np.float64)  # [M, K]
        self.rem = self.req.copy()  # [M, K] remaining requirement (0 once in progress / done)
        self.status = np.zeros(M, dtype=np.int64)  # [M]
        self.members: list[list[int]] = [[] for _ in range(M)]
        self.start = np.full(M, np.nan)  # [M]
        self.finish = np.full(M, np.nan)  # [M]
        self.held = np.zeros((M, K))  # [M, K] capability of the members committed to each task
        # agents
        self.mode = np.full(A, FREE, dtype=np.int64)  # [A]
        self.target = np.full(A, -1, dtype=np.int64)  # [A] task id or -1 (depot / none)
        self.from_pos = np.array(inst.depots, dtype=np.float64)  # [A, 2] where the current leg began
        self.to_pos = self.from_pos.copy()  # [A, 2] where the current leg ends
        self.depart = np.zeros(A)  # [A] departure time of the current leg
        self.arrive = np.zeros(A)  # [A] arrival time of the current leg
        self.free_since = np.zeros(A)  # [A] when a FREE / WAIT agent became free at its position
        self.wait_total = np.zeros(A)  # [A] time waited at tasks for the coalition (AWT)
        self.routes: list[list[int]] = [[] for _ in range(A)]
        self.depot_stops = np.zeros(A, dtype=np.int64)  # [A] returns home while work remained
        self.pool = self.cap.sum(0)  # [K] capability of agents not waiting at an open task
        self.n_open = 0
        self.n_done = 0
        self.n_cancelled = 0  # tasks closed by drop_agent (no longer satisfiable)
        self.clock = 0.0
        self.events: list[tuple[float, int, int]] = []  # (finish, seq, task)
        self._seq = 0
        self.queue: list[int] = []  # deciders of this instant, next first (stored reversed)
        self._deferred: set[int] = set()  # postponed once at this instant
        self._stall = False
        self._commits = 0
        self._stall_commits = -1
        self.decisions = 0  # policy decisions taken (steps)
        self.done = False
        self.success = False
        self.failure: str | None = None
        self.agent: int | None = None
        self._mask: np.ndarray | None = None
        order = list(range(A))
        self.rng.shuffle(order)
        self.queue = order[::-1]
        self._advance()

    # ------------------------------------------------------------------------------------------
    # queries
    # ------------------------------------------------------------------------------------------
    def position(self, a: int, t: float | None = None) -> np.ndarray:
        """Position of agent a at time t (default: now), moving in a straight line along its leg."""
        t = self.clock if t is None else t
        d0, d1 = self.depart[a], self.arrive[a]
        if t >= d1 or d1 <= d0:
            return self.to_pos[a].copy()
        if t <= d0:
            return self.from_pos[a].copy()
        f = (t - d0) / (d1 - d0)
        return self.from_pos[a] + (self.to_pos[a] - self.from_pos[a]) * f

    def positions(self) -> np.ndarray:  # [A, 2]
        span = self.arrive - self.depart  # [A]
        f = (self.clock - self.depart) / np.where(span > 0, span, 1.0)  # [A]
        moving = (span > 0) & (f > 0) & (f < 1)  # [A] strictly inside the leg (as in position())
        mid = self.from_pos + (self.to_pos - self.from_pos) * f[:, None]  # [A, 2]
        ended = (self.clock >= self.arrive) | (span <= 0)  # [A]
        return np.where(moving[:, None], mid, np.where(ended[:, None], self.to_pos, self.from_pos))

    def mask(self) -> np.ndarray:
        """Admissible nodes for the current decider: bool [1 + M], index 0 = depot."""
        if self._mask is None:
            raise RuntimeError("no decision is pending (episode done)")
        return self._mask

    def _task_mask(self, a: int) -> np.ndarray:
        """bool [M]: tasks agent a may join now (ability, max-open and safety rules)."""
        ca = self.cap[a]  # [K]
        contrib = (np.minimum(self.rem, ca) > 0).any(1)  # [M] reduces a positive remaining entry
        if self.open_cap is not None and self.n_open >= self.open_cap:
            contrib &= self.status == OPEN
        if self.rules.safety and contrib.any():
            contrib = self._safe(a, contrib)
        return contrib

    # ---- deadlock avoidance (banker's algorithm over open tasks) -------------------------------
    def _fits(self, rem: np.ndarray, pool: np.ndarray) -> np.ndarray:
        """bool [...]: remaining requirement rows that `pool` could satisfy alone."""
        return (rem <= (pool if self.additive else (pool > 0))).all(-1)

    def _closure(self, rems: np.ndarray, helds: np.ndarray, pool: np.ndarray):
        """Complete open tasks greedily with the pool; returns (all done, final pool, alive [O])."""
        alive = np.ones(len(rems), dtype=bool)  # [O]
        while alive.any():
            ok = alive & self._fits(rems, pool)  # [O]
            if not ok.any():
                break
            pool = pool + helds[ok].sum(0)
            alive &= ~ok
        return not alive.any(), pool, alive

    def _safe(self, a: int, cand: np.ndarray) -> np.ndarray:
        ca = self.cap[a]
        out = cand.copy()
        open_ids = np.flatnonzero(self.status == OPEN)  # [O]
        rems, helds = self.rem[open_ids], self.held[open_ids]  # [O, K]
        pool = self.pool  # a is in the pool (it is not waiting at an open task)
        # empty candidates: a opens X with remaining r_X = max(q_X - ca, 0), leaving the pool
        empty = np.flatnonzero(cand & (self.status == EMPTY))
        if len(empty):
            r = np.maximum(self.rem[empty] - ca, 0.0)  # [E, K]
            instant = (r <= 0).all(1)  # [E] a alone satisfies X: state unchanged, safe
            all_done, p_stuck, alive = self._closure(rems, helds, pool - ca)
            ok = self._fits(r, p_stuck)  # [E]
            if not all_done:
                ok &= self._closure(rems[alive], helds[alive], p_stuck + ca)[0]
            out[empty] = instant | ok
        # open candidates: a joins X
        for i, m in enumerate(open_ids):
            if not cand[m]:
                continue
            r = np.maximum(rems[i] - ca, 0.0)
            if (r <= 0).all():  # X starts: its members are released after it finishes
                keep = np.arange(len(open_ids)) != i
                out[m] = self._closure(rems[keep], helds[keep], pool + helds[i])[0]
            else:
                rems2, helds2 = rems.copy(), helds.copy()
                rems2[i], helds2[i] = r, helds[i] + ca
                out[m] = self._closure(rems2, helds2, pool - ca)[0]
        return out

    # ------------------------------------------------------------------------------------------
    # transitions
    # ------------------------------------------------------------------------------------------
    def step(self, node: int) -> None:
        """Apply the current decider's choice (0 = depot, 1 + m = task m) and advance."""
        a = self.agent
        if a is None or self._mask is None:
            raise RuntimeError("no decision is pending (episode done)")
        if not (0 <= node < len(self._mask)) or not self._mask[node]:
            raise ValueError(f"agent {a}: node {node} is not admissible now")
        self.decisions += 1
        self.commit(a, node)
        self._advance()

    def commit(self, a: int, node: int) -> None:
        """One commitment: agent a departs for its depot (node 0) or task node - 1 (SPEC §3, rule 2)."""
        mode = self.mode[a]
        backdate = self.rules.backdate and mode in (FREE, WAIT)
        t_dep = self.free_since[a] if backdate else self.clock
        here = self.position(a)
        inst = self.inst
        self._mask = None
        self.agent = None
        if node == 0:
            if mode == HOME:
                return  # stays parked (or keeps going home)
            self._leg(a, here, inst.depots[a], t_dep)
            self.mode[a], self.target[a] = HOME, -1
            if not self._all_claimed():
                self.depot_stops[a] += 1
            return
        m = node - 1
        self._commits += 1
        self._leg(a, here, inst.task_locations[m], t_dep)
        self.mode[a], self.target[a] = TASK, m
        self.members[m].append(a)
        self.routes[a].append(m)
        self.held[m] += self.cap[a]
        self.rem[m] = np.maximum(self.rem[m] - self.cap[a], 0.0)
        was_open = self.status[m] == OPEN
        if (self.rem[m] <= 0).all():  # coalition satisfies m: in progress (SPEC §3, rule 3)
            self.status[m] = IN_PROGRESS
            if was_open:
                self.n_open -= 1
                self.pool += self.held[m] - self.cap[a]
            mem = self.members[m]
            start = float(self.arrive[mem].max())
            self.start[m] = start
            self.finish[m] = start + float(inst.durations[m])
            self._seq += 1
            heapq.heappush(self.events, (self.finish[m], self._seq, m))
        else:
            if not was_open:
                self.status[m] = OPEN
                self.n_open += 1
            self.pool -= self.cap[a]
        if self._nothing_to_join():
            for b in np.flatnonzero(self.mode == WAIT):  # nothing left to join: waiting agents go home
                self.commit(int(b), 0)

    def _leg(self, a: int, frm: np.ndarray, to: np.ndarray, t_dep: float) -> None:
        self.from_pos[a] = frm
        self.to_pos[a] = to
        self.depart[a] = t_dep
        self.arrive[a] = t_dep + math.hypot(to[0] - frm[0], to[1] - frm[1]) / self.inst.velocity

    def _nothing_to_join(self) -> bool:
        """No task is empty or open: every task is in progress, done or cancelled."""
        return self.n_open == 0 and not (self.status == EMPTY).any()

    def _all_claimed(self) -> bool:
        """Every task is done, cancelled or in progress (nothing will need a parked agent)."""
        return self.n_done + self.n_cancelled + int((self.status == IN_PROGRESS).sum()) == self.M

    def complete(self, m: int) -> list[int]:
        """One completion: task m finishes; its members become free there. Returns the members."""
        self.status[m] = DONE
        self.n_done += 1
        mem = self.members[m]
        fin, st = self.finish[m], self.start[m]
        for a in mem:
            self.wait_total[a] += st - self.arrive[a]
            self.mode[a], self.target[a] = FREE, -1
            self.from_pos[a] = self.to_pos[a]
            self.depart[a] = self.arrive[a] = fin
            self.free_since[a] = fin
        return list(mem)

    def _advance(self) -> None:
        """Find the next decider with an admissible task, processing events as needed."""
        while True:
            while self.queue:
                a = self.queue.pop()
                mode = self.mode[a]
                if self._nothing_to_join():
                    # nothing left to join: go home for good
                    if mode in (FREE, WAIT):
                        self.commit(a, 0)
                    continue
                tm = self._task_mask(a)
                if tm.any():
                    mask = np.empty(self.M + 1, dtype=bool)
                    mask[0] = not self._stall
                    mask[1:] = tm
                    self.agent, self._mask = a, mask
                    return
                if mode == HOME:
                    continue  # stays parked
                if mode == FREE and a not in self._deferred and self.queue:
                    self._deferred.add(a)  # flashforward: let the others of this instant go first
                    self.queue.insert(0, a)
                    continue
                self.mode[a] = WAIT
            # no decider left at this instant
            self._deferred.clear()
            if self.n_done + self.n_cancelled == self.M:
                self._finish_episode()
                return
            if self.events:
                t = max(self.events[0][0], self.clock)
                if t > self.rules.t_max:
                    self._fail(f"time limit {self.rules.t_max} exceeded")
                    return
                self.clock = t
                freed: list[int] = []
                while self.events and self.events[0][0] <= t:
                    _, _, m = heapq.heappop(self.events)
                    freed += sorted(self.complete(m))
                self._stall = False
                self._requeue(freed)
                continue
            # stall: nothing in progress; offer parked and waiting agents the tasks, depot masked
            if self._stall and self._commits == self._stall_commits:
                self._fail("deadlock: open tasks can no longer be satisfied")
                return
            self._stall, self._stall_commits = True, self._commits
            self._requeue([])
            if not self.queue:
                self._fail("deadlock: no agent can move")
                return

    def _requeue(self, freed: list[int]) -> None:
        self.rng.shuffle(freed)
        waiting = [a for a in range(self.A) if self.mode[a] == WAIT]
        waiting.sort(key=lambda a: (self.free_since[a], a))
        parked = [a for a in range(self.A) if self.mode[a] == HOME]
        if self._all_claimed():
            parked = []  # nothing left to offer them
        order = freed + waiting + parked
        self.queue = order[::-1]

    def _finish_episode(self) -> None:
        for a in range(self.A):
            if self.mode[a] in (FREE, WAIT):
                self.commit(a, 0)
        self.done, self.success = True, self.n_cancelled == 0
        if self.n_cancelled:
            self.failure = f"{self.n_cancelled} task(s) cancelled: no longer satisfiable after robot loss"
        self.agent, self._mask = None, None

    def _fail(self, why: str) -> None:
        self.done, self.success, self.failure = True, False, why
        self.agent, self._mask = None, None

    # ------------------------------------------------------------------------------------------
    # robot loss (the ROS task board calls this when a robot or its agent stops reporting)
    # ------------------------------------------------------------------------------------------
    def drop_agent(self, a: int) -> list[int]:
        """Remove agent a from the mission now (``clock``); returns the tasks this cancels.

        * a stops where it is (mode LOST); it leaves the capability pool and the decision queue.
        * its commitment is released: a task it had joined loses it as a member. A task that was
          in progress restarts (start = max(now, arrival of the remaining members)) if the others
          still satisfy it, else it reopens with the others waiting there.
        * tasks the remaining team can no longer satisfy are CANCELLED (their waiting members are
          freed where they are); if the open tasks can no longer all be completed by the agents
          that are not waiting (the deadlock-avoidance invariant), every open task is reset to
          empty and its members freed.
        * the pending decision, if any, is recomputed; freed, waiting and parked agents are
          offered a decision at this instant. The episode then continues as usual and succeeds
          only if no task was cancelled.
        """
        if self.mode[a] == LOST:
            return []
        now = self.clock
        if self.agent is not None:  # the pending decision is recomputed after the change
            self.queue.append(self.agent)
        self.agent, self._mask = None, None
        if a in self.queue:
            self.queue.remove(a)
        self._deferred.discard(a)
        freed: list[int] = []
        if self.mode[a] == TASK:
            m = int(self.target[a])
            if self.status[m] == OPEN:  # a was waiting there: not in the pool
                self._leave_task(a, m)
            else:
                self.pool -= self.cap[a]
                self._leave_task(a, m)
        else:
            self.pool -= self.cap[a]
        self._stop(a)
        self.mode[a], self.target[a] = LOST, -1
        # tasks the remaining team cannot satisfy any more
        team = self.cap[self.mode != LOST].sum(0)  # [K]
        cancelled = []
        for m in np.flatnonzero((self.status == EMPTY) | (self.status == OPEN)):
            if not self._fits(self.req[m], team):
                freed += self._reset_task(int(m))
                self.status[m] = CANCELLED
                self.rem[m] = 0.0
                self.n_cancelled += 1
                cancelled.append(int(m))
        # deadlock-avoidance invariant: the open tasks must stay completable by the free pool
        open_ids = np.flatnonzero(self.status == OPEN)
        if len(open_ids) and not self._closure(self.rem[open_ids], self.held[open_ids], self.pool)[0]:
            for m in open_ids:
                freed += self._reset_task(int(m))
                self.status[m] = EMPTY
        if not self.done:
            waiting = [b for b in range(self.A) if self.mode[b] == WAIT and b not in self.queue]
            parked = [b for b in range(self.A) if self.mode[b] == HOME and b not in self.queue]
            if self._all_claimed():
                parked = []
            order = [b for b in sorted(set(freed)) if b not in self.queue] + waiting + parked
            self.queue = order[::-1] + self.queue  # after the deciders already queued
            self._stall = False
            self._advance()
        return cancelled

    def _stop(self, a: int) -> None:
        """Agent a stops where it is now (its current leg is cut short)."""
        here = self.position(a)
        self.from_pos[a] = here
        self.to_pos[a] = here
        self.depart[a] = self.arrive[a] = self.clock

    def _leave_task(self, a: int, m: int) -> None:
        """Remove member a from task m (open or in progress); keeps pool and events consistent."""
        self.members[m].remove(a)
        if self.routes[a] and self.routes[a][-1] == m:
            self.routes[a].pop()
        self.held[m] -= self.cap[a]
        self.rem[m] = np.maximum(self.req[m] - self.held[m], 0.0)
        if self.status[m] == OPEN:
            if not self.members[m]:
                self.status[m] = EMPTY
                self.n_open -= 1
            return
        # in progress: its completion event is void; restart or reopen
        self.events = [e for e in self.events if e[2] != m]
        heapq.heapify(self.events)
        mem = self.members[m]
        if mem and (self.rem[m] <= 0).all():
            start = max(self.clock, float(self.arrive[mem].max()))
            self.start[m] = start
            self.finish[m] = start + float(self.inst.durations[m])
            self._seq += 1
            heapq.heappush(self.events, (self.finish[m], self._seq, m))
            return
        self.start[m] = self.finish[m] = np.nan
        if mem:
            self.status[m] = OPEN
            self.n_open += 1
            self.pool -= self.held[m]  # the others now wait at an open task
        else:
            self.status[m] = EMPTY

    def _reset_task(self, m: int) -> list[int]:
        """Empty open task m: its members are freed where they are now. Returns them."""
        mem = list(self.members[m])
        if self.status[m] == OPEN:
            self.n_open -= 1
            self.pool += self.held[m]
        for b in mem:
            self.members[m].remove(b)
            if self.routes[b] and self.routes[b][-1] == m:
                self.routes[b].pop()
            self.wait_total[b] += max(0.0, self.clock - self.arrive[b])
            self._stop(b)
            self.mode[b], self.target[b] = FREE, -1
            self.free_since[b] = self.clock
        self.held[m] = 0.0
        self.rem[m] = self.req[m].copy()
        return mem

    # ------------------------------------------------------------------------------------------
    # snapshots: hmrta-state/1 (the ROS board publishes them; agents rebuild the state to decide)
    # ------------------------------------------------------------------------------------------
    def clone(self) -> "MissionState":
        """Independent copy of the running state (the instance and rules are shared, read-only):
        lookahead and branching without replaying the mission from the start."""
        return copy.deepcopy(self, memo={id(self.inst): self.inst, id(self.rules): self.rules})

    def snapshot(self) -> dict[str, Any]:
        """The full state as an ``hmrta-state/1`` mapping (docs/schemas/hmrta-state-1.schema.json).

        Strict JSON (a task not started has ``null`` start and finish, never NaN) with exact floats
        (JSON keeps Python's shortest round-trip repr); :meth:`from_snapshot` restores a state that
        continues exactly like this one. Per-task and per-agent fields are columns indexed by task
        and agent id; ``queue`` lists the deciders still to come at this instant, next first."""
        version, internal, gauss = self.rng.getstate()
        return {
            "format": STATE_FORMAT,
            "rules": self.rules.to_dict(),
            "seed": self.seed,
            "clock": float(self.clock),
            "decisions": int(self.decisions),
            "done": bool(self.done),
            "success": bool(self.success),
            "failure": self.failure,
            "decider": None if self.agent is None else int(self.agent),
            "mask": None if self._mask is None else self._mask.tolist(),
            "queue": [int(a) for a in reversed(self.queue)],
            "deferred": sorted(int(a) for a in self._deferred),
            "stall": {"commitments": self._commits - self._stall_commits} if self._stall else None,
            "events": [[float(t), int(m)] for t, _, m in sorted(self.events)],
            "pool": self.pool.tolist(),
            "tasks": {
                "status": [STATUS_NAMES[s] for s in self.status.tolist()],
                "remaining": self.rem.tolist(),
                "held": self.held.tolist(),
                "start": [None if math.isnan(x) else x for x in self.start.tolist()],
                "finish": [None if math.isnan(x) else x for x in self.finish.tolist()],
                "members": [[int(a) for a in mem] for mem in self.members],
            },
            "agents": {
                "mode": [MODE_NAMES[x] for x in self.mode.tolist()],
                "target": [None if m < 0 else m for m in self.target.tolist()],
                "from": self.from_pos.tolist(),
                "to": self.to_pos.tolist(),
                "depart": self.depart.tolist(),
                "arrive": self.arrive.tolist(),
                "free_since": self.free_since.tolist(),
                "wait_total": self.wait_total.tolist(),
                "routes": [[int(m) for m in r] for r in self.routes],
                "depot_stops": self.depot_stops.tolist(),
            },
            "rng": {"version": version, "state": list(internal), "gauss_next": gauss},
        }

    @classmethod
    def from_snapshot(cls, inst: Instance, d: Any) -> "MissionState":
        """Rebuild the state of a mission on ``inst`` from an ``hmrta-state/1`` mapping
        (:meth:`snapshot`). Raises :class:`SnapshotError` (a ValueError naming the field) for an
        unknown format or version, or a field that is missing, mistyped or does not fit ``inst``.
        Fields this version does not know are ignored."""
        f = _Fields(d, "")
        got = d.get("format")
        if got != STATE_FORMAT:
            if "format" not in d:
                raise SnapshotError(f"snapshot: missing field 'format' (expected {STATE_FORMAT!r})")
            if isinstance(got, str) and got.rpartition("/")[0] == STATE_FORMAT.rpartition("/")[0]:
                raise SnapshotError(f"snapshot format: unsupported version {got!r} (this build reads "
                                    f"{STATE_FORMAT!r})")
            raise f.err("format", repr(STATE_FORMAT), got)
        A, M, K = inst.n_agents, inst.n_tasks, inst.skills
        self = cls.__new__(cls)
        self.inst = inst
        rules = f.raw("rules")
        try:
            self.rules = parse_rules(rules)
        except ValueError as e:
            raise SnapshotError(f"snapshot {e}") from None
        self.open_cap = self.rules.open_cap(inst)
        self.A, self.M, self.K = A, M, K
        self.additive = inst.additive
        self.cap = np.array(inst.traits if self.additive else inst.traits > 0, dtype=np.float64)
        self.req = np.array(inst.requirements if self.additive else inst.requirements > 0, dtype=np.float64)
        self.seed = f.integer("seed")
        self.clock = f.number("clock")
        self.decisions = f.integer("decisions", 0)
        self.done, self.success = f.boolean("done"), f.boolean("success")
        self.failure = f.text("failure")
        self.agent = f.integer("decider", 0, A, nullable=True)
        mask = f.raw("mask")
        if mask is not None and not (isinstance(mask, list) and len(mask) == M + 1
                                     and all(isinstance(x, bool) for x in mask)):
            raise f.err("mask", f"null or a list of {M + 1} booleans (depot, then each task)", mask)
        if (mask is None) != (self.agent is None):
            raise SnapshotError("snapshot mask: expected a list exactly when a decider is named, null otherwise")
        self._mask = None if mask is None else np.array(mask, dtype=bool)
        self.queue = f.ints("queue", None, 0, A)[::-1]
        self._deferred = set(f.ints("deferred", None, 0, A))
        if f.raw("stall") is None:
            self._stall, self._commits, self._stall_commits = False, 0, -1
        else:
            self._stall, self._commits, self._stall_commits = True, f.obj("stall").integer("commitments", 0), 0
        # pending completions in processing order; their sequence numbers only break ties in time
        self.events = [(t, i + 1, m) for i, (t, m) in enumerate(f.events("events", M))]
        heapq.heapify(self.events)
        self._seq = len(self.events)
        self.pool = f.floats("pool", (K,))
        t = f.obj("tasks")
        self.status = t.names("status", STATUS_NAMES, M)
        self.rem = t.floats("remaining", (M, K))
        self.held = t.floats("held", (M, K))
        self.start = t.floats("start", (M,), nullable=True)
        self.finish = t.floats("finish", (M,), nullable=True)
        self.members = t.id_lists("members", M, A)
        a = f.obj("agents")
        self.mode = a.names("mode", MODE_NAMES, A)
        self.target = np.array(a.ints("target", A, 0, M, nullable=True), dtype=np.int64)
        self.from_pos = a.floats("from", (A, 2))
        self.to_pos = a.floats("to", (A, 2))
        for k in ("depart", "arrive", "free_since", "wait_total"):
            setattr(self, k, a.floats(k, (A,)))
        self.routes = a.id_lists("routes", A, M)
        self.depot_stops = np.array(a.ints("depot_stops", A, 0, None), dtype=np.int64)
        self.n_open = int((self.status == OPEN).sum())
        self.n_done = int((self.status == DONE).sum())
        self.n_cancelled = int((self.status == CANCELLED).sum())
        rng = f.obj("rng")
        if rng.raw("version") != 3:
            raise rng.err("version", "3 (the state layout of Python's random.Random)", rng.raw("version"))
        state = (3, tuple(rng.ints("state", None, 0, 2**32)), rng.raw("gauss_next"))
        if state[2] is not None:
            state = state[:2] + (rng.number("gauss_next"),)
        self.rng = random.Random()
        try:
            self.rng.setstate(state)
        except (ValueError, TypeError, OverflowError) as e:
            raise SnapshotError(f"snapshot rng: not a state of Python's random.Random ({e})") from None
        return self

    # ------------------------------------------------------------------------------------------
    # results
    # ------------------------------------------------------------------------------------------
    def return_times(self) -> np.ndarray:  # [A] time each agent is (last) back at its depot
        return self.arrive.copy()

    @property
    def makespan(self) -> float:
        return float(self.arrive.max()) if self.success else math.nan


class _Fields:
    """Typed reading of one mapping of an ``hmrta-state/1`` snapshot; every error is a
    :class:`SnapshotError` naming the field (``tasks.remaining``, ``agents.routes[3][0]``)."""

    def __init__(self, d: Any, where: str):
        if not isinstance(d, dict):
            raise SnapshotError(f"snapshot {where or '(top level)'}: expected a mapping, got {_short(d)}")
        self.d, self.where = d, where

    def name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def err(self, key: str, what: str, v: Any) -> SnapshotError:
        return SnapshotError(f"snapshot {self.name(key)}: expected {what}, got {_short(v)}")

    def raw(self, key: str) -> Any:
        if key not in self.d:
            raise SnapshotError(f"snapshot: missing field {self.name(key)!r}")
        return self.d[key]

    def obj(self, key: str) -> "_Fields":
        return _Fields(self.raw(key), self.name(key))

    def boolean(self, key: str) -> bool:
        v = self.raw(key)
        if not isinstance(v, bool):
            raise self.err(key, "true or false", v)
        return v

    def text(self, key: str) -> str | None:
        v = self.raw(key)
        if v is not None and not isinstance(v, str):
            raise self.err(key, "a string or null", v)
        return v

    def integer(self, key: str, lo: int | None = None, hi: int | None = None, *, nullable: bool = False) -> Any:
        v = self.raw(key)
        if v is None and nullable:
            return None
        if not _is_int(v, lo, hi):
            raise self.err(key, _int_text(lo, hi) + (" or null" if nullable else ""), v)
        return v

    def number(self, key: str) -> float:
        v = self.raw(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.err(key, "a finite number", v)
        return float(v)

    def ints(self, key: str, n: int | None, lo: int, hi: int | None, *, nullable: bool = False) -> list[int]:
        """A list (of n entries, if given) of integers in [lo, hi); null entries read as -1."""
        v = self.raw(key)
        if not isinstance(v, list) or (n is not None and len(v) != n):
            raise self.err(key, f"a list of {'' if n is None else f'{n} '}integers", v)
        if all(type(x) is int for x in v) and (not v or (min(v) >= lo and (hi is None or max(v) < hi))):
            return list(v)  # the common case, checked fast
        out = []
        for i, x in enumerate(v):
            if x is None and nullable:
                out.append(-1)
            elif _is_int(x, lo, hi):
                out.append(x)
            else:
                raise self.err(f"{key}[{i}]", _int_text(lo, hi) + (" or null" if nullable else ""), x)
        return out

    def id_lists(self, key: str, n: int, hi: int) -> list[list[int]]:
        """n lists of ids in [0, hi) (task members, agent routes)."""
        v = self.raw(key)
        if not isinstance(v, list) or len(v) != n:
            raise self.err(key, f"a list of {n} lists of ids", v)
        if all(type(x) is list for x in v):
            flat = [y for x in v for y in x]
            if all(type(y) is int for y in flat) and (not flat or (min(flat) >= 0 and max(flat) < hi)):
                return [list(x) for x in v]  # the common case, checked fast
        return [_Fields({f"{key}[{i}]": x}, self.where).ints(f"{key}[{i}]", None, 0, hi) for i, x in enumerate(v)]

    def names(self, key: str, names: tuple[str, ...], n: int) -> np.ndarray:
        v = self.raw(key)
        if not isinstance(v, list) or len(v) != n:
            raise self.err(key, f"a list of {n} of {', '.join(names)}", v)
        index = {s: i for i, s in enumerate(names)}
        out = [index.get(s, -1) if type(s) is str else -1 for s in v]
        if -1 in out:
            i = out.index(-1)
            raise self.err(f"{key}[{i}]", f"one of {', '.join(names)}", v[i])
        return np.array(out, dtype=np.int64)

    def floats(self, key: str, shape: tuple[int, ...], *, nullable: bool = False) -> np.ndarray:
        """A float64 array of this shape from nested lists of finite numbers (null read as NaN)."""
        v = self.raw(key)
        what = f"{' x '.join(map(str, shape))} {'numbers or nulls' if nullable else 'finite numbers'}"
        w = [math.nan if x is None else x for x in v] if nullable and isinstance(v, list) else v
        try:
            a = np.asarray(w)
        except (ValueError, TypeError):  # ragged nesting
            raise self.err(key, what, v) from None
        if a.size == 0 and a.dtype.kind == "f" and math.prod(shape) == 0:
            a = a.reshape(shape)
        if a.shape != shape or a.dtype.kind not in "iuf":
            raise self.err(key, what, v)
        a = a.astype(np.float64)
        if (np.isinf(a) if nullable else ~np.isfinite(a)).any():
            raise self.err(key, what, v)
        return a

    def events(self, key: str, M: int) -> list[tuple[float, int]]:
        """Pending completions: a list of [time, task id]."""
        v = self.raw(key)
        if not isinstance(v, list):
            raise self.err(key, "a list of [time, task] pairs", v)
        out = []
        for i, e in enumerate(v):
            if (not isinstance(e, list) or len(e) != 2 or isinstance(e[0], bool) or not isinstance(e[0], (int, float))
                    or not math.isfinite(e[0]) or not _is_int(e[1], 0, M)):
                raise self.err(f"{key}[{i}]", f"[time, task id in 0..{M - 1}]", e)
            out.append((float(e[0]), e[1]))
        return out


def _is_int(v: Any, lo: int | None, hi: int | None) -> bool:
    return (isinstance(v, int) and not isinstance(v, bool) and (lo is None or v >= lo)
            and (hi is None or v < hi))


def _int_text(lo: int | None, hi: int | None) -> str:
    if lo is not None and hi is not None:
        return f"an integer in {lo}..{hi - 1}"
    return "an integer" + ("" if lo is None else f" >= {lo}")
