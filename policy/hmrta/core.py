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
import dataclasses
import heapq
import math
import numbers
import random
from dataclasses import dataclass
from typing import Any

import numpy as np

from .instance import MAX_VALUE, Instance, Species, Task, cover_tolerance, exact_arithmetic
from .reading import finite  # as a mission file's numbers: also integers beyond the float range

# agent modes (LOST: removed from the mission by drop_agent, e.g. a robot that stopped reporting)
FREE, TASK, HOME, WAIT, LOST = 0, 1, 2, 3, 4
MODE_NAMES = ("free", "task", "home", "wait", "lost")
# task status (CANCELLED: called off by the operator (cancel_task) or no longer satisfiable after a
# robot loss; UNRELEASED: an instance task whose release time lies ahead, hidden from every policy)
EMPTY, OPEN, IN_PROGRESS, DONE, CANCELLED, UNRELEASED = 0, 1, 2, 3, 4, 5
STATUS_NAMES = ("empty", "open", "in_progress", "done", "cancelled", "unreleased")
# the rejection of a robot's event scheduled after a mission's end (MissionState._events_ahead); a
# task added after the end (MissionState._reopen) schedules such events again
AFTER_END = "after the mission's end"
EVENT_TYPES = ("add_task", "cancel_task", "add_agent", "drop_agent", "release")


class EventRejected(ValueError):
    """An event the mission cannot take (an infeasible task, an unknown or finished task, a bad
    robot, a time before the mission clock); ``str(e)`` is the one-line reason."""


def team_cap(inst: Instance) -> int:
    """The ``max_open="team"`` cap of a mission: max(1, round(A / 2c)), where c, the mean coalition
    size, is the mean over tasks of (requirement sum) / (mean over agents of trait sum). A / c is
    about how many coalitions the team can field at once. Measured with greedy-coalition
    (docs/semantics.md): the best fixed cap grows with A / c, from 1 on SA-AT (A / c ~ 3) to 3
    or none on MA-AT (25,5,50,5) and (50,5,50,5) (A / c ~ 13-26), and this rule is within 2.5% of the best fixed cap on every
    row tried."""
    req = np.asarray(inst.requirements, dtype=np.float64)[inst.releases <= 0]  # [M0, K] tasks known at start
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


# ---------------------------------------------------------------------------------------------
# event records (MissionState.log, apply_event)
# ---------------------------------------------------------------------------------------------
def _vector(v: Any, n: int, where: str) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)) or len(v) != n or not all(finite(x) for x in v):
        raise EventRejected(f"{where}: expected a list of {n} finite numbers, got {_short(v)}")
    out = tuple(float(x) for x in v)
    if any(x < 0 or x > MAX_VALUE for x in out):
        raise EventRejected(f"{where}: expected values in [0, {MAX_VALUE:g}], got {_short(v)}")
    return out


