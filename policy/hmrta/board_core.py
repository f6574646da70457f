"""The board's state machine as the board, its journal replay and the agents' replicas share it:
:class:`BoardState` (the SPEC §3 state machine that logs every leg), :func:`state_digest`, the
header of a published version (:class:`Header`, :class:`View`, :func:`board_header`) and
:class:`BoardCore`, which applies the board's events. :mod:`hmrta.board` decides what happens;
:mod:`hmrta.replica` follows it with this module alone."""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from .core import LOST, MissionState, Rules, apply_event, copy_fields
from .instance import Instance
from .reading import finite

BOARD_FORMAT = "hmrta-board/2"
LEG_WINDOW = 4  # legs per robot repeated on every board (a reader that skipped versions catches up)
HOLD = -1  # leg node: stay where you are (0 = own depot, 1 + m = task m)
RESEND = -2  # leg node: publish this goal again now (it repeats a leg the robot has not reached)


# BoardState's own fields, left out of its plain MissionState clone
_BOARD_ONLY = frozenset(("leg_log", "leg_arrive", "leg_base", "leg_seqs", "until"))


class BoardState(MissionState):
    """The mission state machine, logging every leg a commitment starts.

    One ``step`` may run several events ahead of the mission clock (a robot commits to a task,
    the task completes, the robot is sent home), so the current leg alone would lose moves; the
    log keeps them all, in order, for the robots' goals. A replica built from a keyframe holds
    only each robot's latest legs: ``leg_base[a]`` legs come before ``leg_log[a]``."""

    def __init__(self, inst, seed: int = 0, rules: Rules = Rules()):
        self.leg_log: list[list[tuple[int, float, float, float]]] = [[] for _ in range(inst.n_agents)]
        self.leg_arrive: list[list[float]] = [[] for _ in range(inst.n_agents)]  # planned arrival of each leg
        self.leg_base: list[int] = [0] * inst.n_agents  # legs before leg_log[a] (a replica's keyframe left out)
        # [A] legs each robot has been given: leg_base[a] + len(leg_log[a]), kept as the logs grow
        # (the digest and the arrival gate read it every version: no walk over the robots' logs)
        self.leg_seqs = np.zeros(inst.n_agents, dtype=np.int64)
        self.touched: set[int] = set()  # robots given legs since a reader last took this set (agent hosts)
        self.until = 0.0  # live: the state never runs ahead of the mission clock (MissionState.advance_to)
        super().__init__(inst, seed=seed, rules=rules)
        self.grow_legs()  # robots a scenario adds at time 0, before the first decision

    @classmethod
    def from_keyframe(cls, inst: Instance, snap: dict[str, Any], legs: Sequence[Any], until: float) -> "BoardState":
        """The board's state from a keyframe: its ``hmrta-state/1`` snapshot, its legs (per robot
        ``(seq, latest legs)`` or None for a lost robot) and the mission time the state may reach
        (``until``). SnapshotError (a ValueError) for a snapshot that does not fit ``inst``."""
        st = cls.from_snapshot(inst, snap)
        st.until = float(until)
        st.leg_log, st.leg_arrive, st.leg_base, st.touched = [], [], [], set()
        for a in range(st.A):
            e = legs[a] if a < len(legs) else None
            window = [(int(g[0]), float(g[1]), float(g[2]), float(g[3])) for g in e[1]] if e else []
            st.leg_log.append(window)
            st.leg_arrive.append([math.nan] * len(window))  # not on the wire (the board's leg timers only)
            st.leg_base.append(int(e[0]) - len(window) if e else 0)
        st.leg_seqs = np.array([b + len(w) for b, w in zip(st.leg_base, st.leg_log)], dtype=np.int64)  # [A]
        return st

    def grow_legs(self) -> None:
        """Leg logs for robots added to the mission."""
        while len(self.leg_log) < self.A:
            self.leg_log.append([])
        while len(self.leg_arrive) < len(self.leg_log):
            self.leg_arrive.append([])
        while len(self.leg_base) < len(self.leg_log):
            self.leg_base.append(0)
        if len(self.leg_seqs) < len(self.leg_log):
            self.leg_seqs = np.concatenate([self.leg_seqs, np.zeros(len(self.leg_log) - len(self.leg_seqs), np.int64)])

    def commit(self, a: int, node: int) -> None:
        before = (float(self.depart[a]), float(self.arrive[a]))
        super().commit(a, node)
        if (float(self.depart[a]), float(self.arrive[a])) != before or node > 0:
            self.log_leg(a, node)

    def log_leg(self, a: int, node: int) -> None:
        while len(self.leg_log) <= a:  # a robot added during the mission
            self.leg_log.append([])
        self.grow_legs()
        self.leg_log[a].append((node, float(self.to_pos[a, 0]), float(self.to_pos[a, 1]), float(self.depart[a])))
        self.leg_arrive[a].append(max(float(self.arrive[a]), float(self.depart[a])))
        self.leg_seqs[a] += 1
        self.touched.add(a)

    def log_resend(self, a: int, i: int) -> None:
        """Repeat leg i of robot a as a RESEND leg (its agent publishes that goal again)."""
        j = i - self.leg_base[a]
        if j < 0:
            raise IndexError(f"resend of leg {i} of robot {a}: this replica holds its legs from {self.leg_base[a]} on")
        _, x, y, depart = self.leg_log[a][j]
        self.leg_log[a].append((RESEND, x, y, depart))
        self.leg_arrive[a].append(self.leg_arrive[a][j])
        self.leg_seqs[a] += 1
        self.touched.add(a)

    def leg_seq(self, a: int) -> int:
        """How many legs robot a has been given (the last one is numbered this)."""
        return int(self.leg_seqs[a])

    def legs(self, a: int, after: int | None = None) -> tuple[int, tuple] | None:
        """Robot a's legs as on the board: ``(seq, legs)``, its latest LEG_WINDOW legs, or every
        leg numbered above ``after`` that this state holds; None for a lost robot."""
        if self.mode[a] == LOST:
            return None
        log = self.leg_log[a]
        n = LEG_WINDOW if after is None else max(LEG_WINDOW, self.leg_seq(a) - after)
        return self.leg_seq(a), tuple(log[-n:])

    def clone(self) -> MissionState:
        """A plain :class:`MissionState` copy, without the leg log and the live hold (``until``):
        what a lookahead branches on, exactly as offline."""
        twin = MissionState.__new__(MissionState)
        twin.__dict__.update(copy_fields(self.__dict__, (self.inst, self.rules), _BOARD_ONLY))
        return twin


