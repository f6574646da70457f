"""The task board's protocol, without ROS: a mission board as a plain object.

:class:`MissionBoard` holds the SPEC §3 state machine (:class:`BoardState`, a
:class:`hmrta.core.MissionState` that logs every leg) and everything the board decides about the
messages it receives; the ROS node (``hmrta_coordinator.task_board``) only maps topics, parameters
and timers onto it, in the way a simulator's ROS wrapper delegates to its world object. Feed it
decoded messages and clock values, call :meth:`MissionBoard.poll` and publish the
:class:`View` it returns (if any). Nothing here imports rclpy.

* **Choices** (:meth:`MissionBoard.choice`): schema-decoded choices are validated in order
  (session, authentication when a :class:`hmrta.keys.Verifier` is given, known robot, lost robot,
  duplicate, version, released decision, turn, mask); a valid one is applied with
  ``MissionState.step``, anything else returns a :class:`Rejected` and changes nothing.
* **The clock and the arrival gate**: the board releases a decision only when the mission clock
  (:meth:`MissionBoard.set_clock`) has reached the decision's instant, and gives the
  clock a *horizon* it may not pass: the next decision instant, and the start of any task whose
  members have not yet reported (:meth:`MissionBoard.pose`) being at the task.
* **Robot loss**: a robot whose agent heartbeat (:meth:`MissionBoard.heartbeat`) stops for
  ``heartbeat_timeout`` seconds (its pose may stay silent: poses only confirm arrivals), or that does not decide within ``decision_timeout`` seconds, is
  dropped (``MissionState.drop_agent``) by :meth:`MissionBoard.tick`.
* **Arrivals and stuck robots**: a robot counts as arrived at a task (or home) once its leg
  there has departed and its pose is within ``tolerance`` (mission units) of the goal. Each leg the
  board waits for has a timeout of ``leg_timeout_factor`` x its planned travel time +
  ``leg_timeout_floor``. The leg's timer runs on the mission clock from the leg's departure to its
  planned arrival, then on wall seconds: in a real-time mission that is wall time throughout; in a
  simulated one, a late robot holds the simulated clock at its task (the arrival gate), so mission
  time stops and only wall time can measure how late it is. After one timeout the board re-sends
  the goal (a ``RESEND`` leg: the agent publishes that goal again at once); after a second one it
  drops the robot like a lost one (reason ``stuck: no arrival at task m within X s``).
* **Robots joining** (:meth:`MissionBoard.join`, from the ``joining`` list of a heartbeat): a
  robot not in the mission that announces its species (or traits, and its position when its
  driver reports one) is added with ``add_agent`` at the mission clock, journaled, and named;
  robots a scenario's ``add_robot`` events add are named ``robot_<n>`` (n = robots at the start +
  how many the scenario added before). ``robots_changed`` tells the node to republish the mission
  (same session, the grown robot list and instance).
* **Journal and replay** (``journal``: a path): every published board version is appended to a
  JSON-lines journal (``hmrta-journal/1``), one line per version with the events applied since the
  previous one (choices, arrival confirmations, losses, the start); lines that carry events are
  flushed and fsynced before :meth:`MissionBoard.poll` returns the version for publishing. A board
  created on an existing journal replays it (same session, same versions, same state) and goes on
  from there. A torn last line (a write cut short) is detected (no newline, or not a JSON object)
  and dropped before anything is appended; it is never applied in part, since one line holds all
  the events of one version.
* **Stream and keyframes** (:meth:`MissionBoard.poll`, :class:`View`): each version is published
  as a header with the events applied since the previous version (the records of its journal
  line) and the state's digest (:func:`state_digest`); some versions are also keyframes (legs and
  full state): the first, after a restart, after robots were added, the last, periodically and
  when a replica asks (:meth:`MissionBoard.request`). Replicas (:mod:`hmrta.replica`) apply the
  events with the same code as the board (:class:`BoardCore`).
* **Result** (:meth:`MissionBoard.result`): the ``hmrta-solution/1`` of the mission with the
  board's extras (lost robots and reasons, undone tasks, latencies, rejections, keyframes).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import statistics
import time
import uuid
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from .core import DONE, LOST, STATUS_NAMES, EventRejected, MissionState, Rules
from .instance import Instance
from .keys import rejection_code
from .reading import finite, one_line
from .solution import Solution, solution_from_state
from .board_core import (BOARD_FORMAT, HOLD, LEG_WINDOW, RESEND, BoardCore, BoardState, Header, View, board_header,
                         point_or_none, state_digest)
from .journal import JOURNAL_FORMAT, JOURNAL_START, Journal, JournalError, instance_digest, journal_header, read_journal

# (also the names of hmrta.board_core and hmrta.journal that users of this module import from it)
__all__ = ["BOARD_FORMAT", "HOLD", "JOURNAL_FORMAT", "JOURNAL_START", "LEG_WINDOW", "RESEND", "BoardCore",
           "BoardState", "Header", "Journal", "JournalError", "MissionBoard", "Rejected", "TokenBucket", "View",
           "board_header", "check_journal_decisions", "instance_digest", "journal_header", "read_journal",
           "replay_journal", "state_digest"]

EPS = 1e-6  # sim-time comparisons (stamps are rounded to the nanosecond)
PHASES = ("starting", "wait", "decide", "closing", "done")
KEYFRAME_INTERVAL = 0.25  # seconds: keyframes asked for by replicas, at most one per interval
KEYFRAME_REPEAT = 1.0  # seconds: the latest keyframe's version is published again at most this often
HEADER_REPEAT = 0.25  # seconds: an idle board streams its latest header again (a replica that missed it sees the gap)
CHECK_GATE = False  # tests: every incremental arrival gate is compared with the full scan
GATE_RESCAN = 0.5  # seconds: while the arrival gate holds the mission clock, every robot is rescanned this often
STALL_GAP = 1.0  # seconds: a watchdog tick (every 0.1 s on the node) later than this after the previous one: the board stalled
NEVER_REPORTED = "never reported"  # why a robot silent until the start-up timeout is dropped
REFUSED = "its agent refused the mission"  # why a robot whose agent refuses is dropped (then its reason)
POSES_REJECTED = "no pose accepted"  # why a robot whose every pose was rejected is dropped (then the last reason)
REFUSAL_CHARS = 300  # of an agent's reason, kept and logged
LIVE_EVENTS = frozenset(("add_task", "cancel_task", "add_agent", "drop_agent"))  # journaled events from outside the mission file
HEADER_BYTES = 330  # about the bytes of a stream header without its events (for the automatic keyframe period)


class TokenBucket:
    """At most ``rate`` events a second on average, ``burst`` at once (``rate`` <= 0: no limit):
    :meth:`take` says whether one more may happen at time ``now`` (seconds) and counts it."""

    def __init__(self, rate: float, burst: float, now: float):
        self.rate, self.burst = rate, burst
        self.tokens, self.time = burst, now

    def take(self, now: float) -> bool:
        if self.rate <= 0:
            return True
        self.tokens = min(self.burst, self.tokens + (now - self.time) * self.rate)
        self.time = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


@dataclass(frozen=True)
class Rejected:
    """Why a message was refused (``reason``: a code of hmrta-rejection/1)."""
    reason: str
    detail: str
    robot: str = ""
    version: int = -1


def percentile(xs: list[float], q: float) -> float:
    if not xs:
        return math.nan
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, math.ceil(q / 100 * len(s)) - 1))]


@dataclass
class LegTimer:
    """The timeout of the leg (index ``leg`` in the robot's leg log) the board waits for."""
    leg: int
    depart: float
    arrive: float
    limit: float  # seconds: leg_timeout_factor x planned travel + leg_timeout_floor
    reached: float | None = None  # wall time when the mission clock reached the planned arrival
    resent: bool = False


def _task_index(rid: str, M: int) -> int | None:
    """A cancel request's id read as the index of one of the mission's M tasks (decimal digits), or
    None. An operator's task of the same id takes precedence (MissionBoard.task_request)."""
    return int(rid) if rid.isascii() and rid.isdigit() and int(rid) < M else None


def _r(v: float | None) -> float | None:
    return None if v is None or v != v else round(float(v), 3)


class MissionBoard(BoardCore):
    """The board's protocol logic (see the module docstring). Wall times come from ``now``
    (default ``time.monotonic``); ``log(level, text)`` receives what the board reports
    (levels ``info``, ``warning``)."""

    def __init__(self, inst: Instance, names: Sequence[str] | None = None, *, seed: int = 0,
                 rules: Rules = Rules(), method: str = "greedy", session: str | None = None,
                 verifier: Any = None, tolerance: float = 0.25, heartbeat_timeout: float = 5.0,
                 leg_timeout_factor: float = 3.0, leg_timeout_floor: float = 10.0, scale: float = 1.0,
                 decision_timeout: float = 30.0, startup_timeout: float = 120.0, wait_for_robots: bool = True,
                 journal: str | os.PathLike | None = None, keyframe_period: int = 0,
                 now: Callable[[], float] = time.monotonic, log: Callable[[str, str], None] | None = None):
        A = inst.n_agents
        names = list(names or [f"robot_{a}" for a in range(A)])
        if len(names) != A or len(set(names)) != A:
            raise ValueError(f"robot_names: expected {A} distinct names, got {len(names)}")
        self.inst, self.names, self.seed, self.rules, self.method = inst, names, seed, rules, method
        self.index = {n: a for a, n in enumerate(names)}
        self.verifier = verifier
        self.tolerance, self.heartbeat_timeout = tolerance, heartbeat_timeout
        self.leg_timeout_factor, self.leg_timeout_floor = leg_timeout_factor, leg_timeout_floor
        self.scale = scale  # metres per mission unit (log messages only)
        self.leg_timers: dict[int, LegTimer] = {}
        self.decision_timeout, self.startup_timeout = decision_timeout, startup_timeout
        self.now = now
        self.log = log or (lambda level, text: None)
        self.state = BoardState(inst, seed=seed, rules=rules)
        self.session = session or uuid.uuid4().hex[:12]
        # when this mission was first created (wall clock, journaled: a board restarted on its journal
        # keeps it): of two missions in one mission namespace, the later one gives way (ROS nodes)
        self.created = round(time.time(), 6)
        self.version = 0  # published board version
        self.rev = 0  # state revision
        self.phase = "starting"
        self.clock = 0.0  # latest mission clock (/clock)
        # the clock may not pass the horizons the board published (sim_robot never takes it past
        # them): the largest published (journaled: a board restarted on its journal knows its
        # predecessor's; inf for a journal written without it), and the latest clock heard beyond
        # it, followed as far as each new horizon allows (see set_clock)
        self.allowed = 0.0
        self._beyond = 0.0
        self._beyond_warned = -math.inf  # when the board last warned of a clock beyond the horizons
        self.t_created = now()
        self.t_start: float | None = None
        self.started = False  # the mission has started (journaled: a replayed board does not wait again)
        self.seen_status: list[float | None] = [None] * A
        self._hosts: dict[int, tuple[str, str | None, float]] = {}  # robot -> (host, host before, since)
        self._two_hosts: set[int] = set()  # robots warned of two agent processes
        self.seen_pose: list[float | None] = [None] * A
        self.last_pose: list[tuple[float, float] | None] = [None] * A
        self.ptr = [0] * A  # route prefix whose arrivals are confirmed
        self.lost: dict[int, str] = {}
        self.stopped_at: dict[int, tuple[float, float]] = {}  # lost robot -> its last reported position
        self.accepted: set[tuple[int, int]] = set()
        self.released_at = 0.0  # wall time when the current decision was released
        # the board's own stalls (a watchdog tick more than STALL_GAP after the previous one: its
        # process stopped or starved): the wall time of the latest, from which every robot's
        # timeout counts afresh (see _stalled)
        self._ticked: float | None = None
        self._resumed = -math.inf
        self.latency_ms: list[float] = []
        self.agent_ms: list[float] = []
        self.rejected: Counter[str] = Counter()
        self.auth_rejected: dict[str, Counter[str]] = {"choice": Counter(), "status": Counter()}
        self.finished = False
        self.restarts = 0  # times this mission's board was restarted on its journal
        self.replayed = 0  # board versions replayed from the journal (0: the mission starts afresh)
        self._started_wall: float | None = None  # a replayed mission: the wall clock (epoch) at its start
        self._final_wall: float | None = None  # wall seconds from start to end, fixed when the mission is done
        self._key: tuple | None = None
        # the incremental arrival gate (see gate): the state it was computed on, each robot's
        # part, robots whose pose changed since, robots waiting for their leg's departure
        self._gate_sig: tuple | None = None
        self._gate_part = np.zeros(0)
        self._gate_dirty: set[int] = set()
        self._gate_waiting: set[int] = set()
        self._gate_clock = -math.inf
        self._gate_rescanned = -math.inf  # board time of the last scan of every robot
        # what each robot's part was computed from (between changes of the structure, a new
        # decision rescans only the robots whose route, legs or gate task's start changed)
        self._gate_task = np.zeros(0, dtype=np.int64)  # [A] the task its scan stopped at (-1: none)
        self._gate_rlen = np.zeros(0, dtype=np.int64)  # [A] its route's length then
        self._gate_llen = np.zeros(0, dtype=np.int64)  # [A] its leg log's length then
        self._gate_start = np.zeros(0)  # [M] every task's start then
        self._gate_progress: tuple | None = None
        self._cache_rev = -1
        self._legs: tuple = ()
        self._state_json = ""
        if keyframe_period < 0:
            raise ValueError(f"keyframe_period: expected a number of versions >= 0 (0: automatic), "
                             f"got {keyframe_period}")
        self.keyframe_period = keyframe_period  # versions between periodic keyframes (0: by size, see poll)
        self._keyframe_due: str | None = "first"  # a keyframe goes with the next version (and why)
        self._asked: str | None = None  # a replica behind the board asked for a keyframe (why)
        self._confirm = False  # a replica at the current version asked: the header is repeated
        self._head: View | None = None  # the latest version published
        self._kf_version, self._kf_time, self._kf_size = 0, -math.inf, 0  # the latest keyframe
        self._streamed = -math.inf  # when the latest header was streamed
        self._since_kf = 0  # bytes of stream headers since the latest keyframe (automatic period)
        self.keyframes: Counter[str] = Counter()  # keyframes published, by reason
        self.stream_bytes = 0  # bytes of the stream headers published (about: the JSON of each)
        self._events: list[dict[str, Any]] = []  # applied since the last published version
        # what changed the mission from outside its file (operator tasks, robots joining, robots the
        # board dropped), by event type: such a mission no longer equals its offline rollout
        self.live_events: Counter[str] = Counter()
        self.requests: dict[str, str] = {}  # operator task id -> last status reported on the events topic
        self._join_names: list[str] = []  # names of robots joining, given to the next added agents
        self._scenario_added = 0  # robots a scenario's add_robot events added (named robot_<A0 + k>)
        self.join_refused: dict[str, str] = {}  # robot asking to join -> why it was refused (warned once)
        self.refusals: dict[int, str] = {}  # robot of the mission -> why its agent refuses to take part
        self._refusals_said: set[int] = set()  # robots whose refusal was logged (once per board process)
        self.pose_rejections: dict[int, str] = {}  # robot -> why its latest pose was rejected (e.g. its frame)
        self._joins = TokenBucket(self.JOIN_RATE, 2 * self.JOIN_RATE, now())  # robots taken in
        self._join_slowed = False  # warned that joins come faster than JOIN_RATE
        self.robots_changed = False  # robots were added since the node last published the mission
        self.task_events: list[dict[str, Any]] = []  # hmrta-task-event/1 bodies not yet published
        # robots a scenario adds or loses at time 0, applied as the state is built (robots_changed:
        # the node publishes the mission again with them before its first version)
        self._sync_robots()
        self._scenario_losses()
        self.journal: Journal | None = None
        if journal is not None:
            self._open_journal(Path(journal))
        if not wait_for_robots and not self.started:
            self.start()

    # ------------------------------------------------------------------------------------------
    # journal
    # ------------------------------------------------------------------------------------------
    def _mission_header(self) -> dict[str, Any]:
        return {"format": JOURNAL_FORMAT, "session": self.session, "instance": self.inst.name,
                "instance_sha256": instance_digest(self.inst), "robots": list(self.names), "seed": self.seed,
                "method": self.method, "rules": self.rules.to_dict(), "created": self.created}

    def _open_journal(self, path: Path) -> None:
        header, records, keep, dropped = read_journal(path)
        if dropped:
            self.log("warning", f"journal {path}: dropped {dropped}")
        if header is None:
            self.journal = Journal(path, 0)
            self.journal.append(self._mission_header(), sync=True)
            return
        mine = self._mission_header()
        for k in ("instance_sha256", "robots", "seed", "method", "rules"):
            if header.get(k) != mine[k]:
                if k in ("method", "rules"):  # the same mission, another method: resume it under its own
                    raise JournalError(
                        f"{path}: the mission ran method {header.get('method')!r} and its journal resumes it only "
                        f"under that method ({k} differs: {header.get(k)!r} in the journal, {mine[k]!r} now): "
                        f"restart the board with -p method:=portfolio (the default: it takes the journal's method) "
                        f"or -p method:={header.get('method')}; a new mission needs another journal path")
                raise JournalError(f"{path}: written for another mission ({k} differs: {header.get(k)!r} in the "
                                   f"journal, {mine[k]!r} now); remove it or give another journal path")
        self.session = str(header["session"])
        created = header.get("created")  # (a journal written without it: this process's start)
        if finite(created):
            self.created = float(created)
        for i, rec in enumerate(records):
            try:
                self._replay(rec)
            except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as e:
                raise JournalError(f"{path}: line {i + 2} cannot be replayed ({e})") from None
        self.restarts += 1
        self.replayed = len(records)
        self.seen_status = [None] * len(self.names)  # no agent heard by this process yet (robots that joined too)
        self.journal = Journal(path, keep)
        self._events.append({"type": "resume", "t": float(self.state.clock)})
        self._keyframe_due = "resumed"  # replicas of the previous board process may have missed its last versions
        self.log("info", f"resumed from journal {path}: {len(records)} versions replayed, board version "
                         f"{self.version}, {self.state.n_done}/{self.state.M} tasks done, {len(self.lost)} lost")

    def _replay(self, rec: dict[str, Any]) -> None:
        for ev in rec.get("ev", ()):
            kind = ev["type"]
            if kind == "add_agent" and "name" in ev:
                self._joined(str(ev["name"]))  # before it is added: the name goes to this robot
            self.apply_event(ev)
            if kind == "start":
                self.started = True
                self._started_wall = ev.get("wall")
            elif kind == "drop_agent" and (pose := point_or_none(ev.get("pose"))) is not None:
                self.stopped_at[int(ev["robot"])] = pose
            elif kind == "choice":
                self.accepted.add((int(ev["robot"]), int(ev["version"])))
                if ev.get("latency_ms") is not None:
                    self.latency_ms.append(float(ev["latency_ms"]))
                self.agent_ms.append(float(ev.get("compute_ms", 0.0)))
            elif kind == "arrival":
                a = int(ev["robot"])
                self.ptr[a] = max(self.ptr[a], int(ev["ptr"]))
                self._gate_sig = None  # confirmed outside the gate: recompute every robot
            elif kind == "add_task":
                self.requests[str(ev["name"])] = "accepted"
            elif kind == "resume":
                self.restarts += 1
            if kind in LIVE_EVENTS:
                self.live_events[kind] += 1
        self.version = int(rec["v"])
        self.clock = max(self.clock, float(rec.get("clock", 0.0)))
        self.allowed = max(self.allowed, float(rec.get("horizon", math.inf)), self.clock)
        self.finished = self.finished or rec.get("phase") == "done"
        if rec.get("phase") == "done" and isinstance(rec.get("wall_seconds"), (int, float)):
            self._final_wall = float(rec["wall_seconds"])  # resumed after the end: the mission's own time
        if "rev" in rec and int(rec["rev"]) != self.rev:
            raise ValueError(f"state revision {self.rev} after replay, the journal says {rec['rev']}")
        if "n_done" in rec and int(rec["n_done"]) != self.state.n_done:
            raise ValueError(f"{self.state.n_done} tasks done after replay, the journal says {rec['n_done']}")

    # ------------------------------------------------------------------------------------------
    # inputs
    # ------------------------------------------------------------------------------------------
    def choice(self, c: Any) -> Rejected | None:
        """Validate and apply a decoded choice (attributes ``robot``, ``session``, ``version``,
        ``node``, ``compute_ms``, ``payload``). Returns None if applied, else why not."""
        t_recv = self.now()
        a = self.index.get(c.robot)
        who = f"choice of {c.robot!r} for board {c.version}"

        def no(reason: str, detail: str) -> Rejected:
            self.rejected[reason] += 1
            return Rejected(reason, f"{who}: {detail}", c.robot, c.version)

        if c.session != self.session:
            return no("foreign_session", f"for mission run {c.session!r}, not this one")
        if self.verifier is not None:
            why = self.verifier.verify(c.payload)
            if why is not None:
                code = rejection_code(why)
                self.auth_rejected["choice"][code] += 1
                return no(code, why)
        if a is None:
            return no("unknown_robot", "unknown robot")
        if a in self.lost:
            return no("lost", f"robot was declared lost ({self.lost[a]})")
        if (a, c.version) in self.accepted:
            return no("duplicate", "duplicate (already applied)")
        if c.version != self.version:
            return no("stale", f"board is at version {self.version}")
        if self.finished or self.phase != "decide":
            return no("not_released", f"no decision is open ({self.phase})")
        st = self.state
        if a != st.agent:
            return no("not_your_turn", f"it is {self.names[st.agent]}'s turn")
        mask = st.mask()
        if not 0 <= c.node < len(mask) or not mask[c.node]:
            what = "its depot" if c.node == 0 else f"task {c.node - 1}"
            return no("masked", f"node {c.node} ({what}) is not admissible now")
        self.accepted.add((a, c.version))
        latency = (t_recv - self.released_at) * 1e3
        self.latency_ms.append(latency)
        self.agent_ms.append(float(c.compute_ms))
        st.step(c.node)
        self.rev += 1
        self._events.append({"type": "choice", "t": float(st.clock), "until": float(st.until), "robot": a,
                             "node": int(c.node), "version": int(c.version), "latency_ms": round(latency, 6),
                             "compute_ms": float(c.compute_ms)})
        return None

    def malformed(self) -> None:
        """Count a message that did not decode."""
        self.rejected["malformed"] += 1

    def heartbeat(self, session: str, robots: Sequence[str], payload: Any = None,
                  joining: Sequence[Any] = (), host: str = "", refused: Sequence[Any] = ()) -> str | None:
        """An agent heartbeat naming ``robots`` (and ``joining``: robots asking to join, objects
        with ``robot``, ``species``, ``traits``, ``position``; see :meth:`join`; ``refused``:
        robots whose agents refuse the mission, objects with ``robot`` and ``why``; see
        :meth:`refusal`) from the agent process ``host``; returns a warning text when something
        in it is ignored, or when two processes keep sending heartbeats for one robot (two agents
        driving it)."""
        if session != self.session:
            return None  # agents of another mission run
        if self.verifier is not None:
            why = self.verifier.verify(payload)
            if why is not None:  # keeps nobody alive
                self.auth_rejected["status"][rejection_code(why)] += 1
                named = [*robots, *(r.robot for r in refused)]  # (a refusal speaks for its robot too)
                return f"ignoring heartbeat of {', '.join(named[:4])[:200]}: {why}"
        warn = None
        now = self.now()
        for j in joining:
            warn = self.join(j.robot, j.species, j.traits, j.position) or warn
        unknown = []
        for r in robots:
            a = self.index.get(r)
            if a is None:
                unknown.append(r)
            else:
                self.seen_status[a] = now
                self.refusals.pop(a, None)  # an agent that takes part after all (restarted with the right method)
                if host:
                    warn = self._host_of(a, host, now) or warn
        for r in refused:
            self.refusal(r.robot, r.why)
        if not self.started:
            self._maybe_start()
        return f"heartbeat names unknown robot {unknown[0]!r}" if unknown else warn

    def refusal(self, name: str, why: str) -> None:
        """Robot ``name``'s agent refuses the mission (``why``: its reason, from its heartbeat).
        Taken only for a robot of the mission that no agent has reported to this board process:
        a refusal never drops a robot whose agent is heard (heartbeats and their timeouts decide
        for those), whoever sends it. Each robot's first refusal is logged, once.

        Before the start, the board stops waiting once the agents of every robot not lost have
        refused: they are dropped with their reasons and the mission starts without them (and
        fails), instead of waiting out the start-up timeout; at the timeout, a robot whose agent
        refused is dropped with its reason. A robot whose heartbeat then lists it (an agent
        restarted to take part) is waited for again. After the start, such a robot (which the
        heartbeat timeout would drop as silent) is dropped at once, with its reason."""
        a = self.index.get(name)
        if a is None or a in self.lost or self.finished or self.seen_status[a] is not None:
            return
        why = one_line(why)[:REFUSAL_CHARS]  # one line, bounded (from any publisher)
        if a not in self._refusals_said:
            self._refusals_said.add(a)
            T = self.startup_timeout
            self.log("warning", f"robot {name!r}: its agent refuses the mission: {why}" + (
                "" if self.started else f" (waiting for an agent of it that takes part "
                                        f"{f'until the start-up timeout, {T:g} s' if T > 0 else '(no start-up timeout)'})"))
        if self.started:
            self.lose(a, f"{REFUSED}: {why}")
            return
        self.refusals[a] = why
        if all(b in self.refusals or b in self.lost for b in range(self.state.A)):
            self.log("warning", "the agents of every robot refuse the mission: it starts without them")
            for b in sorted(self.refusals):
                self.lose(b, f"{REFUSED}: {self.refusals[b]}")
            self.start()

    # a robot's heartbeats going back to the process they came from before, within this many seconds
    # of the switch: both processes are alive (a restarted agent's old process has stopped)
    TWO_HOSTS_WINDOW = 10.0
    # robots that ask to join are taken at most this many a second (a burst of twice as many): the
    # agents repeat the request every heartbeat, so the others join moments later, and one
    # unauthenticated heartbeat naming a hundred robots cannot grow the mission by a hundred at once
    JOIN_RATE = 10.0

    def _join_token(self, now: float) -> bool:
        if self._joins.take(now):
            return True
        if not self._join_slowed:
            self._join_slowed = True
            self.log("warning", f"robots ask to join faster than {self.JOIN_RATE:g} a second: the others are "
                                f"taken as their agents ask again")
        return False

    def _host_of(self, a: int, host: str, now: float) -> str | None:
        """Follow which agent process sends robot a's heartbeats; the warning (once per robot) when
        they come from two at once."""
        if a not in self._hosts:
            self._hosts[a] = (host, None, -math.inf)
        last, before, switched = self._hosts[a]
        if host == last:
            return None
        if host == before and now - switched < self.TWO_HOSTS_WINDOW and a not in self._two_hosts:
            self._two_hosts.add(a)
            self._hosts[a] = (host, last, now)
            return (f"robot {self.names[a]!r}: heartbeats from two agent processes ({before} and {last}): two agents "
                    f"drive one robot? Each of its turns is taken from whichever answers first; stop one of them")
        self._hosts[a] = (host, last, now)
        return None

    def join(self, name: str, species: int | None = None, traits: Sequence[float] | None = None,
             position: Sequence[float] | None = None) -> str | None:
        """A robot not in the mission asks to join (its agent's heartbeat): once the mission runs,
        it is added (``add_agent``) at the event time, at ``position`` (where its driver reports
        it) or its species' depot, under its name, and journaled; ``robots_changed`` tells the node
        to republish the mission. Agents repeat the request until the robot is in the mission, so
        one that comes before the start or while a board is replaying is simply added later.
        Returns a warning the first time a request is refused (with the reason), else None."""
        if name in self.index or not self.started or self.finished or self.state.done:
            return None
        if self.verifier is not None:
            why = ("robots cannot join an authenticated mission at run time (its keystore names every robot; "
                   "start the mission with it)")
        else:
            if not self._join_token(self.now()):  # over JOIN_RATE: its agent asks again at its next heartbeat
                return None
            st = self.state
            rec: dict[str, Any] = {"type": "add_agent", "t": self._event_time(), "until": float(st.until),
                                   "name": name}
            for k, v in (("species", species), ("traits", traits), ("position", position)):
                if v is not None:
                    rec[k] = int(v) if k == "species" else [float(x) for x in v]
            self._joined(name)
            try:
                a = self._external(rec)
            except EventRejected as e:
                self._join_names.remove(name)
                why = str(e)
            else:
                self._events.append(rec)
                self.join_refused.pop(name, None)
                where = f"at {tuple(rec['position'])}" if "position" in rec else "at its species' depot"
                self.log("info", f"robot {name} joined the mission at t={rec['t']:.3f} as agent {a} "
                                 f"(species {int(st.inst.agent_species[a])}, {where})")
                return None
        if self.join_refused.get(name) == why:
            return None
        self.join_refused[name] = why
        return f"robot {name!r} cannot join: {why}"

    def pose(self, a: int, x: float, y: float) -> bool:
        """Robot a reports its position (mission coordinates). Returns whether the report can
        change what the board publishes: a new position, or one before the start. A robot that
        reports where it already was (a driver's periodic pose) only shows that it is alive: its
        part of the arrival gate, which reads nothing else of the report, stays as it is."""
        self.seen_pose[a] = self.now()
        moved = self.last_pose[a] != (x, y)
        if moved:
            self.last_pose[a] = (x, y)
            self._gate_dirty.add(a)
        if not self.started:
            self._maybe_start()
            return True
        return moved

    def set_clock(self, t: float) -> bool:
        """The mission clock; returns whether it advanced. The state runs up to it (completions,
        scheduled events and the decisions they bring; journaled as an ``advance`` event when
        anything happened) and holds there.

        A clock past the horizons the board has published (``allowed``; the simulated robots
        never take it there) comes from another publisher on the clock's topic: a second
        sim_robot of another mission, a recording played back, a stray node. The board then
        follows it only up to ``allowed``, and further as each new horizon allows, and warns (at
        most every 10 s): a stray clock cannot run the mission past what the board
        released (tasks completing with nobody there). A clock heard within the horizons (the
        simulated robots' own) is followed as it comes, and forgets the one beyond them, so a
        single stray message does not hurry the rest of the mission."""
        if t <= self.allowed + EPS:
            self._beyond = 0.0
        else:
            now = self.now()
            if now - self._beyond_warned >= 10.0:  # at most every 10 s, however often it comes
                self._beyond_warned = now
                self.log("warning", f"mission clock {t:.3f} s is past the board's horizon {self.allowed:.3f} s: "
                                    f"followed only up to the horizon (is another sim_robot, a recording being "
                                    f"played back, or another node publishing on the mission clock's topic?)")
            self._beyond = max(self._beyond, t)
            t = self.allowed
        return self._to_clock(t)

    def foreign_clock(self, t: float) -> str | None:
        """Why ``t``, the first mission clock this board process hears, cannot be its own mission's
        (None where it can): a board that starts its mission afresh (nothing replayed from a
        journal) has released no time beyond ``allowed`` (0 before the start), and its own
        simulated robots never take the clock past that. A clock already beyond it is another
        mission's: a sim_robot still following the board of an earlier run (it keeps the mission
        it started with, so this one's robots would never move), a second mission on this ROS
        domain, a recording played back. Followed up to the horizons (as :meth:`set_clock` does
        with a stray clock mid-mission), it would run this mission on their time and hold it
        forever at an arrival nobody drives to."""
        if self.replayed or t <= self.allowed + EPS:
            return None
        return (f"the mission clock is at {t:.3f} s before this board released any time (horizon "
                f"{self.allowed:.3f} s): it is another mission's clock; a sim_robot still following an earlier board "
                f"(it keeps its first mission): restart this board on that board's journal (-p journal:=FILE) to "
                f"resume its mission, or restart sim_robot for a new one; or another mission on this ROS domain "
                f"(give each its own mission_namespace or ROS_DOMAIN_ID)")

    def _to_clock(self, t: float) -> bool:
        """Move the clock (and the state, held there) to ``t`` if it is later; whether it moved."""
        if t > self.clock:
            self.clock = t
            if self.started and not self.finished:
                self._advance(t + EPS)
            return True
        return False

    def _advance(self, until: float) -> None:
        st = self.state
        if st.done or st.agent is not None:
            st.until = max(st.until, until)
            return
        before = (float(st.clock), st.agent, st.done, st.decisions, len(st.log), int(st.n_done), int(st.n_cancelled))
        self._held(lambda: st.advance_to(until), bump=False)
        if (float(st.clock), st.agent, st.done, st.decisions, len(st.log), int(st.n_done),
                int(st.n_cancelled)) != before:
            self.rev += 1
            self._events.append({"type": "advance", "t": float(st.clock), "until": float(st.until)})

    def _maybe_start(self) -> None:
        if all(s is not None for s in self.seen_status) and all(s is not None for s in self.seen_pose):
            self.start()

    def start(self) -> None:
        self.started = True
        self.t_start = self.now()
        self._events.append({"type": "start", "t": float(self.state.clock), "wall": time.time()})
        self.log("info", "all robots present: mission starts" if not self.lost else
                 f"mission starts without {len(self.lost)} robot(s)")

    def tick(self) -> None:
        """The watchdog (call it periodically): start-up timeout, heartbeat and decision timeouts."""
        if self.finished:
            return
        now = self.now()
        if self._ticked is not None and now - self._ticked > STALL_GAP:
            self._stalled(now, now - self._ticked)
        self._ticked = now
        if self.t_start is None and self.started:  # replayed from a journal: everyone gets a fresh timeout
            self.t_start = now
        if not self.started:
            if self.startup_timeout > 0 and now - max(self.t_created, self._resumed) > self.startup_timeout:
                for a in range(self.state.A):
                    if a in self.refusals:  # (never a robot an agent reported: heartbeat)
                        self.lose(a, f"{REFUSED}: {self.refusals[a]}")
                    elif self.seen_pose[a] is None and a in self.pose_rejections:  # heard, but never usable
                        self.lose(a, f"{POSES_REJECTED}: {self.pose_rejections[a]}")
                    elif self.seen_status[a] is None or self.seen_pose[a] is None:
                        self.lose(a, NEVER_REPORTED)
                self.start()
            return
        T = self.heartbeat_timeout
        if T > 0:
            for a in range(self.state.A):
                if a in self.lost:
                    continue
                # liveness is the agent's heartbeat: a silent pose (a robot standing still whose
                # driver reports only on updates, as amcl does) drops nobody
                seen = self.seen_status[a]
                if seen is None and self.restarts:  # not heard by this process of a board restarted
                    # on its journal: it is found by the agents' publishers only after DDS discovery
                    # (seconds, more on a loaded machine; heartbeats sent before are not delivered),
                    # so the start-up timeout applies, as at the first start
                    if self.startup_timeout > 0 and now - max(self.t_start, self._resumed) > self.startup_timeout:
                        self.lose(a, f"no agent heartbeat since the board restarted ({self.startup_timeout:g} s)")
                elif now - max(seen or 0.0, self.t_start, self._resumed) > T:
                    self.lose(a, f"no agent heartbeat for {T:g} s")
        if (self.decision_timeout > 0 and self.phase == "decide"
                and now - max(self.released_at, self._resumed) > self.decision_timeout):
            self.lose(self.state.agent, f"no decision within {self.decision_timeout:g} s")
        self._check_legs(now)

    @property
    def resumed_at(self) -> float:
        """When (``now()``) the board last ran again after a stall of its own or was restarted on
        its journal (-inf if never): what it was sent before is still arriving, so silences count
        from then."""
        return self._resumed

    def _stalled(self, now: float, gap: float) -> None:
        """The board itself did not run for ``gap`` seconds (more than STALL_GAP): what the robots
        sent meanwhile is still unread in its queues, or lost on the way and being repaired by the
        middleware (a reliable reader delivers nothing newer until then), so every robot's
        heartbeat, decision and start-up timeout counts afresh from ``now``, as on a board restarted
        on its journal, and leg timeouts leave the gap out. Without this, a board resumed after a
        pause longer than the heartbeat timeout drops every robot at its first tick."""
        self._resumed = now
        for tm in self.leg_timers.values():
            if tm.reached is not None:
                tm.reached += gap
        self.log("warning", f"the board did not run for {gap:.1f} s (its process stopped or starved): "
                            f"every robot's timeout counts afresh")

    # ------------------------------------------------------------------------------------------
    # stuck robots: leg timeouts
    # ------------------------------------------------------------------------------------------
    def awaited(self, a: int) -> tuple[int, int] | None:
        """(index in robot a's leg log, node) of the departed leg whose arrival the board waits
        for (its next unconfirmed task, or its depot once every task is closed), or None."""
        st = self.state
        if a in self.lost or st.mode[a] == LOST or not self.started or self.finished:
            return None
        log = st.leg_log[a] if a < len(st.leg_log) else []
        if st.done:
            i = self._last_leg(a, lambda n: n != RESEND)
            if i is None or log[i][0] != 0 or self._near(a, st.inst.depots[a]):
                return None
        else:
            route = st.routes[a]
            if self.ptr[a] >= len(route):
                return None
            node = 1 + int(route[self.ptr[a]])
            i = self._last_leg(a, lambda n: n == node)
            if i is None:
                return None
        return (i, log[i][0]) if log[i][3] <= self.clock + EPS else None

    def _last_leg(self, a: int, want: Callable[[int], bool]) -> int | None:
        log = self.state.leg_log[a]
        return next((i for i in range(len(log) - 1, -1, -1) if want(log[i][0])), None)

    def _check_legs(self, now: float) -> None:
        """Re-send the goal of a robot whose leg timed out once; drop it after a second timeout."""
        F, F0 = self.leg_timeout_factor, self.leg_timeout_floor
        if F <= 0 and F0 <= 0:
            return
        st = self.state
        for a in range(st.A):
            w = self.awaited(a)
            if w is None:
                self.leg_timers.pop(a, None)
                continue
            i, node = w
            tm = self.leg_timers.get(a)
            if tm is None or tm.leg != i:
                _, x, y, depart = st.leg_log[a][i]
                arrive = st.leg_arrive[a][i]
                resent = any(g == (RESEND, x, y, depart) for g in st.leg_log[a][i + 1:])  # replayed journal
                tm = self.leg_timers[a] = LegTimer(i, depart, arrive, max(0.0, F) * (arrive - depart) + max(0.0, F0),
                                                   resent=resent)
            if tm.reached is None and self.clock >= tm.arrive - EPS:
                tm.reached = now
            elapsed = max(0.0, min(self.clock, tm.arrive) - tm.depart) + (now - tm.reached if tm.reached else 0.0)
            what = "its depot" if node == 0 else f"task {node - 1}"
            if elapsed > 2 * tm.limit and tm.resent:
                self.lose(a, f"stuck: no arrival at {what} within {2 * tm.limit:.1f} s "
                             f"(goal re-sent after {tm.limit:.1f} s; {self._away(a, i)})")
                self.leg_timers.pop(a, None)
            elif elapsed > tm.limit and not tm.resent:
                tm.resent = True
                st.log_resend(a, i)
                self.rev += 1
                self._events.append({"type": "resend", "t": float(self.clock), "robot": a, "leg": i})
                self.log("warning", f"robot {self.names[a]} has not arrived at {what} {tm.limit:.1f} s after it "
                                    f"departed (planned travel {tm.arrive - tm.depart:.1f} s; {self._away(a, i)}): "
                                    f"re-sending its goal")

    def _away(self, a: int, i: int) -> str:
        """How far robot a's last pose is from the goal of its leg i, in metres."""
        _, x, y, _ = self.state.leg_log[a][i]
        p = self.last_pose[a]
        if p is None:
            return "no pose"
        d = math.hypot(p[0] - x, p[1] - y) * self.scale
        return f"last pose {d:.3f} m from the goal (tolerance {self.tolerance * self.scale:.3f} m)"

    def pose_rejected(self, a: int, why: str) -> None:
        """Robot a's pose was rejected (``why``: e.g. its frame): said with the robot's name if it
        is dropped at the start-up timeout for want of a pose, instead of "never reported"."""
        if 0 <= a < len(self.seen_pose):
            self.pose_rejections[a] = one_line(why)[:REFUSAL_CHARS]

    def waiting(self) -> list[str]:
        """Robots whose agent heartbeat or pose was never seen (before the start)."""
        return [n for a, n in enumerate(self.names) if self.seen_status[a] is None or self.seen_pose[a] is None]

    def lose(self, a: int, reason: str) -> list[int]:
        """Drop robot a at the mission clock (its commitments are released); returns the tasks
        this cancels."""
        if a in self.lost or self.finished:
            return []
        t = self._event_time()
        cancelled = self._drop(a, reason, t)
        ev = {"type": "drop_agent", "t": t, "until": float(self.state.until), "robot": a, "reason": reason}
        if self.last_pose[a] is not None:  # where the robot itself last said it was (the plan may differ)
            self.stopped_at[a] = self.last_pose[a]
            ev["pose"] = list(self.last_pose[a])
        self._events.append(ev)
        extra = f"; cancelled task(s) {cancelled} (no longer satisfiable)" if cancelled else ""
        self.log("warning", f"robot {self.names[a]} lost ({reason}): its commitments are released{extra}")
        return cancelled

    def _event_time(self) -> float:
        """When an event given now applies: the mission clock, or the instant of the pending
        decision (the clock is held at it until the decision is made)."""
        st = self.state
        return float(st.clock) if st.agent is not None else max(float(self.clock), float(st.clock))

    def _sync_robots(self) -> None:
        """Give robots the state added (a scenario's add_robot, a robot that joined) a name and
        the board's per-robot bookkeeping; ``robots_changed`` tells the node to republish the
        mission."""
        st = self.state
        while len(self.names) < st.A:
            a = len(self.names)
            if self._join_names:
                name = self._join_names.pop(0)
            else:  # a scenario's add_robot event: the k-th is robot_<robots at the start + k>
                name = f"robot_{self.inst.n_agents + self._scenario_added}"
                self._scenario_added += 1
            while name in self.index:
                name += "_"
            self.names.append(name)
            self.index[name] = a
            self.seen_status.append(self.now() if self.started else None)
            self.seen_pose.append(self.now() if self.started else None)
            self.last_pose.append(None)
            self.ptr.append(0)
            self.robots_changed = True
            self._keyframe_due = self._keyframe_due or "robots"
        st.grow_legs()

    def _joined(self, name: str) -> None:
        """The name of the robot the next add_agent creates (a robot that joined)."""
        self._join_names.append(name)

    # ------------------------------------------------------------------------------------------
    # operator requests (hmrta-task-request/1) and task events (hmrta-task-event/1)
    # ------------------------------------------------------------------------------------------
    def _not_taking(self, op: str, rid: str) -> str | None:
        """Why the mission takes no operator request ``op`` (of task id ``rid``) now, or None. Once
        every task is done or cancelled, while the robots go home, an add reopens the mission
        (MissionState.add_task), unless a robot was lost since (the ended state no longer takes
        losses, so it would count on that robot); a cancel there of an id the mission does not
        know is left to the check of ids (no such task)."""
        st = self.state
        if not self.started:
            return "the mission is not running"
        if not (st.done or self.finished):
            return None
        if self.finished or st.failure:
            return "the mission is over"
        lost_on_the_way = any(st.mode[a] != LOST for a in self.lost)
        if op == "add":
            return ("the mission is over (every task is done; the robots are going home, and a robot was lost on "
                    "the way)" if lost_on_the_way else None)
        if not self._names_a_task(rid):
            return None  # no such task: said as such
        if lost_on_the_way:
            return "the mission is over (every task is done or cancelled; the robots are going home)"
        m = st.names.index(rid) if rid in st.names else _task_index(rid, st.M)
        which = f"task {rid!r}: already {STATUS_NAMES[st.status[m]]}; " if m is not None else ""
        return (f"{which}nothing to cancel: every task is done or cancelled (the robots are going home; a task "
                f"added now reopens the mission)")

    def _id_problem(self, op: str, rid: str) -> str | None:
        """Why task id ``rid`` cannot be added (taken, or decimal digits) or cancelled (no such
        task), or None."""
        if op == "add" and rid in self.requests:
            return f"task {rid!r}: a task with this id exists already"
        if op == "add" and rid.isascii() and rid.isdigit():
            return (f"task {rid!r}: an id of decimal digits names a task of the mission by its index (hmrta-task "
                    f"cancel {rid}): choose an id with a letter")
        if op == "cancel" and not self._names_a_task(rid):
            return (f"task {rid!r}: no task with this id (an operator's task by its id, a task of the mission "
                    f"by its index 0..{self.state.M - 1})")
        return None

    def _names_a_task(self, rid: str) -> bool:
        """Whether ``rid`` is an operator's task id or the index of a task of the mission."""
        return rid in self.requests or _task_index(rid, self.state.M) is not None

    def task_request(self, op: str, rid: str, task: dict[str, Any] | None = None,
                     request_id: str = "") -> dict[str, Any]:
        """Add (``op`` "add", ``task`` {location, requirements, duration}) or cancel a task by
        its client id; returns the answer (event "accepted" or "rejected" with a reason, and the
        client's ``request_id`` echoed when given), also queued in :attr:`task_events`. Accepted
        requests are journaled like every event."""
        st = self.state
        ans: dict[str, Any] = {"id": rid, "op": op}
        if request_id:
            ans["request_id"] = request_id
        why = self._not_taking(op, rid) or self._id_problem(op, rid)
        if why is None:
            rec: dict[str, Any] = {"type": "add_task" if op == "add" else "cancel_task", "t": self._event_time(),
                                   "until": float(st.until), "name": rid}
            if op == "add":
                rec["task"] = task
            elif rid not in self.requests:  # a task of the mission, by its index
                del rec["name"]
                rec["task"] = ans["task"] = _task_index(rid, st.M)
            elif rid in st.names:  # an operator's task: say which task it is, as for an add
                ans["task"] = st.names.index(rid)
            try:
                self._external(rec)
            except EventRejected as e:
                why = str(e)
            else:
                self._events.append(rec)
                if op == "add":
                    self.requests[rid] = "accepted"
                    ans["task"] = st.names.index(rid) if rid in st.names else None
        ans.update({"event": "rejected", "reason": why} if why is not None else {"event": "accepted"})
        ans["t"] = float(st.clock) if why is None else float(max(self.clock, st.clock))
        self.task_events.append(ans)
        return ans

    def _track(self) -> None:
        """Queue started / done / cancelled events of operator tasks whose status changed."""
        st = self.state
        order = {"accepted": 0, "started": 1, "done": 2, "cancelled": 2}
        for rid, last in self.requests.items():
            if rid not in st.names:
                continue
            m = st.names.index(rid)
            now = {"in_progress": "started", "done": "done", "cancelled": "cancelled"}.get(STATUS_NAMES[st.status[m]])
            if now is None or now == last:
                continue
            if now == "started" and self.clock < float(st.start[m]) - EPS:
                continue  # the coalition is complete; the task starts when its last member arrives
            if now == "done" and order[last] < 1:
                self.task_events.append({"id": rid, "event": "started", "task": m, "t": float(st.start[m])})
            t = float(st.finish[m]) if now == "done" else float(st.start[m]) if now == "started" else float(st.clock)
            self.task_events.append({"id": rid, "event": now, "task": m, "t": t})
            self.requests[rid] = now

    # ------------------------------------------------------------------------------------------
    # the clock and arrival confirmations
    # ------------------------------------------------------------------------------------------
    def _near(self, a: int, xy) -> bool:
        p = self.last_pose[a]
        return p is not None and math.hypot(p[0] - xy[0], p[1] - xy[1]) <= self.tolerance

    def _departed(self, a: int, node: int) -> bool:
        """Whether robot a's leg to ``node`` has departed (a robot near a task before it set off
        for it, a neighbour of its previous task, has not arrived there)."""
        i = self._last_leg(a, lambda n: n == node)
        return i is not None and self.state.leg_log[a][i][3] <= self.clock + EPS

    def _m(self, xy) -> str:
        """A mission position in metres, readably."""
        return f"({float(xy[0]) * self.scale:.2f}, {float(xy[1]) * self.scale:.2f}) m"

    def gate(self) -> float:
        """Earliest start of a task with a member not yet confirmed there (inf: none); confirms
        (``ptr``, journaled ``arrival`` events, in robot order) the arrivals it passes.

        Incremental: each robot's part (its earliest unconfirmed task's start) is kept and
        recomputed only for the robots it can have changed for: every robot when the mission's
        structure changed (a keyframe, robots or tasks added, cancelled or lost); after a
        decision or an event, the robots whose route or leg log grew and those whose task (where
        their scan stopped) got a new start time (:meth:`_gate_changed`); a robot that reported
        a pose; and, when the clock moved, the robots found at their task before their leg there
        had departed; and, as a safety net, every robot every
        ``GATE_RESCAN`` seconds while the gate holds the mission clock (a part kept by mistake
        could delay the mission by that long, never hold it). So a pose message costs one robot's
        scan, not the whole team's. ``CHECK_GATE`` (tests) compares every call with the full scan
        (:meth:`_gate_reference_parts`)."""
        st = self.state
        sig = (id(st), st.A, st.M, int(st.n_cancelled), st.done, len(self.lost))
        progress = (self.rev, st.decisions, len(st.log), int(st.n_done), float(st.clock))
        if sig != self._gate_sig:  # the structure changed (or an arrival was confirmed elsewhere)
            self._gate_sig, self._gate_progress = sig, progress
            self._gate_part = np.full(st.A, math.inf)  # [A] each robot's part of the gate
            self._gate_task = np.full(st.A, -1, dtype=np.int64)
            self._gate_waiting = set()
            todo: Iterable[int] = range(st.A)
            self._gate_lengths()
        else:
            todo = self._gate_dirty
            if progress != self._gate_progress:  # decisions, completions: the robots they can have changed
                self._gate_progress = progress
                todo = todo | self._gate_changed()
            if self.clock != self._gate_clock:
                todo = todo | self._gate_waiting
            todo = sorted(todo)
        self._gate_dirty = set()
        self._gate_clock = self.clock
        for a in todo:
            self._gate_part[a] = self._gate_robot(a)
        now = self.now()
        if isinstance(todo, range):
            self._gate_rescanned = now
        gate = float(self._gate_part.min()) if st.A else math.inf
        if CHECK_GATE:  # every robot's part, not just the gate
            ptr, n_events = list(self.ptr), len(self._events)
            parts = self._gate_reference_parts()
            assert np.array_equal(parts, self._gate_part) and self.ptr == ptr and len(self._events) == n_events, \
                f"incremental arrival gate differs from the full scan at robots " \
                f"{np.flatnonzero(parts != self._gate_part).tolist()}"
        if gate <= self.clock + EPS and now - self._gate_rescanned >= GATE_RESCAN:
            # the gate has held the mission clock for a while: every robot afresh (the full scan),
            # so that a part kept by mistake could never hold a mission
            self._gate_rescanned = now
            for a in range(st.A):
                self._gate_part[a] = self._gate_robot(a)
            gate = float(self._gate_part.min())
        return gate

    def _gate_lengths(self) -> None:
        """Record every robot's route and leg-log lengths, and every task's start, as the gate saw them."""
        st = self.state
        self._gate_rlen = np.fromiter(map(len, st.routes[:st.A]), dtype=np.int64, count=st.A)  # [A]
        self._gate_llen = st.leg_seqs[:st.A].copy()  # [A]
        self._gate_start = st.start[:st.M].copy()  # [M]

    def _gate_changed(self) -> set[int]:
        """The robots whose part a decision or an event can have changed since the last gate: a
        longer route or leg log (it committed, was given a leg), or a new start time of the task
        its scan stopped at (a task's start is set when its coalition is complete)."""
        old_r, old_l, old_s = self._gate_rlen, self._gate_llen, self._gate_start
        self._gate_lengths()
        new_s = self._gate_start
        moved = ~((new_s == old_s) | (np.isnan(new_s) & np.isnan(old_s)))  # [M] a start set or changed
        changed = (self._gate_rlen != old_r) | (self._gate_llen != old_l)  # [A]
        if moved.any():
            t = self._gate_task
            changed |= (t >= 0) & moved[np.maximum(t, 0)]
        return set(np.flatnonzero(changed).tolist())

    def _gate_robot(self, a: int) -> float:
        """Robot a's part of :meth:`gate` (it confirms a's arrivals)."""
        st = self.state
        self._gate_waiting.discard(a)
        self._gate_task[a] = -1
        if st.mode[a] == LOST:
            return math.inf
        locs = st.inst.task_locations
        route = st.routes[a]
        part = math.inf
        p = min(self.ptr[a], len(route))
        while p < len(route):
            m = route[p]
            if self._near(a, locs[m]):
                if self._departed(a, 1 + int(m)):
                    p += 1
                    continue
                self._gate_waiting.add(a)  # there before its leg departed: the clock can change this
            self._gate_task[a] = m
            s = st.start[m]
            if s == s:  # not NaN: the task has its coalition and a start time
                part = float(s)
            break
        if p != self.ptr[a]:
            self.ptr[a] = p
            self._events.append({"type": "arrival", "t": float(st.clock), "robot": a, "ptr": p})
        return part

    def _gate_reference_parts(self) -> np.ndarray:
        """Every robot's part of the gate computed afresh (what the incremental :meth:`gate` must
        hold); the incremental bookkeeping is left as it was."""
        waiting, tasks = set(self._gate_waiting), self._gate_task.copy()
        parts = np.array([self._gate_robot(a) for a in range(self.state.A)], dtype=float)  # [A]
        self._gate_waiting, self._gate_task = waiting, tasks
        return parts

    def waiting_for(self) -> str:
        """What the clock is waiting for (diagnostics)."""
        st = self.state
        locs = st.inst.task_locations
        if st.done:
            away = [self.names[a] for a in range(st.A)
                    if a not in self.lost and not self._near(a, st.inst.depots[a])]
            return f"clock {self.clock:.3f} s, robots not yet home: {', '.join(away[:10]) or 'none'}"
        late, due = [], []  # unconfirmed arrivals; those of tasks due to start by now (holding the clock)
        for a in range(st.A):
            route = st.routes[a]
            if a not in self.lost and self.ptr[a] < len(route):
                m = int(route[self.ptr[a]])
                if st.start[m] == st.start[m]:
                    p = self.last_pose[a]
                    where = "no pose yet" if p is None else (
                        f"last pose {self._m(p)}, {math.hypot(p[0] - locs[m][0], p[1] - locs[m][1]) * self.scale:.2f} m "
                        f"from the task")
                    late.append(f"{self.names[a]} at task {m} (starts t={float(st.start[m]):.3f} s, {where}, "
                                f"task at {self._m(locs[m])}, tolerance {self.tolerance * self.scale:.2f} m)")
                    if float(st.start[m]) <= self.clock + EPS:
                        due.append(late[-1])
        return (f"clock {self.clock:.3f} s, plan at {float(st.clock):.3f} s; arrivals not confirmed: "
                f"{'; '.join((due or late)[:10]) or 'none'}")

    def _target(self) -> tuple[str, int | None, float]:
        """(phase, decider, horizon) from the state, the clock and the confirmations; sets
        ``finished`` when the mission is over."""
        if self.finished:
            return "done", None, float(self.clock)
        if not self.started:
            return "starting", None, 0.0
        st = self.state
        if st.done:
            alive = [a for a in range(st.A) if a not in self.lost]
            final = max([float(st.arrive[a]) for a in alive] + [float(st.clock)])
            if ((st.failure and not st.n_cancelled)  # deadlock / time limit: nobody is going home
                    or (self.clock >= final - EPS and all(self._near(a, st.inst.depots[a]) for a in alive))):
                self.finished = True
                return "done", None, float(self.clock)
            return "closing", None, final
        gate = self.gate()
        t = float(st.clock)
        if st.agent is None:  # held until the next completion or scheduled event
            nxt = min([float(st.events[0][0])] if st.events else [], default=math.inf)
            nxt = min([nxt, float(st.pending[0][0])] if st.pending else [nxt])
            h = min(nxt, gate)
            return "wait", None, h if math.isfinite(h) else max(t, float(self.clock))
        if self.clock >= t - EPS and gate > t + EPS:
            return "decide", st.agent, t
        return "wait", None, min(t, gate)

    def _legs_now(self) -> tuple:
        st = self.state
        return tuple(st.legs(a) for a in range(st.A))

    # ------------------------------------------------------------------------------------------
    # publishing: the stream of versions and the keyframes
    # ------------------------------------------------------------------------------------------
    def request(self, version: int, reason: str = "") -> None:
        """A replica asks for a keyframe (hmrta-keyframe-request/1): it is at ``version`` (-1:
        it has none). A replica at the current version gets the current header again (it learns
        that it is up to date); any other gets a keyframe of the current version, at most one
        every KEYFRAME_INTERVAL seconds (a repeat of the latest keyframe's version at most every
        KEYFRAME_REPEAT seconds). Answered by the next :meth:`poll`."""
        if version == self.version and version > 0:
            self._confirm = True
        else:
            self._asked = self._asked or (reason or "requested")

    def poll(self) -> View | None:
        """The board message to publish now, or None if nothing published changed. A new
        version carries the events applied since the previous one (journaled, fsynced, first)
        and the state's digest; it is also a keyframe (legs and full state) when it is the
        first, after a restart on the journal, after robots were added, at the end, when a
        replica asked, and periodically: every ``keyframe_period`` versions, or (0) once the
        stream has carried as many bytes as the latest keyframe, so that keyframes cost at most
        as much as the stream."""
        if self._beyond > self.clock < self.allowed:  # a clock heard past an earlier horizon: up to this one
            self._to_clock(min(self._beyond, self.allowed))
        phase, decider, horizon = self._target()
        self._track()
        key = (self.rev, phase, decider, horizon)
        if key == self._key:
            return self._answer()
        self._key = key
        self.phase = phase
        self.version += 1
        self.allowed = max(self.allowed, float(horizon))
        st = self.state
        events, self._events = self._events, []
        self.live_events.update(ev["type"] for ev in events if ev["type"] in LIVE_EVENTS)
        if self.journal is not None:
            rec: dict[str, Any] = {"v": self.version, "rev": self.rev, "n_done": int(st.n_done), "phase": phase,
                                   "clock": float(self.clock), "horizon": float(horizon)}
            if events:
                rec["ev"] = events
            if phase == "done":
                rec["wall_seconds"] = self.wall_seconds()
            self.journal.append(rec, sync=bool(events) or phase == "done")
        if phase == "decide":
            self.released_at = self.now()  # latency: board update -> choice received
        self._head = View(self.session, self.version, self.version - 1, self.rev, phase, decider, float(st.clock),
                          float(horizon), int(st.n_done), int(st.n_cancelled), st.M, tuple(sorted(self.lost)),
                          tuple(events), state_digest(st))
        self._confirm = False
        size = HEADER_BYTES + (len(json.dumps(events, separators=(",", ":"))) if events else 2)
        self._since_kf += size
        self.stream_bytes += size
        self._streamed = self.now()
        reason = self._keyframe_due or ("done" if phase == "done" else None)
        if reason is None and self._asked is not None and self.now() - self._kf_time >= KEYFRAME_INTERVAL:
            reason = "requested"
        if reason is None and (self.version - self._kf_version >= self.keyframe_period if self.keyframe_period
                               else self._since_kf >= self._kf_size):
            reason = "period"
        return self._keyframe(reason, stream=True) if reason else self._head

    def _answer(self) -> View | None:
        """No new version: answer the replicas that asked (a keyframe, or the header again), and
        stream the latest header again every HEADER_REPEAT seconds, so that a replica that
        missed the latest version finds out."""
        h = self._head
        if h is None:
            return None
        now = self.now()
        if (self._asked is not None and now - self._kf_time >= KEYFRAME_INTERVAL
                and (self._kf_version != h.version or now - self._kf_time >= KEYFRAME_REPEAT)):
            return self._keyframe("requested", stream=False)
        if self._confirm or now - self._streamed >= HEADER_REPEAT:
            self._confirm = False
            self._streamed = now
            return h
        return None

    def _keyframe(self, reason: str, stream: bool) -> View:
        """The latest version as a keyframe: its header with the legs and the state snapshot
        (serialised once per state revision) and ``until``."""
        st, h = self.state, self._head
        if self._cache_rev != self.rev:
            self._cache_rev = self.rev
            self._legs = self._legs_now()
            self._state_json = json.dumps(st.snapshot(), separators=(",", ":"))
        self._keyframe_due = self._asked = None
        self._kf_version, self._kf_time, self._since_kf = h.version, self.now(), 0
        self._kf_size = len(self._state_json)
        self.keyframes[reason] += 1
        return dataclasses.replace(h, keyframe=True, stream=stream, reason=reason, until=float(st.until),
                                   legs=self._legs, state_json=self._state_json)

    # ------------------------------------------------------------------------------------------
    def wall_seconds(self) -> float:
        """Wall seconds of the mission: from its start (by the first board process, across
        restarts) to now, or to its end once it is done (then fixed, also for a board resumed
        on the finished journal later)."""
        if self._final_wall is not None:
            return self._final_wall
        wall = self.now() - (self.t_start or self.t_created)
        if self.restarts and isinstance(self._started_wall, (int, float)):  # since the first board process started it
            wall = max(wall, time.time() - self._started_wall)
        if self.finished:
            self._final_wall = wall = round(wall, 6)  # as the journal's done version keeps it
        return wall

    def result(self) -> Solution:
        """The mission's hmrta-solution/1 (final once ``finished``)."""
        st = self.state
        wall = self.wall_seconds()
        # compute: what the agents spent deciding (each choice's compute_ms, journaled), as a
        # solve's compute is its planning time; the mission's own time is mission_wall_seconds
        sol = solution_from_state(st, self.method, self.seed, round(sum(self.agent_ms) / 1000.0, 6))
        dyn = sol.extra.get("dynamic")
        if isinstance(dyn, dict) and self.stopped_at:  # a lost robot's last reported position (copies: the
            dyn["events"] = [{**e, "reported_at": list(self.stopped_at[e["agent"]])}  # state's log stays as it is)
                             if e.get("type") == "drop_agent" and e.get("agent") in self.stopped_at else e
                             for e in dyn.get("events", ())]
        alive = [a for a in range(st.A) if a not in self.lost]
        sol.extra.update({
            "transport": "ros2",
            "robots": self.names,
            "lost_robots": [self.names[a] for a in sorted(self.lost)],
            "lost_reasons": {self.names[a]: r for a, r in sorted(self.lost.items())},
            "undone_tasks": [m for m in range(st.M) if st.status[m] != DONE],
            "mission_wall_seconds": round(wall, 3),
            "decision_latency_ms": {"median": _r(statistics.median(self.latency_ms) if self.latency_ms else None),
                                    "p99": _r(percentile(self.latency_ms, 99)), "n": len(self.latency_ms)},
            "agent_compute_ms": {"median": _r(statistics.median(self.agent_ms) if self.agent_ms else None),
                                 "p99": _r(percentile(self.agent_ms, 99))},
            "rejected_messages": dict(self.rejected),
            "authenticated": self.verifier is not None,
            "auth_rejections": {k: dict(v) for k, v in self.auth_rejected.items()},
            "board_versions": self.version,
            "live_events": dict(self.live_events),
            "board_keyframes": dict(self.keyframes),
        })
        if self.journal is not None:
            sol.extra["journal"] = str(self.journal.path)
            sol.extra["board_restarts"] = self.restarts
        if self.lost and alive:
            sol.extra["home_time"] = max(float(st.arrive[a]) for a in alive)
        if not sol.success:  # robots dropped with a reason an operator can act on (their agents', their poses')
            for reason, what, says in ((REFUSED, "refused by their agents", "saying"),
                                       (POSES_REJECTED, "had every pose rejected", "")):
                hit = [(self.names[a], r[len(reason) + 2:]) for a, r in sorted(self.lost.items())
                       if r.startswith(f"{reason}: ")]
                if hit:
                    sol.extra["failure"] = (
                        f"{sol.extra.get('failure') or 'the mission did not succeed'}; {len(hit)} of {st.A} robot(s) "
                        f"{what} ({', '.join(n for n, _ in hit[:5])}{', ...' if len(hit) > 5 else ''}), "
                        f"{hit[0][0]}'s{' ' + says if says else ''}: {hit[0][1]}")
        never = [self.names[a] for a, r in sorted(self.lost.items()) if r == NEVER_REPORTED]
        if not sol.success and never:  # the likely cause: processes that never came up on this domain
            sol.extra["failure"] = (
                f"{sol.extra.get('failure') or 'the mission did not succeed'}; {len(never)} of {st.A} robot(s) "
                f"never reported within the start-up timeout ({self.startup_timeout:g} s): "
                f"{', '.join(never[:5])}{', ...' if len(never) > 5 else ''} (is sim_robot or the robots' driver "
                f"running, and an agent for each robot, on this ROS domain? An agent that refuses the mission's method "
                f"exits 2 and says why in its log)")
        return sol

    def close(self) -> None:
        if self.journal is not None:
            self.journal.close()


class _Replay(BoardCore):
    """A board's state machine from the mission's initial state, as the board builds it."""

    def __init__(self, inst: Instance, seed: int, rules: Rules):
        self.state = BoardState(inst, seed=seed, rules=rules)
        self.rev, self.lost = 0, {}


def replay_journal(inst: Instance, path: str | os.PathLike, seed: int, rules: Rules) -> tuple[BoardCore, int, float]:
    """The state machine a board's journal leaves (``inst``, ``seed``, ``rules``: what the board
    was started with), its last version and that version's mission clock (0, 0.0 for a journal
    with no version yet), without writing to the journal. Raises JournalError for a journal that
    cannot be read and ValueError for one that does not fit the mission."""
    _, records, _, _ = read_journal(path)
    core = _Replay(inst, seed, rules)
    for rec in records:
        for ev in rec.get("ev", ()):
            core.apply_event(ev)
    last = records[-1] if records else {}
    return core, int(last.get("v", 0)), float(last.get("clock", 0.0))


def check_journal_decisions(inst: Instance, path: str | os.PathLike, decide: Callable[[MissionState], int],
                            seed: int, rules: Rules) -> tuple[int, str | None]:
    """Replay a board's journal from the mission's initial state (``inst``, ``seed``, ``rules``:
    what the board was started with) and ask ``decide`` at every choice it records, on the state
    the robot decided on: (choices that agree, the first that does not, described, or None).

    The offline check of a live mission that changed while it ran (operators' tasks, robots lost
    or joining): the events come from the journal, in the order the board applied them, so the
    check holds every decision to the method's, whatever the events. Raises JournalError for a
    journal that cannot be read and ValueError for one that does not fit the mission."""
    _, records, _, _ = read_journal(path)
    core = _Replay(inst, seed, rules)
    agree = 0
    for rec in records:
        for ev in rec.get("ev", ()):
            if ev.get("type") == "choice":
                want = int(decide(core.state))
                if want != int(ev["node"]):
                    return agree, (f"board version {rec.get('v')}, mission time {float(core.state.clock):.3f}: robot "
                                   f"{ev['robot']} chose node {ev['node']}, the method node {want}")
                agree += 1
            core.apply_event(ev)
    return agree, None