def _unit_point(v: Any, where: str) -> tuple[float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 2 or not all(finite(x) and 0 <= x <= 1 for x in v):
        raise EventRejected(f"{where}: expected [x, y] in the unit square, got {_short(v)}")
    return float(v[0]), float(v[1])


def _task_record(task: Task, K: int) -> dict[str, Any]:
    return {"location": [float(x) for x in task.location], "requirements": [float(x) for x in task.requirements],
            "duration": float(task.duration)}


def _task_from_record(d: Any, K: int, requirement_type: str = "additive") -> Task:
    if not isinstance(d, dict):
        raise EventRejected(f"new task: expected a mapping with location, requirements, duration, got {_short(d)}")
    for k in ("location", "requirements", "duration"):
        if k not in d:
            raise EventRejected(f"new task: missing field {k!r}")
    loc = _unit_point(d["location"], "new task: location")
    req = _vector(d["requirements"], K, "new task: requirements")
    if not any(req):
        raise EventRejected("new task: requirements: expected at least one non-zero requirement (all zero)")
    dur = d["duration"]
    if not finite(dur) or not 0 <= dur <= MAX_VALUE:
        raise EventRejected(f"new task: duration: expected a number in [0, {MAX_VALUE:g}], got {_short(dur)}")
    return Task(loc, req, float(dur))


def _check_record(rec: Any) -> None:
    """Shape of an external event record (values are checked when it is applied)."""
    if not isinstance(rec, dict) or rec.get("type") not in EVENT_TYPES:
        raise EventRejected(f"event: expected a mapping with type one of {', '.join(EVENT_TYPES)}, got {_short(rec)}")
    if not finite(rec.get("t")):
        raise EventRejected(f"event {rec['type']}: t: expected a finite number, got {_short(rec.get('t'))}")
    kind = rec["type"]
    if kind == "cancel_task" and not (("task" in rec) ^ ("name" in rec)):
        raise EventRejected("event cancel_task: expected exactly one of task (an id) and name (a client id)")
    if kind == "add_task" and "task" not in rec:
        raise EventRejected("event add_task: missing field 'task'")
    if kind == "drop_agent" and "agent" not in rec:
        raise EventRejected("event drop_agent: missing field 'agent'")


def apply_event(state: "MissionState", record: dict) -> Any:
    """Replay one event record on ``state`` (a journal, a test). Records are those of
    :attr:`MissionState.log` (``add_task``, ``cancel_task``, ``add_agent``, ``drop_agent``; outcome
    fields such as ``id`` are ignored) and ``{"type": "choice", "agent": a, "node": n}`` for a
    decision. Returns what the matching method returns; raises EventRejected (the state unchanged)
    or ValueError for a choice that does not fit the pending decision."""
    kind = record.get("type") if isinstance(record, dict) else None
    if kind == "choice":
        a, node = record.get("agent"), record.get("node")
        if state.agent is None or a != state.agent:
            raise ValueError(f"choice of agent {a!r}: the pending decider is {state.agent}")
        if not _is_int(node, 0, None):
            raise ValueError(f"choice of agent {a}: node: expected an integer >= 0, got {_short(node)}")
        state.step(node)
        return node
    t = record.get("t")
    if kind == "add_task":
        task = _task_from_record(record.get("task"), state.K, state.inst.requirement_type)
        return state.add_task(task, t, record.get("name"))
    if kind == "cancel_task":
        return state.cancel_task(record["name"] if "name" in record else record.get("task"), t)
    if kind == "add_agent":
        return state.add_agent(record.get("species"), record.get("traits"), record.get("position"), t)
    if kind == "drop_agent":
        return state.drop_agent(record.get("agent"), t)
    raise EventRejected(f"event: unknown type {_short(kind)} (expected choice, add_task, cancel_task, "
                        f"add_agent or drop_agent)")


_ATOMS = (int, float, bool, str, type(None), np.integer, np.floating, np.bool_)
# list fields of MissionState holding lists of numbers (one level of copy is a full copy), and
# those holding immutable entries (numbers, strings, tuples of numbers)
_NESTED_LISTS = frozenset(("members", "routes", "moves"))
_FLAT_LISTS = frozenset(("queue", "events", "names"))


def copy_fields(fields: dict[str, Any], shared: tuple = (), skip: frozenset[str] = frozenset()) -> dict[str, Any]:
    """An independent copy of a state's fields (``MissionState.__dict__``) but ``skip``: arrays,
    sets and the random stream by their own copy, the known list fields one level deep, numbers
    and strings as they are, the objects in ``shared`` (the instance, the rules: read-only) as
    they are, anything else by ``copy.deepcopy`` (tests/policy/test_core.py checks that the copy
    shares nothing mutable)."""
    memo = {id(o): o for o in shared}
    out: dict[str, Any] = {}
    for k, v in fields.items():
        if k in skip:
            continue
        if id(v) in memo or isinstance(v, _ATOMS):
            out[k] = v
        elif type(v) is np.ndarray:
            out[k] = v.copy()
        elif k in _NESTED_LISTS and type(v) is list:
            out[k] = [list(x) for x in v]
        elif (k in _FLAT_LISTS and type(v) is list) or type(v) is set:
            out[k] = type(v)(v)
        elif type(v) is random.Random:
            out[k] = random.Random()
            out[k].setstate(v.getstate())
        else:
            out[k] = copy.deepcopy(v, memo)
    return out


class MissionState:
    """Exact event-driven state of one mission (SPEC §3). See the module docstring."""

    # live missions (the ROS board): the state processes nothing due after ``until`` (it holds,
    # with no decision pending and not done) until :meth:`advance_to` moves it on; offline: no hold
    until: float = math.inf

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
        # mission events (docs/semantics.md, "Events during a mission")
        self.base = (M, A, inst.n_species)  # tasks, agents and species of the instance at mission start
        self.release = np.array(inst.releases, dtype=np.float64)  # [M] when each task became known
        self.names: list[str | None] = [None] * M  # client ids of added tasks
        self.by_operator = np.zeros(M, dtype=bool)  # [M] cancelled by cancel_task (not unsatisfiable)
        hidden = self.release > 0
        self.status[hidden] = UNRELEASED
        self.rem[hidden] = 0.0
        self.n_hidden = int(hidden.sum())
        self.pending: list[tuple[float, int, dict]] = []  # timed external events, hidden until applied
        self._eseq = 0
        self.log: list[dict] = []  # external events applied (or rejected), in order
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
        # [A] every robot's movements in time order: (t, node) a leg started at t towards node (0
        # its depot, 1 + m task m), (t, -1) it stopped where it was at t. What a drawing of the
        # mission needs (hmrta.render); None in a state restored from a snapshot (not carried)
        self.moves: list[list[tuple[float, int]]] | None = [[] for _ in range(A)]
        self.depot_stops = np.zeros(A, dtype=np.int64)  # [A] returns home while work remained
        self.pool = self.cap.sum(0)  # [K] capability of agents not waiting at an open task
        self._exact = self._arithmetic_exact()  # masks may take the fast path of _safe
        self._tol = 0.0 if self._exact else cover_tolerance(self.cap, self.req)  # a remaining entry at most this is met
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
        for m in np.flatnonzero(hidden):
            self._schedule({"type": "release", "t": float(self.release[m]), "task": int(m)})
        for rec in inst.events:
            self._schedule(dict(rec))
        self._externals(0.0)  # events at time 0 come before the first decisions
        order = list(range(self.A))
        self.rng.shuffle(order)
        self.queue = [a for a in order if self.mode[a] != LOST][::-1]  # (a robot lost at 0 never decides)
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
        """bool [M]: tasks agent a may join now (ability, max-open and safety rules).

        Same values as :meth:`_task_mask_reference`, at a cost that hardly grows with the mission:
        one product over the tasks for the ability rule (remaining entries are never negative, so
        a positive sum over a's skills is a positive entry a reduces) and the banker's check of
        :meth:`_safe` in a few passes over the open tasks instead of one per candidate."""
        ca = self.cap[a]  # [K]
        contrib = (self.rem @ (ca > 0).astype(np.float64)) > 0  # [M] reduces a positive remaining entry
        if self.open_cap is not None and self.n_open >= self.open_cap:
            contrib &= self.status == OPEN
        if self.rules.safety and contrib.any():
            contrib = self._safe(a, contrib) if self._exact else self._safe_reference(a, contrib)
        return contrib

    def _task_mask_reference(self, a: int) -> np.ndarray:
        """The rules of :meth:`_task_mask` computed directly: every task, and one banker's check
        per candidate (the definition the fast path is tested against)."""
        ca = self.cap[a]  # [K]
        contrib = (np.minimum(self.rem, ca) > 0).any(1)  # [M] reduces a positive remaining entry
        if self.open_cap is not None and self.n_open >= self.open_cap:
            contrib &= self.status == OPEN
        if self.rules.safety and contrib.any():
            contrib = self._safe_reference(a, contrib)
        return contrib

    def _mask_reference(self) -> np.ndarray:
        """bool [1 + M]: the mask of the pending decision recomputed by :meth:`_task_mask_reference`
        (for tests: equal to :meth:`mask`)."""
        if self._mask is None:
            raise RuntimeError("no decision is pending (episode done)")
        mask = np.empty(self.M + 1, dtype=bool)
        mask[0] = not self._stall
        mask[1:] = self._task_mask_reference(self.agent)
        return mask

    # ---- deadlock avoidance (banker's algorithm over open tasks) -------------------------------
    def _fits(self, rem: np.ndarray, pool: np.ndarray) -> np.ndarray:
        """bool [...]: remaining requirement rows that `pool` could satisfy alone (to within the
        mission's cover tolerance, :func:`hmrta.instance.cover_tolerance`)."""
        return (rem <= (pool + self._tol if self.additive else (pool > 0))).all(-1)

    def _rows_within(self, bound: np.ndarray) -> np.ndarray:
        """bool [M]: tasks whose remaining requirement is <= bound [K] in every skill."""
        rem = self.rem
        ok = np.ones(self.M, dtype=bool)
        for k in range(self.K):  # a column at a time: K is small, the tasks many
            ok &= rem[:, k] <= bound[k] + self._tol
        return ok

    def _arithmetic_exact(self) -> bool:
        """True when every capability, requirement, held and pool entry is a multiple of 2^-24
        and their sums stay below 2^28: then every sum and difference the masks compute (pools,
        remaining requirements) is exact, whatever the order of the additions (:meth:`_safe`)."""
        return exact_arithmetic(self.cap, self.req, self.rem, self.held, self.pool)

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
        """:meth:`_safe_reference` in a few closures instead of one per open candidate, valid when
        the arithmetic is exact (``_exact``: every capability and requirement a multiple of 2^-24
        and their sums far below 2^53, so the closures add and compare exact values).

        The closure is a monotone least fixpoint (a larger pool or a smaller remaining requirement
        never completes fewer tasks), so with F = closure(open tasks, pool - c_a):

        * a joins open task X without satisfying it (X: remaining r_X - c_a, held h_X + c_a, pool
          pool - c_a): everything F completes still completes. If X is among them, the pool is
          then F's final pool + c_a and the rest is F's stuck tasks, the same for every such X
          (and the same check as for an empty candidate). If X is stuck in F, the rest is F's
          stuck tasks with X changed, from F's final pool.
        * a satisfies open task X (X starts, its holders come back later: open tasks without X,
          pool + h_X): with G = closure(open tasks, pool), every other task G completes still
          completes, after which the pool is G's final pool (+ h_X if G left X stuck). So X is
          safe when G completes everything, never when G completes X but not everything, and
          otherwise as the closure of G's other stuck tasks from G's final pool + h_X.

        Tested against the reference, decision by decision, in tests/policy/test_fast_paths.py."""
        ca = self.cap[a]  # [K]
        out = cand.copy()
        open_ids = np.flatnonzero(self.status == OPEN)  # [O]
        rems, helds = self.rem[open_ids], self.held[open_ids]  # [O, K]
        pool = self.pool  # a is in the pool (it is not waiting at an open task)
        empty = np.flatnonzero(cand & (self.status == EMPTY))  # [E]
        on_open = cand[open_ids]  # [O] open candidates
        r_open = self._remaining(rems - ca)  # [O, K] remaining of each open task if a joins
        starts = (r_open <= 0).all(1)  # [O] a satisfies the task
        joins = on_open & ~starts  # [O]
        starts &= on_open
        if len(empty) or joins.any():
            f_done, f_pool, f_alive = self._closure(rems, helds, pool - ca)  # F
            # F's completions, then the stuck ones with a back in the pool (X done in F)
            after = f_done or self._closure(rems[f_alive], helds[f_alive], f_pool + ca)[0]
            if len(empty):
                # a opens X: safe if a alone satisfies X (remaining <= c_a), or if X's remaining
                # after a fits F's final pool (remaining <= f_pool + c_a; binary: <= (f_pool > 0)
                # + c_a) and the stuck ones complete after it. The second bound is >= c_a, so it
                # covers the first when it applies.
                if after and (not self.additive or (f_pool >= 0).all()):
                    bound = f_pool + ca if self.additive else (f_pool > 0) + ca  # [K]
                else:
                    bound = ca
                out[empty] = self._rows_within(bound)[empty]
            if joins.any():
                out[open_ids[joins & ~f_alive]] = after
                stuck = np.flatnonzero(f_alive)  # [L] F's stuck tasks (open rows)
                for j in np.flatnonzero(joins & f_alive):  # X stuck in F: the rest with X changed
                    rems2, helds2 = rems[stuck], helds[stuck]  # [L, K] (copies)
                    x = int(np.searchsorted(stuck, j))
                    rems2[x], helds2[x] = r_open[j], helds[j] + ca
                    out[open_ids[j]] = self._closure(rems2, helds2, f_pool)[0]
        if starts.any():
            g_done, g_pool, g_alive = self._closure(rems, helds, pool)  # G
            if g_done:
                out[open_ids[starts]] = True
            else:
                out[open_ids[starts & ~g_alive]] = False
                stuck = np.flatnonzero(g_alive)  # [L]
                for j in np.flatnonzero(starts & g_alive):  # X stuck in G: G's other stuck tasks
                    keep = stuck[stuck != j]
                    out[open_ids[j]] = self._closure(rems[keep], helds[keep], g_pool + helds[j])[0]
        return out

    def _safe_reference(self, a: int, cand: np.ndarray) -> np.ndarray:
        """The deadlock-avoidance mask by definition: for each candidate, the state after a's
        commitment must let the greedy closure complete every open task."""
        ca = self.cap[a]
        out = cand.copy()
        open_ids = np.flatnonzero(self.status == OPEN)  # [O]
        rems, helds = self.rem[open_ids], self.held[open_ids]  # [O, K]
        pool = self.pool  # a is in the pool (it is not waiting at an open task)
        # empty candidates: a opens X with remaining r_X = max(q_X - ca, 0), leaving the pool
        empty = np.flatnonzero(cand & (self.status == EMPTY))
        if len(empty):
            r = self._remaining(self.rem[empty] - ca)  # [E, K]
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
            r = self._remaining(rems[i] - ca)
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
        if backdate and node > 0:  # never before the task was known (released, or added)
            t_dep = max(t_dep, float(self.release[node - 1]))
        here = self.position(a)
        inst = self.inst
        self._mask = None
        self.agent = None
        if node == 0:
            if mode == HOME:
                return  # stays parked (or keeps going home)
            self._leg(a, here, inst.depots[a], t_dep, 0)
            self.mode[a], self.target[a] = HOME, -1
            if not self._all_claimed():
                self.depot_stops[a] += 1
            return
        m = node - 1
        self._commits += 1
        self._leg(a, here, inst.task_locations[m], t_dep, node)
        self.mode[a], self.target[a] = TASK, m
        self.members[m].append(a)
        self.routes[a].append(m)
        self.held[m] += self.cap[a]
        self.rem[m] = self._remaining(self.rem[m] - self.cap[a])
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

    def _remaining(self, short: np.ndarray) -> np.ndarray:
        """[K] a remaining requirement from what is still short (requirement minus what the
        coalition holds): 0 where nothing, or no more than the cover tolerance, is short."""
        return np.where(short > self._tol, short, 0.0)

    def _leg(self, a: int, frm: np.ndarray, to: np.ndarray, t_dep: float, node: int) -> None:
        if self.moves is not None:
            self.moves[a].append((float(t_dep), int(node)))
        self.from_pos[a] = frm
        self.to_pos[a] = to
        self.depart[a] = t_dep
        self.arrive[a] = t_dep + math.hypot(to[0] - frm[0], to[1] - frm[1]) / self.inst.velocity

    def _nothing_to_join(self) -> bool:
        """No task is empty or open: every task is in progress, done or cancelled."""
        return self.n_open == 0 and not (self.status == EMPTY).any()

    def _all_claimed(self) -> bool:
        """Every known task is done, cancelled or in progress (nothing will need a parked agent)."""
        return self.n_done + self.n_cancelled + self.n_hidden + int((self.status == IN_PROGRESS).sum()) == self.M

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
                if mode == LOST:  # lost after it was queued (an event of the same instant): it never decides
                    continue
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
            if self.n_done + self.n_cancelled == self.M and not self._events_ahead():
                self._finish_episode()
                return
            te = self.pending[0][0] if self.pending else math.inf  # next external event
            if self.events and self.events[0][0] <= te:
                # completions of the next instant, then the external events of that instant
                if not self._jump(self.events[0][0]):
                    return
                continue
            if self.pending and (self._all_claimed() or (self._stall and self._commits == self._stall_commits)):
                if not self._jump(te):  # nothing to do before the next external event
                    return
                continue
            # stall: nothing in progress; offer parked and waiting agents the tasks, depot masked
            if self._stall and self._commits == self._stall_commits:
                self._fail("deadlock: open tasks can no longer be satisfied")
                return
            self._stall, self._stall_commits = True, self._commits
            self._requeue([])
            if not self.queue:
                if self.pending:
                    if not self._jump(te):
                        return
                    continue
                self._fail("deadlock: no agent can move")
                return

    def _jump(self, t: float) -> bool:
        """Advance the clock to t: the completions due by then, then the external events due by
        then, in time order; the freed agents, waiting and parked ones are queued. False if t lies
        beyond ``t_max`` (the episode fails)."""
        t = max(t, self.clock)
        if t > self.until:  # held: the live mission clock has not reached t (advance_to resumes here)
            return False
        if t > self.rules.t_max:
            self._fail(f"time limit {self.rules.t_max} exceeded")
            return False
        self.clock = t
        freed: list[int] = []
        while self.events and self.events[0][0] <= t:
            _, _, m = heapq.heappop(self.events)
            freed += sorted(self.complete(m))
        freed += self._externals(t)
        self._stall = False
        self._requeue(freed)
        return True

    def _events_ahead(self) -> bool:
        """With every known task done or cancelled: whether scheduled events still belong to the
        mission. Tasks to come (added, released) always do; robots joining or lost only until the
        last robot is home. Those after it are dropped, logged as rejected: they would only push
        the end (the makespan) to their own time."""
        if not self.pending:
            return False
        if any(rec["type"] in ("add_task", "release") for _, _, rec in self.pending):
            return True
        alive = self.mode != LOST  # [A]
        end = float(self.arrive[alive].max()) if alive.any() else -math.inf  # every robot is on its way home
        if self.pending[0][0] <= end:
            return True
        for _, _, rec in sorted(self.pending):
            self.log.append({**rec, "rejected": f"{AFTER_END} at {end:g} (every task done or cancelled, "
                                                f"every robot home)"})
        self.pending = []
        return False

    def _requeue(self, freed: list[int]) -> None:
        freed = [b for b in freed if self.mode[b] != LOST]  # freed, then lost at the same instant: not shuffled in
        self.rng.shuffle(freed)
        waiting = np.flatnonzero(self.mode == WAIT)  # [W]
        waiting = waiting[np.lexsort((waiting, self.free_since[waiting]))].tolist()  # by (free_since, id)
        parked = [] if self._all_claimed() else np.flatnonzero(self.mode == HOME).tolist()  # nothing to offer them
        order = freed + waiting + parked
        self.queue = order[::-1]

    def _finish_episode(self) -> None:
        for a in range(self.A):
            if self.mode[a] in (FREE, WAIT):
                self.commit(a, 0)
        lost = self.n_cancelled - int(self.by_operator.sum())  # operator cancellations are no failure
        self.done, self.success = True, lost == 0
        if lost:
            self.failure = f"{lost} task(s) cancelled: no longer satisfiable after robot loss"
        self.agent, self._mask = None, None

    def _fail(self, why: str) -> None:
        self.done, self.success, self.failure = True, False, why
        self.agent, self._mask = None, None

    # ------------------------------------------------------------------------------------------
    # robot loss (the ROS task board calls this when a robot or its agent stops reporting)
    # ------------------------------------------------------------------------------------------
    def drop_agent(self, a: int, now: float | None = None) -> list[int]:
        """Remove agent a from the mission at ``now`` (default: the clock); returns the tasks this
        cancels (a later ``now`` schedules the loss and returns []).

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
          only if no task was cancelled as unsatisfiable.
        """
        if not _is_int(a, 0, self.A):
            raise EventRejected(f"robot {a!r}: no such robot (0..{self.A - 1})")
        if self.mode[a] == LOST:
            return []
        out = self._event({"type": "drop_agent", "t": self._when(now), "agent": int(a)})
        return [] if out is None else out[0]

    def _here_since(self, a: int) -> float:
        """Since when robot a has been where it is now: its arrival at the end of its leg, or now
        while it is on its way (or about to leave)."""
        t, d0, d1 = float(self.clock), float(self.depart[a]), float(self.arrive[a])
        return min(d1, t) if t >= d1 or d1 <= d0 else t

    def _drop_agent(self, a: int) -> tuple[list[int], list[int]]:
        """drop_agent without the re-queueing: (cancelled tasks, freed agents)."""
        if self.mode[a] == LOST:
            return [], []
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
        return cancelled, freed

    # ------------------------------------------------------------------------------------------
    # mission events: tasks added and cancelled, robots added (docs/semantics.md, "Events during
    # a mission"). Every event is a plain JSON-able record {"type", "t", ...}; ``log`` keeps the
    # records of the external events applied or rejected, and :func:`apply_event` replays them.
    # ------------------------------------------------------------------------------------------
    def add_task(self, task: Task, now: float | None = None, name: str | None = None) -> int | None:
        """Add an empty task at ``now`` (default: the clock; a later time schedules it and returns
        None); its id is the previous number of tasks, its release time ``now``. It is offered at
        the next decisions: the pending decision is recomputed and parked and waiting robots decide
        again at once. A task the remaining team cannot satisfy is rejected (EventRejected)."""
        if self.done and self.success:  # every task done or cancelled, the robots on their way home
            return self._reopen(task, now, name)
        rec = {"type": "add_task", "t": self._when(now), "task": _task_record(task, self.K)}
        if name is not None:
            rec["name"] = str(name)
        return self._event(rec)

    def _reopen(self, task: Task, now: float | None, name: str | None) -> int:
        """:meth:`add_task` on a mission that ended well (every task done or cancelled, every
        robot sent home): the task is added at ``now`` and the mission goes on from there, exactly
        as the mission that knew the task would come then. That mission stays open for it (a task
        still to come keeps a mission open, :meth:`_events_ahead`) and its robots, with nothing to
        join, go home at the same moments. So the robots' events dropped as coming after the end
        are scheduled again, the task is scheduled at ``now``, and the mission runs there as that
        mission runs: the robots, parked or on their way home, then decide at once.

        A task added at the very instant the mission ended comes one ulp later
        (``np.nextafter``): at that instant the robots freed by the last completion have already
        decided to go home, while in a mission that knew of the task they would have seen it. A
        task after the time limit (``rules.t_max``) is rejected. A rejected task (EventRejected, or
        any other error) leaves the ended mission as it was."""
        t = self._time(now)
        t = t if t > self.clock else float(np.nextafter(self.clock, math.inf))
        if t > self.rules.t_max:
            raise EventRejected(f"new task: at {t:g}, after the mission's time limit {self.rules.t_max:g}")
        rec = {"type": "add_task", "t": t, "task": _task_record(task, self.K)}
        if name is not None:
            rec["name"] = str(name)
        ended = self.clone()
        try:
            self.done, self.success, self.failure = False, False, None
            n = len(self.log)
            while n and str(self.log[n - 1].get("rejected", "")).startswith(AFTER_END):
                n -= 1
            for old in self.log[n:]:  # the robots' events after the end: they belong to the mission again
                self._schedule({k: v for k, v in old.items() if k != "rejected"})
            del self.log[n:]
            self._schedule(rec)
            hold, self.until = self.until, t
            self._advance()  # as the mission that knew: the robots' events, then the task at t
            self.until = hold
            added = next(e for e in reversed(self.log) if e["type"] == "add_task")
            if "rejected" in added:
                raise EventRejected(added["rejected"])
            return added["id"]
        except BaseException:
            self.__dict__.update(ended.__dict__)
            raise

    def cancel_task(self, m: int | str, now: float | None = None) -> list[int] | None:
        """Cancel task m (an id, or the client id given to :meth:`add_task`) at ``now``; returns
        the robots it frees (None when scheduled for a later time). An empty, open or unreleased
        task is closed; a task in progress stops (its coalition is freed; see docs/semantics.md).
        Freed robots are free where they are at ``now`` (en route: part-way along their leg)
        and re-plan from there. An unknown, done or cancelled task is rejected (EventRejected)."""
        rec: dict[str, Any] = {"type": "cancel_task", "t": self._when(now)}
        rec["name" if isinstance(m, str) else "task"] = m
        return self._event(rec)

    def add_agent(self, species: int | None = None, traits: Any = None, position: Any = None,
                  now: float | None = None) -> int | None:
        """Add a robot at ``now``: of ``species`` (an index) or with a new trait vector ``traits``
        (then ``position`` is required and becomes its depot). It is free at ``position`` (default:
        its species' depot) and decides at once. Returns its id (the previous number of robots),
        or None when scheduled for a later time."""
        rec: dict[str, Any] = {"type": "add_agent", "t": self._when(now)}
        if species is not None:
            rec["species"] = species
        if traits is not None:
            rec["traits"] = [float(x) for x in traits]
        if position is not None:
            rec["position"] = [float(x) for x in position]
        return self._event(rec)

    def advance_to(self, t: float, idle: bool = False) -> None:
        """Live missions: let the state run up to mission time ``t`` (completions and scheduled
        events due by then, and the decisions they bring) and hold there. Holding splits the
        run without changing it: a state advanced step by step ends exactly like one never held.
        With ``idle``, a held state (nothing due before ``t``) moves its clock to ``t``, so that an
        event given at ``t`` applies at once."""
        self.until = max(self.until, float(t))
        if self.done or self.agent is not None:
            return
        self._advance()
        if idle and not self.done and self.agent is None and self.clock < t:
            self.clock = float(t)

    def schedule(self, record: dict) -> None:
        """Queue an external event record (``t`` >= the clock) to be applied when the mission
        reaches its time, in time order with the task completions, after the completions of the
        same instant. Until then it is invisible to every policy."""
        self._when(record.get("t") if isinstance(record, dict) else None)
        _check_record(record)
        self._schedule(dict(record))

    def _when(self, now: Any) -> float:
        if self.done:
            raise EventRejected("the mission is over")
        return self._time(now)

    def _time(self, now: Any) -> float:
        """The time of an event given ``now`` (default: the clock): a finite time, not before the clock."""
        t = self.clock if now is None else now
        if not finite(t):
            raise EventRejected(f"event time: expected a finite number, got {_short(t)}")
        if t < self.clock:
            raise EventRejected(f"event time {t} lies before the mission clock {self.clock}")
        return float(t)

    def _schedule(self, rec: dict) -> None:
        self._eseq += 1
        heapq.heappush(self.pending, (float(rec["t"]), self._eseq, rec))

    def _event(self, rec: dict) -> Any:
        """Apply a record now (t == clock), or schedule it (t > clock)."""
        _check_record(rec)
        if rec["t"] > self.clock:
            self._schedule(rec)
            return None
        out, freed = self._apply(rec)  # EventRejected leaves the state unchanged
        self.log.append({**rec, **self._outcome(rec, out)})
        if not self.done:
            queued = set(self.queue)
            waiting = [b for b in np.flatnonzero(self.mode == WAIT).tolist() if b not in queued]
            parked = [] if self._all_claimed() else [b for b in np.flatnonzero(self.mode == HOME).tolist()
                                                     if b not in queued]
            order = [b for b in sorted(set(freed)) if b not in queued] + waiting + parked
            self.queue = order[::-1] + self.queue  # after the deciders already queued
            self._stall = False
            self._advance()
        return out

    def _outcome(self, rec: dict, out: Any) -> dict:
        """The outcome fields of an applied record (in the log): the id of a task or robot added,
        the tasks a robot's loss cancelled, where it stopped (``at``) and since when it was there
        (``since``: the loss itself when it was on its way), the robots a cancellation freed (and,
        set by the cancellation itself, ``started``: when a task in progress had started, or was
        to start once its coalition arrived)."""
        kind = rec["type"]
        if kind == "add_task":
            return {"id": out}
        if kind == "add_agent":
            return {"id": out}
        if kind == "drop_agent":
            cancelled, since = out
            return {"cancelled": list(cancelled), "at": [float(x) for x in self.to_pos[rec["agent"]]], "since": since}
        if kind == "cancel_task":
            return {"freed": list(out)}
        return {}

    def _externals(self, t: float) -> list[int]:
        """Apply the scheduled events due by t; returns the agents they free or add."""
        freed: list[int] = []
        while self.pending and self.pending[0][0] <= t:
            _, _, rec = heapq.heappop(self.pending)
            rec = {**rec, "t": float(self.clock)}
            try:
                out, f = self._apply(rec)
            except EventRejected as e:
                self.log.append({**rec, "rejected": str(e)})
                continue
            if rec["type"] != "release":
                self.log.append({**rec, **self._outcome(rec, out)})
            elif out is not None and self.status[out] == CANCELLED:  # released unsatisfiable: say so
                self.log.append({**rec, "cancelled": [int(out)]})
            freed += sorted(f)
        return freed

    def _apply(self, rec: dict) -> tuple[Any, list[int]]:
        """Apply one event at the clock: (outcome, agents to offer a decision). The pending
        decision, if any, goes back to the queue first. Raises EventRejected with the state
        unchanged."""
        kind = rec["type"]
        if kind == "drop_agent":
            a = rec["agent"]
            if not _is_int(a, 0, self.A):
                raise EventRejected(f"robot {a!r}: no such robot (0..{self.A - 1})")
            if self.mode[a] == LOST:
                raise EventRejected(f"robot {a}: already lost")
            since = self._here_since(a)  # before its leg is cut short
            cancelled, freed = self._drop_agent(a)
            return (cancelled, since), freed
        if kind == "release":
            m = rec["task"]
            if self.status[m] != UNRELEASED:
                return None, []  # cancelled before its release
            self._requeue_pending()
            self.n_hidden -= 1
            self.status[m] = EMPTY
            self.rem[m] = self.req[m]
            if not self._fits(self.req[m], self.cap[self.mode != LOST].sum(0)):
                self.status[m] = CANCELLED
                self.rem[m] = 0.0
                self.n_cancelled += 1
            return m, []
        if kind == "add_task":
            return self._add_task(rec)
        if kind == "cancel_task":
            return self._cancel_task(rec)
        if kind == "add_agent":
            return self._add_agent(rec)
        raise EventRejected(f"unknown event type {kind!r}")

    def _requeue_pending(self) -> None:
        if self.agent is not None:  # the pending decision is recomputed after the change
            self.queue.append(self.agent)
        self.agent, self._mask = None, None

    def _add_task(self, rec: dict) -> tuple[int, list[int]]:
        task = _task_from_record(rec["task"], self.K, self.inst.requirement_type)
        name = rec.get("name")
        if name is not None and name in self.names:
            raise EventRejected(f"task {name!r}: a task with this id exists already")
        who = f"task {name!r}" if name is not None else "new task"
        req = np.array(task.requirements if self.additive else np.array(task.requirements) > 0, dtype=np.float64)
        team = self.cap[self.mode != LOST].sum(0)  # [K]
        tol = cover_tolerance(self.cap, np.vstack([self.req, req[None]])) if self.additive else 0.0
        short_of = np.flatnonzero(req - tol > (team if self.additive else (team > 0)))
        if len(short_of):
            k = int(short_of[0])
            raise EventRejected(f"{who}: no robot left with skill {k}" if team[k] <= 0 else
                                f"{who}: needs {req[k]:g} of skill {k}, the remaining team has {team[k]:g}")
        self._requeue_pending()
        m = self.M
        t = float(rec["t"])
        self.inst = dataclasses.replace(self.inst, tasks=self.inst.tasks + (dataclasses.replace(task, release=t),),
                                        _cache={})
        self.M += 1
        self.req = np.vstack([self.req, req[None]])
        self.rem = np.vstack([self.rem, req[None]])
        self.held = np.vstack([self.held, np.zeros((1, self.K))])
        self.status = np.append(self.status, EMPTY)
        self.members.append([])
        self.start = np.append(self.start, np.nan)
        self.finish = np.append(self.finish, np.nan)
        self.release = np.append(self.release, t)
        self.names.append(name)
        self.by_operator = np.append(self.by_operator, False)
        self._exact = self._exact and self._arithmetic_exact()
        self._tol = tol
        return m, []

    def _task_id(self, rec: dict) -> int:
        if "name" in rec:
            name = rec["name"]
            if name not in self.names:
                raise EventRejected(f"task {name!r}: no such task")
            return self.names.index(name)
        m = rec["task"]
        if not _is_int(m, 0, self.M):
            raise EventRejected(f"task {m!r}: no such task (0..{self.M - 1})")
        return m

    def _cancel_task(self, rec: dict) -> tuple[list[int], list[int]]:
        m = self._task_id(rec)
        who = f"task {rec['name']!r}" if "name" in rec else f"task {m}"
        st = self.status[m]
        if st in (DONE, CANCELLED):
            raise EventRejected(f"{who}: already {STATUS_NAMES[st]}")
        self._requeue_pending()
        freed: list[int] = []
        if st == UNRELEASED:
            self.n_hidden -= 1
        elif st == OPEN:
            freed = self._reset_task(m)
        elif st == IN_PROGRESS:  # stops: the coalition is freed where it is now
            self.events = [e for e in self.events if e[2] != m]
            heapq.heapify(self.events)
            start = float(self.start[m])
            rec["started"] = start  # an outcome field of the logged record (its coalition worked from then)
            for b in self.members[m]:
                if self.routes[b] and self.routes[b][-1] == m:
                    self.routes[b].pop()
                self.wait_total[b] += max(0.0, min(self.clock, start) - self.arrive[b])
                self._stop(b)
                self.mode[b], self.target[b] = FREE, -1
                self.free_since[b] = self.clock
            freed = list(self.members[m])
            self.members[m] = []
            self.held[m] = 0.0
            self.start[m] = self.finish[m] = np.nan
        self.status[m] = CANCELLED
        self.rem[m] = 0.0
        self.n_cancelled += 1
        self.by_operator[m] = True
        return freed, freed

    def _add_agent(self, rec: dict) -> tuple[int, list[int]]:
        inst, K = self.inst, self.K
        s, traits, pos = rec.get("species"), rec.get("traits"), rec.get("position")
        if (s is None) == (traits is None):
            raise EventRejected("new robot: give exactly one of species and traits")
        if pos is not None:
            pos = _unit_point(pos, "new robot: position")
        if s is not None:
            if not _is_int(s, 0, inst.n_species):
                raise EventRejected(f"new robot: species {s!r}: no such species (0..{inst.n_species - 1})")
            species = inst.species
        else:
            tr = _vector(traits, K, "new robot: traits")
            if not any(tr):
                raise EventRejected("new robot: traits: expected at least one non-zero trait (all zero)")
            if pos is None:
                raise EventRejected("new robot: a robot with new traits needs a position (its depot)")
            species = inst.species + (Species(tr, 0, pos),)
            s = len(species) - 1
        here = np.array(pos if pos is not None else species[s].depot, dtype=np.float64)
        self._requeue_pending()
        a = self.A
        self.inst = dataclasses.replace(inst, species=species, added_agents=inst.added_agents + (s,), _cache={})
        self.A += 1
        cap = np.array(self.inst.traits[a] if self.additive else self.inst.traits[a] > 0, dtype=np.float64)
        self.cap = np.vstack([self.cap, cap[None]])
        self.mode = np.append(self.mode, FREE)
        self.target = np.append(self.target, -1)
        self.from_pos = np.vstack([self.from_pos, here[None]])
        self.to_pos = np.vstack([self.to_pos, here[None]])
        for k in ("depart", "arrive", "free_since"):
            setattr(self, k, np.append(getattr(self, k), self.clock))
        self.wait_total = np.append(self.wait_total, 0.0)
        self.routes.append([])
        if self.moves is not None:
            self.moves.append([])
        self.depot_stops = np.append(self.depot_stops, 0)
        self.pool = self.pool + cap
        self._exact = self._exact and self._arithmetic_exact()
        self._tol = cover_tolerance(self.cap, self.req)
        return a, [a]

    def _stop(self, a: int) -> None:
        """Agent a stops where it is now (its current leg is cut short)."""
        here = self.position(a)
        self.from_pos[a] = here
        self.to_pos[a] = here
        self.depart[a] = self.arrive[a] = self.clock
        if self.moves is not None:
            self.moves[a].append((float(self.clock), -1))

    def _leave_task(self, a: int, m: int) -> None:
        """Remove member a from task m (open or in progress); keeps pool and events consistent."""
        self.members[m].remove(a)
        if self.routes[a] and self.routes[a][-1] == m:
            self.routes[a].pop()
        self.held[m] -= self.cap[a]
        self.rem[m] = self._remaining(self.req[m] - self.held[m])
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
        lookahead and branching without replaying the mission from the start. Copies field by
        field (:func:`copy_fields`): 0.4 ms halfway through a mission of 600 robots and 2,000
        tasks, where a deep copy takes 4 ms (``benchmarks/clone.py``)."""
        twin = MissionState.__new__(MissionState)
        twin.__dict__.update(copy_fields(self.__dict__, (self.inst, self.rules)))
        return twin

    def snapshot(self) -> dict[str, Any]:
        """The full state as an ``hmrta-state/1`` mapping (docs/schemas/hmrta-state-1.schema.json).

        Strict JSON (a task not started has ``null`` start and finish, never NaN) with exact floats
        (JSON keeps Python's shortest round-trip repr); :meth:`from_snapshot` restores a state that
        continues exactly like this one. Per-task and per-agent fields are columns indexed by task
        and agent id; ``queue`` lists the deciders still to come at this instant, next first."""
        version, internal, gauss = self.rng.getstate()
        d = {
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
                "release": self.release.tolist(),
                "names": list(self.names),
                "cancelled_by_operator": self.by_operator.tolist(),
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
            "pending": [copy.deepcopy(rec) for _, _, rec in sorted(self.pending, key=lambda e: e[:2])],
            "log": copy.deepcopy(self.log),
        }
        M0, A0, S0 = self.base
        if self.M > M0 or self.A > A0:  # the mission grew: what the instance file does not hold
            inst = self.inst
            d["added"] = {
                "tasks": [{**_task_record(t, self.K), "release": float(t.release)} for t in inst.tasks[M0:]],
                "species": [{"traits": [float(x) for x in sp.traits], "depot": [float(x) for x in sp.depot]}
                            for sp in inst.species[S0:]],
                "agents": [int(x) for x in inst.added_agents[A0 - (inst.n_agents - len(inst.added_agents)):]],
                # the sizes of the mission as it started: a reader given the grown instance (a
                # republished mission) cuts it back to them, so nothing added counts twice
                "base": {"tasks": int(M0), "agents": int(A0), "species": int(S0)},
            }
        return d

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
        self = cls.__new__(cls)
        rules = f.raw("rules")
        try:
            self.rules = parse_rules(rules)
        except ValueError as e:
            raise SnapshotError(f"snapshot {e}") from None
        if isinstance(d.get("added"), dict) and d["added"].get("base") is not None:
            inst = _base(inst, f.obj("added").obj("base"))
        self.open_cap = self.rules.open_cap(inst)  # fixed at mission start
        self.base = (inst.n_tasks, inst.n_agents, inst.n_species)
        if d.get("added") is not None:
            inst = _grown(inst, f.obj("added"))
        A, M, K = inst.n_agents, inst.n_tasks, inst.skills
        self.inst = inst
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
        for m in np.flatnonzero((self.status == EMPTY) | (self.status == UNRELEASED)):
            if self.members[m]:  # commitments make a task open (greedy-coalition's estimates rely on it)
                raise t.err(f"members[{m}]", f"no members for a task that is {STATUS_NAMES[self.status[m]]}",
                            self.members[m])
        self.release = t.floats("release", (M,)) if "release" in t.d else np.array(inst.releases, dtype=np.float64)
        names = t.raw("names") if "names" in t.d else [None] * M
        if not isinstance(names, list) or len(names) != M or not all(x is None or isinstance(x, str) for x in names):
            raise t.err("names", f"a list of {M} strings or nulls", names)
        self.names = list(names)
        byop = t.raw("cancelled_by_operator") if "cancelled_by_operator" in t.d else [False] * M
        if not isinstance(byop, list) or len(byop) != M or not all(isinstance(x, bool) for x in byop):
            raise t.err("cancelled_by_operator", f"a list of {M} booleans", byop)
        self.by_operator = np.array(byop, dtype=bool)
        a = f.obj("agents")
        self.mode = a.names("mode", MODE_NAMES, A)
        self.target = np.array(a.ints("target", A, 0, M, nullable=True), dtype=np.int64)
        self.from_pos = a.floats("from", (A, 2))
        self.to_pos = a.floats("to", (A, 2))
        for k in ("depart", "arrive", "free_since", "wait_total"):
            setattr(self, k, a.floats(k, (A,)))
        self.routes = a.id_lists("routes", A, M)
        self.moves = None  # (not in snapshots)
        self.depot_stops = np.array(a.ints("depot_stops", A, 0, None), dtype=np.int64)
        self.n_open = int((self.status == OPEN).sum())
        self.n_done = int((self.status == DONE).sum())
        self.n_cancelled = int((self.status == CANCELLED).sum())
        self.n_hidden = int((self.status == UNRELEASED).sum())
        self._exact = self._arithmetic_exact()
        self._tol = cover_tolerance(self.cap, self.req)
        pending = d.get("pending") or []
        log = d.get("log") or []
        if not isinstance(pending, list) or not isinstance(log, list) or not all(isinstance(x, dict) for x in log):
            raise SnapshotError("snapshot pending / log: expected lists of event records")
        self.pending = []
        for i, rec in enumerate(pending):
            try:
                _check_record(rec)
            except EventRejected as e:
                raise SnapshotError(f"snapshot pending[{i}]: {e}") from None
            self.pending.append((float(rec["t"]), i + 1, copy.deepcopy(rec)))
        self._eseq = len(self.pending)
        self.log = copy.deepcopy(log)
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


def _base(inst: Instance, f: "_Fields") -> Instance:
    """``inst`` cut back to the mission's start sizes (``added.base`` of a snapshot): the instance
    of a grown mission (tasks, species and robots appended) read with a snapshot that lists the
    additions again."""
    M0, A0, S0 = f.integer("tasks", 0), f.integer("agents", 0), f.integer("species", 1)
    block = sum(s.count for s in inst.species[:S0])
    if M0 > inst.n_tasks or S0 > inst.n_species or not block <= A0 <= inst.n_agents:
        raise SnapshotError(f"snapshot added.base: the mission started with {M0} tasks, {A0} robots and {S0} "
                            f"species; the instance has {inst.n_tasks}, {inst.n_agents} and {inst.n_species}")
    if (M0, A0, S0) == (inst.n_tasks, inst.n_agents, inst.n_species):
        return inst
    return dataclasses.replace(inst, tasks=inst.tasks[:M0], species=inst.species[:S0],
                               added_agents=inst.added_agents[:A0 - block], _cache={})


def _grown(inst: Instance, f: "_Fields") -> Instance:
    """The instance of a mission that grew: the tasks, species and robots added to it."""
    try:
        tasks = f.raw("tasks")
        species = f.raw("species")
        agents = f.raw("agents")
        if not (isinstance(tasks, list) and isinstance(species, list) and isinstance(agents, list)):
            raise SnapshotError("snapshot added: expected lists tasks, species and agents")
        K = inst.skills
        new_tasks = tuple(dataclasses.replace(_task_from_record(x, K), release=float(x.get("release", 0.0)))
                          for x in tasks)
        new_species = tuple(Species(_vector(x.get("traits") if isinstance(x, dict) else None, K, "traits"), 0,
                                    _unit_point(x.get("depot") if isinstance(x, dict) else None, "depot"))
                            for x in species)
    except EventRejected as e:
        raise SnapshotError(f"snapshot added: {e}") from None
    S = inst.n_species + len(new_species)
    if not all(_is_int(x, 0, S) for x in agents):
        raise SnapshotError(f"snapshot added.agents: expected species indices in 0..{S - 1}, got {_short(agents)}")
    return dataclasses.replace(inst, tasks=inst.tasks + new_tasks, species=inst.species + new_species,
                               added_agents=inst.added_agents + tuple(agents), _cache={})


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
        if not finite(v):
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