_DIGEST_WEIGHTS = np.zeros(0, dtype=np.uint64)


def _fingerprint(arr: np.ndarray) -> int:
    """A 64-bit fingerprint of an array's little-endian int64 / float64 bit patterns: their sum
    weighted by fixed odd pseudo-random 64-bit words (one per position), modulo 2**64. Exact
    integer arithmetic, so every machine gets the same value; any change of one entry changes it."""
    global _DIGEST_WEIGHTS
    bits = np.ascontiguousarray(arr).reshape(-1).view(np.uint64)  # [n] the entries' bit patterns
    n = len(bits)
    if len(_DIGEST_WEIGHTS) < n:  # grown once per size, always the same stream
        _DIGEST_WEIGHTS = np.random.default_rng(0x6469676573740a).integers(
            0, 2**64, size=max(n, 2 * len(_DIGEST_WEIGHTS)), dtype=np.uint64) | np.uint64(1)
    return int(np.dot(bits, _DIGEST_WEIGHTS[:n])) if n else 0


def state_digest(st: BoardState) -> str:
    """A cheap fingerprint of the board's state (16 hex digits): the clock, the decider, the
    counters, the decision queue, every task's status and remaining requirement, every robot's
    mode, target, current leg and number of legs. The board puts it in every version it
    publishes; a replica whose state gives another digest has diverged and resynchronises.
    The arrays and the queue enter as :func:`_fingerprint` s (a few microseconds for thousands
    of entries), the scalars as text, all through blake2b."""
    h = hashlib.blake2b(digest_size=8)
    A = st.A
    seq = st.leg_seqs[:A].copy()
    seq[st.mode[:A] == LOST] = -1  # [A] leg_seq of each robot (-1: lost)
    h.update(repr((float(st.clock), st.agent, int(st.decisions), bool(st.done), int(st.n_done), int(st.n_cancelled),
                   A, st.M, len(st.log), len(st.pending), len(st.events), len(st.queue))).encode())
    prints = [_fingerprint(seq), _fingerprint(np.fromiter(st.queue, dtype=np.int64, count=len(st.queue)))]
    for arr in (st.status, st.mode, st.target):
        prints.append(_fingerprint(np.asarray(arr, dtype="<i8")))
    for arr in (st.depart, st.arrive, st.to_pos, st.rem):
        prints.append(_fingerprint(np.asarray(arr, dtype="<f8")))
    h.update(np.array(prints, dtype="<u8").tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class Header:
    """The header of one board version (hmrta-board/2): the events applied since the previous
    version, in order, and the state's digest. The board publishes :class:`View` s; a replica
    reads :class:`hmrta.replica.Frame` s."""
    session: str
    version: int
    prev: int  # the version whose state the events apply to
    rev: int
    phase: str
    decider: int | None
    clock: float
    horizon: float
    n_done: int
    n_cancelled: int
    n_tasks: int
    lost: tuple[int, ...]
    events: tuple[dict[str, Any], ...]  # the journal records of this version (hmrta-journal/1 events)
    digest: str  # state_digest of the state after the events


@dataclass(frozen=True)
class View(Header):
    """One board message to publish: a version of the board stream (its :class:`Header`) and, for
    a keyframe, also the legs and the full state. A keyframe repeated on request has ``stream``
    False (its version was streamed already); a header repeated to confirm a replica's version
    has ``keyframe`` False and the version already streamed."""
    keyframe: bool = False  # also publish the full board: legs and state
    stream: bool = True  # publish the header on the board stream
    reason: str = ""  # why a keyframe: first, period, requested, robots, resumed, done
    until: float | None = None  # keyframes: the mission time the state may reach (MissionState.advance_to)
    legs: tuple | None = None  # keyframes: per robot (seq, latest legs) or None (lost)
    state_json: str | None = None  # keyframes: the hmrta-state/1 snapshot as compact JSON (cached per revision)


def board_header(v: Any) -> dict[str, Any]:
    """The header line of an hmrta-board/2 message from a :class:`View` (or anything with its
    fields): ``until`` only in keyframes."""
    d = {"format": BOARD_FORMAT, "session": v.session, "version": v.version, "prev": v.prev, "rev": v.rev,
         "phase": v.phase, "decider": v.decider, "clock": v.clock, "horizon": v.horizon, "n_done": v.n_done,
         "n_cancelled": v.n_cancelled, "n_tasks": v.n_tasks, "lost": list(v.lost), "ev": list(v.events),
         "digest": v.digest}
    if v.until is not None:
        d["until"] = v.until
    return d


# ---------------------------------------------------------------------------------------------
# the state machine and the events that move it (the board, its journal replay, replicas)
# ---------------------------------------------------------------------------------------------
def point_or_none(p: Any) -> tuple[float, float] | None:
    """(x, y) of a journaled position [x, y] of finite numbers, else None."""
    return (float(p[0]), float(p[1])) if isinstance(p, list) and len(p) == 2 and all(map(finite, p)) else None


class BoardCore:
    """The board's state machine (:class:`BoardState`, revision ``rev``, lost robots ``lost``) and
    how the board's events change it. :class:`hmrta.board.MissionBoard` applies events as they come and
    replays its journal with :meth:`apply_event`; an agent's :class:`hmrta.replica.Replica`
    applies the events the board publishes the same way, so both states stay equal."""

    state: BoardState
    rev: int
    lost: dict[int, str]

    def apply_event(self, ev: dict[str, Any]) -> None:
        """Apply what one journal event (hmrta-journal/1) did to the state. Raises ValueError
        (KeyError, TypeError, IndexError) for an event that does not fit the state."""
        st = self.state
        kind = ev["type"]
        if "until" in ev:  # the state's hold when the event was applied (MissionState.advance_to)
            st.until = max(st.until, float(ev["until"]))
        if kind == "choice":
            a, node = int(ev["robot"]), int(ev["node"])
            if st.agent != a:
                raise ValueError(f"choice of agent {a}, but the decider is {st.agent}")
            st.step(node)
            self.rev += 1
        elif kind == "drop_agent":
            self._drop(int(ev["robot"]), str(ev.get("reason", "")), float(ev["t"]))
        elif kind == "advance":
            self._held(lambda: st.advance_to(float(ev["until"])))
        elif kind == "resend":
            st.log_resend(int(ev["robot"]), int(ev["leg"]))
            self.rev += 1
        elif kind in ("add_task", "cancel_task", "add_agent"):
            self._external(ev)
        elif kind not in ("start", "arrival", "resume"):  # board bookkeeping only
            raise ValueError(f"unknown event type {kind!r}")

    def _drop(self, a: int, reason: str, t: float) -> list[int]:
        self.lost[a] = reason
        st = self.state

        def change() -> list[int]:
            if not st.done:
                st.advance_to(t, idle=True)
            return st.drop_agent(a) if not st.done else []
        return self._held(change, skip=a)

    def _external(self, rec: dict[str, Any]) -> Any:
        """Apply an operator event (add_task, cancel_task, add_agent) at its time ``t``: the held
        state moves to ``t`` first. EventRejected leaves the state as it was: the event is tried
        on a copy first, since moving to ``t`` alone changes the state (its clock, the decisions
        due by then), and a refused event is neither journaled nor published, so the replicas
        would never hear of that move."""
        st = self.state
        trial = st.clone()
        trial.until = st.until
        trial.advance_to(float(rec["t"]), idle=True)
        apply_event(trial, rec)  # EventRejected: nothing changed

        def change() -> Any:
            st.advance_to(float(rec["t"]), idle=True)
            return apply_event(st, rec)
        return self._held(change)

    def _held(self, change: Callable[[], Any], skip: int = -1, bump: bool = True) -> Any:
        """Apply ``change`` to the state; robots it stopped short of their destination (no new
        commitment) get a hold leg."""
        st = self.state
        n_legs = st.leg_seqs.copy()  # [B] the robots' legs before the change
        B = len(n_legs)
        to_pos = st.to_pos[:B].copy()  # [B, 2]
        out = change()
        moved = np.flatnonzero((st.to_pos[:B] != to_pos).any(axis=1))  # destination changed
        for b in moved.tolist():
            if b != skip and st.leg_seqs[b] == n_legs[b]:  # ... with no new leg: stopped short
                st.log_leg(b, HOLD)
        self._scenario_losses()
        self._sync_robots()
        if bump:
            self.rev += 1
        return out

    def _scenario_losses(self) -> None:
        """Robots the state lost that the board did not drop: lost by a scenario event (one at
        time 0 is applied as the state is built)."""
        for b in np.flatnonzero(self.state.mode == LOST).tolist():
            if b not in self.lost:
                self.lost[b] = "lost (scenario event)"

    def _sync_robots(self) -> None:
        """Robots the state added get their leg logs."""
        self.state.grow_legs()


# ---------------------------------------------------------------------------------------------
# the board
# ---------------------------------------------------------------------------------------------
