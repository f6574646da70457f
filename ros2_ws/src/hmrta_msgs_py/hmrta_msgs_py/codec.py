"""Payload codecs: pairs of pure functions ``*_to_msg`` / ``*_from_msg``.

Structured payloads are JSON objects inside ``std_msgs/String``, each naming its format and
version in a ``format`` field (``hmrta-choice/1``; JSON Schemas in ``docs/schemas/``); standard
types are used where they exist (``geometry_msgs/PoseStamped`` for poses and goals,
``rosgraph_msgs/Clock`` for sim time, ``visualization_msgs/MarkerArray`` for RViz). Every decoder
validates what it reads and raises :class:`DecodeError` (one line, names the field) on anything
malformed, an unknown format or an unknown version; nothing else escapes a ``*_from_msg``. Writers
emit exactly the published schema; readers ignore fields they do not know.

Board wire format (``hmrta-board/2``): the board stream (``/hmrta/board``) carries one header
per version: the version, the previous one, the events applied in between (the board's journal
records, in order) and the state's digest (:mod:`hmrta.replica` applies them). A keyframe
(``/hmrta/board_keyframe``) is three JSON documents separated by newlines (JSON text never
contains a raw newline): the same header (with ``until``), the legs (one entry per robot) and the
full mission-state snapshot (``hmrta-state/1``, :meth:`hmrta.core.MissionState.snapshot`).
Readers that only need the header never parse the rest; :class:`BoardDecoder` shares one decoded
copy between the nodes of a process. A replica that needs a keyframe asks with an
``hmrta-keyframe-request/1``.

Choices and statuses may be signed (``hmrta.keys``): ``choice_to_msg(c, signer)`` /
``status_to_msg(s, signer)`` add ``counter`` and ``mac``; their decoders check the two fields'
types and keep the decoded object in ``payload`` for the board's verifier.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String
from visualization_msgs.msg import Marker, MarkerArray

from hmrta.board import BOARD_FORMAT, board_header
from hmrta.core import STATE_FORMAT, Rules, parse_rules
from hmrta.instance import CONTROL, Instance, InstanceError, instance_from_dict
from hmrta.reading import short
from hmrta.solution import FORMAT as RESULT_FORMAT

MISSION_FORMAT = "hmrta-mission/1"
KEYFRAME_REQUEST_FORMAT = "hmrta-keyframe-request/1"
CHOICE_FORMAT = "hmrta-choice/1"
STATUS_FORMAT = "hmrta-status/1"
REJECTION_FORMAT = "hmrta-rejection/1"
TASK_REQUEST_FORMAT = "hmrta-task-request/1"
TASK_EVENT_FORMAT = "hmrta-task-event/1"
# every format this module writes (a keyframe's third line is an hmrta-state/1 snapshot)
FORMATS = (MISSION_FORMAT, BOARD_FORMAT, STATE_FORMAT, CHOICE_FORMAT, STATUS_FORMAT, REJECTION_FORMAT, RESULT_FORMAT,
           TASK_REQUEST_FORMAT, TASK_EVENT_FORMAT, KEYFRAME_REQUEST_FORMAT)

PHASES = ("starting", "wait", "decide", "closing", "done")
HOLD = -1  # leg node: stay where you are (0 = own depot, 1 + m = task m)
RESEND = -2  # leg node: publish this goal again now (the robot has not reached it in time)


class DecodeError(ValueError):
    """A received payload is malformed (bad JSON, unknown format or version, missing or mistyped field)."""


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def _dumps(d: Any) -> str:
    return json.dumps(d, separators=(",", ":"), allow_nan=False)


def _loads(text: Any, what: str) -> Any:
    if not isinstance(text, str):
        raise DecodeError(f"{what}: expected text, got {type(text).__name__}")
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError) as e:
        raise DecodeError(f"{what}: invalid JSON ({getattr(e, 'msg', e)})") from None


def check_format(d: dict[str, Any], fmt: str) -> None:
    """DecodeError unless ``d["format"]`` is ``fmt``; the reason tells a missing format, another
    version of the same format and another format apart."""
    got = d.get("format")
    if got == fmt:
        return
    if "format" not in d:
        raise DecodeError(f"{fmt}: missing field 'format' (expected {fmt!r})")
    if isinstance(got, str) and got.rpartition("/")[0] == fmt.rpartition("/")[0]:
        raise DecodeError(f"{fmt}: unsupported version {got!r} (this build reads {fmt!r})")
    raise DecodeError(f"expected format {fmt!r}, got {_short(got)}")


def _short(v: Any, n: int = 60) -> str:
    """A received value in a message's reason: one line, bounded (a hostile value may be megabytes)."""
    r = short(v)
    return r if len(r) <= n else r[: n - 3] + "..."


def _obj(text: Any, fmt: str) -> dict[str, Any]:
    d = _loads(text, fmt)
    if not isinstance(d, dict):
        raise DecodeError(f"{fmt}: expected a JSON object, got {type(d).__name__}")
    check_format(d, fmt)
    return d


def _get(d: dict[str, Any], key: str, kind: type | tuple[type, ...], what: str, *, optional: bool = False,
         default: Any = None) -> Any:
    if key not in d:
        if optional:
            return default
        raise DecodeError(f"{what}: missing field {key!r}")
    v = d[key]
    if v is None and optional:
        return default
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if isinstance(v, bool) and bool not in kinds:  # bool is an int subclass: never accept it as a number
        raise DecodeError(f"{what}.{key}: expected {'/'.join(k.__name__ for k in kinds)}, got {_short(v)}")
    if not isinstance(v, kinds):
        raise DecodeError(f"{what}.{key}: expected {'/'.join(k.__name__ for k in kinds)}, got {_short(v)}")
    if isinstance(v, float) and not math.isfinite(v):
        raise DecodeError(f"{what}.{key}: expected a finite number, got {_short(v)}")
    return v


def _num(d: dict[str, Any], key: str, what: str, **kw: Any) -> float:
    v = _get(d, key, (int, float), what, **kw)
    return v if v is None else float(v)


def _str(text: str) -> String:
    msg = String()
    msg.data = text
    return msg


def _name(v: Any, what: str) -> str:
    if not isinstance(v, str) or not v or len(v) > 256:
        raise DecodeError(f"{what}: expected a non-empty robot name, got {_short(v)}")
    return v


# ---------------------------------------------------------------------------------------------
# time
# ---------------------------------------------------------------------------------------------
def time_to_stamp(t: float) -> Time:
    """Seconds (>= 0) -> builtin_interfaces/Time, rounded to the nanosecond."""
    ns = int(round(float(t) * 1e9))
    if ns < 0:
        raise ValueError(f"time must be >= 0, got {t}")
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_to_time(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def clock_to_msg(t: float) -> Clock:
    return Clock(clock=time_to_stamp(t))


def clock_from_msg(msg: Clock) -> float:
    return stamp_to_time(msg.clock)


# ---------------------------------------------------------------------------------------------
# poses and goals (geometry_msgs/PoseStamped; mission coordinates x scale = frame coordinates)
# ---------------------------------------------------------------------------------------------
def pose_to_msg(xy: Sequence[float], stamp: float, frame_id: str = "map", scale: float = 1.0,
                yaw: float | None = None) -> PoseStamped:
    """A pose (a goal, a simulated robot's pose) at mission coordinates ``xy``, heading ``yaw``
    (radians from the frame's x axis, about z; None: the identity orientation)."""
    msg = PoseStamped()
    msg.header.stamp = time_to_stamp(stamp)
    msg.header.frame_id = frame_id
    msg.pose.position.x = float(xy[0]) * scale
    msg.pose.position.y = float(xy[1]) * scale
    if yaw is None or not math.isfinite(yaw):
        msg.pose.orientation.w = 1.0
    else:
        msg.pose.orientation.z = math.sin(yaw / 2.0)
        msg.pose.orientation.w = math.cos(yaw / 2.0)
    return msg


def yaw_from_msg(msg: PoseStamped | PoseWithCovarianceStamped | Odometry) -> float | None:
    """The heading about z (radians) of a pose of any of :data:`POSE_TYPES`; None when its
    orientation is not a usable quaternion (all zeros, non-finite)."""
    q = (msg.pose.pose if hasattr(msg.pose, "covariance") else msg.pose).orientation
    x, y, z, w = q.x, q.y, q.z, q.w
    if not all(math.isfinite(v) for v in (x, y, z, w)) or x * x + y * y + z * z + w * w < 1e-12:
        return None
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


# the robot pose message types the board reads (its ``pose_type`` / ``pose_types`` parameters)
POSE_TYPES: dict[str, type] = {"PoseStamped": PoseStamped, "PoseWithCovarianceStamped": PoseWithCovarianceStamped,
                               "Odometry": Odometry}


def pose_type(text: str) -> str:
    """The name in :data:`POSE_TYPES` of a pose message type given as ``PoseStamped``,
    ``geometry_msgs/msg/PoseStamped``, ``odometry`` (any case); ValueError naming the choices."""
    leaf = str(text).strip().rsplit("/", 1)[-1].lower()
    for name in POSE_TYPES:
        if name.lower() == leaf:
            return name
    raise ValueError(f"expected a pose type ({', '.join(POSE_TYPES)}), got {_short(text)}")


def pose_from_msg(msg: PoseStamped | PoseWithCovarianceStamped | Odometry,
                  scale: float = 1.0) -> tuple[float, float, float]:
    """-> (x, y, stamp seconds) in mission coordinates, from any of :data:`POSE_TYPES` (the
    frame is ``msg.header.frame_id``)."""
    pose = msg.pose.pose if hasattr(msg.pose, "covariance") else msg.pose
    x, y = pose.position.x, pose.position.y
    if not (math.isfinite(x) and math.isfinite(y)):
        raise DecodeError(f"pose: non-finite position ({x}, {y})")
    return x / scale, y / scale, stamp_to_time(msg.header.stamp)


# ---------------------------------------------------------------------------------------------
# mission (the instance, robot names and run settings; transient local)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Mission:
    session: str  # random id of this board run: caches and restarts key on it
    instance: Instance
    robots: tuple[str, ...]  # robot name of agent index a
    seed: int
    method: str  # the method every agent runs (hmrta.methods)
    frame_id: str = "map"
    scale: float = 1.0  # frame units per mission unit
    rules: Rules | None = None  # the state-machine rules the mission runs under (required on the wire)
    created: float = 0.0  # wall time its board first created it (0: not said, as the oldest): the later of two
    # missions in one mission namespace gives way

    def newer_than(self, other: "Mission") -> bool:
        """Whether this mission was created after ``other`` (ties: by session)."""
        return (self.created, self.session) > (other.created, other.session)

    def index(self, robot: str) -> int | None:
        try:
            return self.robots.index(robot)
        except ValueError:
            return None


def mission_to_msg(m: Mission) -> String:
    if m.rules is None:
        raise ValueError("mission_to_msg: Mission.rules is required (the rules the mission runs under)")
    rules = m.rules if isinstance(m.rules, Rules) else parse_rules(m.rules, "Mission.rules")  # or its to_dict()
    return _str(_dumps({"format": MISSION_FORMAT, "session": m.session, "instance": m.instance.to_dict(),
                        "robots": list(m.robots), "seed": m.seed, "method": m.method,
                        "frame_id": m.frame_id, "scale": m.scale, "rules": rules.to_dict(), "created": m.created}))


def mission_from_msg(msg: String) -> Mission:
    w = MISSION_FORMAT
    d = _obj(msg.data, w)
    try:
        inst = instance_from_dict(_get(d, "instance", dict, w), source="mission")
    except InstanceError as e:
        raise DecodeError(f"{w}.instance: {e}") from None
    robots = _get(d, "robots", list, w)
    names = tuple(_name(r, f"{w}.robots[{i}]") for i, r in enumerate(robots))
    if len(names) != inst.n_agents or len(set(names)) != len(names):
        raise DecodeError(f"{w}.robots: expected {inst.n_agents} distinct names, got {len(names)}")
    scale = _num(d, "scale", w)
    if scale <= 0:
        raise DecodeError(f"{w}.scale: expected a positive number, got {scale}")
    rules = _get(d, "rules", dict, w)
    try:
        rules = parse_rules(rules)
    except ValueError as e:
        raise DecodeError(f"{w}.{e}") from None
    created = d.get("created", 0.0)
    if isinstance(created, bool) or not isinstance(created, (int, float)) or not (0 <= created < math.inf):
        raise DecodeError(f"{w}.created: expected a wall time in seconds >= 0, got {created!r}")
    return Mission(_get(d, "session", str, w), inst, names, _get(d, "seed", int, w), _get(d, "method", str, w),
                   _get(d, "frame_id", str, w), scale, rules, float(created))


# ---------------------------------------------------------------------------------------------
# board: the stream of versions (headers with their events) and keyframes (+ legs + state)
# ---------------------------------------------------------------------------------------------
Leg = tuple[int, float, float, float]  # (node, x, y, depart): go to (x, y) when the clock reaches depart
# per robot: (seq of its latest leg, its latest legs in order, the last one numbered seq); None: lost
RobotLegs = tuple[int, tuple[Leg, ...]]


@dataclass(frozen=True, eq=False)
class Board:
    session: str
    version: int  # increments whenever anything published changes; choices name the version they answer
    rev: int  # state revision: increments when the mission state changes
    phase: str  # starting | wait | decide | closing | done
    decider: int | None  # agent whose turn it is (phase 'decide')
    clock: float  # mission time of the state
    horizon: float  # the sim clock may advance up to here
    n_done: int
    n_cancelled: int
    n_tasks: int
    lost: tuple[int, ...] = ()
    legs: tuple[RobotLegs | None, ...] | None = None  # keyframes: per agent; None for a lost robot
    state: dict[str, Any] | None = field(default=None, repr=False)  # keyframes: the hmrta-state/1 snapshot
    prev: int | None = None  # the version the events apply to (default: version - 1)
    events: tuple[dict[str, Any], ...] = ()  # the board's journal records of this version, in order
    digest: str = ""  # hmrta.board_core.state_digest of the state after the events
    until: float | None = None  # keyframes: the mission time the board's state may reach
    keyframe: bool = False  # a keyframe (header, legs and state) rather than a stream header

    def __post_init__(self) -> None:
        if self.prev is None:
            object.__setattr__(self, "prev", self.version - 1)

    def header(self) -> dict[str, Any]:
        return board_header(self)


def board_to_msg(b: Board, state_json: str | None = None) -> String:
    """A stream header, or (``b.keyframe``) a keyframe: header, legs and state; ``state_json``
    (optional) is ``json.dumps(b.state)`` computed once by the caller."""
    head = _dumps(b.header())
    if not b.keyframe:
        return _str(head)
    if b.legs is None or (b.state is None and state_json is None):
        raise ValueError("board_to_msg: a keyframe needs legs and state")
    legs = _dumps([None if g is None else [g[0], [list(x) for x in g[1]]] for g in b.legs])
    return _str("\n".join((head, legs, state_json if state_json is not None else state_to_json(b.state))))


def state_to_json(state: dict[str, Any]) -> str:
    """The snapshot line (exact floats: JSON keeps Python's shortest round-trip repr)."""
    return json.dumps(state, separators=(",", ":"))


def _split(data: Any) -> list[str]:
    if not isinstance(data, str):
        raise DecodeError(f"{BOARD_FORMAT}: expected text")
    parts = data.split("\n", 2)
    if len(parts) not in (1, 3):
        raise DecodeError(f"{BOARD_FORMAT}: expected a header line, or header, legs and state lines (a keyframe)")
    return parts


def _event(e: Any, where: str) -> dict[str, Any]:
    """An event record's shape (its fields are checked when a replica applies it)."""
    if not isinstance(e, dict) or not isinstance(e.get("type"), str):
        raise DecodeError(f"{where}: expected an event object with a type, got {_short(e)}")
    return e


def _board_header(text: str, keyframe: bool) -> Board:
    w = BOARD_FORMAT
    d = _obj(text, w)
    phase = _get(d, "phase", str, w)
    if phase not in PHASES:
        raise DecodeError(f"{w}.phase: expected one of {PHASES}, got {_short(phase)}")
    lost = _get(d, "lost", list, w)
    if not all(isinstance(a, int) and not isinstance(a, bool) for a in lost):
        raise DecodeError(f"{w}.lost: expected a list of agent indices")
    events = tuple(_event(e, f"{w}.ev[{i}]") for i, e in enumerate(_get(d, "ev", list, w)))
    until = _num(d, "until", w, optional=not keyframe)
    return Board(_get(d, "session", str, w), _get(d, "version", int, w), _get(d, "rev", int, w), phase,
                 _get(d, "decider", int, w, optional=True), _num(d, "clock", w), _num(d, "horizon", w),
                 _get(d, "n_done", int, w), _get(d, "n_cancelled", int, w), _get(d, "n_tasks", int, w), tuple(lost),
                 prev=_get(d, "prev", int, w), events=events, digest=_get(d, "digest", str, w), until=until,
                 keyframe=keyframe)


def _leg(g: Any, where: str) -> Leg:
    if (not isinstance(g, list) or len(g) != 4 or not isinstance(g[0], int) or isinstance(g[0], bool)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in g[1:])):
        raise DecodeError(f"{where}: expected [node, x, y, depart], got {_short(g)}")
    return g[0], float(g[1]), float(g[2]), float(g[3])


def _legs(text: str) -> tuple[RobotLegs | None, ...]:
    w = f"{BOARD_FORMAT}.legs"
    legs = _loads(text, w)
    if not isinstance(legs, list):
        raise DecodeError(f"{w}: expected a list")
    out: list[RobotLegs | None] = []
    for i, e in enumerate(legs):
        if e is None:
            out.append(None)
            continue
        if (not isinstance(e, list) or len(e) != 2 or not isinstance(e[0], int) or isinstance(e[0], bool)
                or not isinstance(e[1], list) or len(e[1]) > e[0]):
            raise DecodeError(f"{w}[{i}]: expected [seq, [legs...]], got {_short(e)}")
        out.append((e[0], tuple(_leg(g, f"{w}[{i}][1][{j}]") for j, g in enumerate(e[1]))))
    return tuple(out)


def _state(text: str) -> dict[str, Any]:
    """The board's third line: an hmrta-state/1 snapshot (its fields are checked by
    :meth:`hmrta.core.MissionState.from_snapshot`, which raises SnapshotError)."""
    w = f"{BOARD_FORMAT}.state"
    st = _loads(text, w)
    if not isinstance(st, dict):
        raise DecodeError(f"{w}: expected a JSON object")
    try:
        check_format(st, STATE_FORMAT)
    except DecodeError as e:
        raise DecodeError(f"{w}: {e}") from None
    return st


def board_from_msg(msg: String, *, legs: bool = True, state: bool = True) -> Board:
    """Decode a stream header or a keyframe (``keyframe`` tells which); ``legs`` / ``state``
    False skips parsing a keyframe's legs and state (they stay None)."""
    parts = _split(msg.data)
    b = _board_header(parts[0], len(parts) == 3)
    if len(parts) == 1:
        return b
    lg = _legs(parts[1]) if legs else None
    st = _state(parts[2]) if state else None
    return dataclasses.replace(b, legs=lg, state=st)


class BoardDecoder:
    """Decodes each board message once per process: nodes hosted together share one read-only
    copy.

    ``decode(msg)`` returns the header (and a keyframe's legs); ``state(msg)`` a keyframe's
    snapshot (parsed on first use; None for a stream header). Keyed by the header line, which
    names the board session and version.
    """

    def __init__(self) -> None:
        self._key: str | None = None
        self._board: Board | None = None
        self._state_text: str | None = None
        self._state: dict[str, Any] | None = None

    def decode(self, msg: String) -> Board:
        data = msg.data
        parts = _split(data)
        key = data if len(parts) == 1 else parts[0] + "\n"
        if key == self._key and self._board is not None:
            return self._board
        b = board_from_msg(msg, legs=True, state=False)
        self._key, self._board = key, b
        self._state_text, self._state = (parts[2] if len(parts) == 3 else None), None
        return b

    def state(self, msg: String) -> dict[str, Any] | None:
        self.decode(msg)
        if self._state is None and self._state_text is not None:
            self._state = _state(self._state_text)
        return self._state


# ---------------------------------------------------------------------------------------------
# keyframe request (a replica -> board)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class KeyframeRequest:
    session: str  # the board session the replica follows
    version: int  # the replica's version (-1: it has none); the board's current one: a confirmation
    reason: str = ""  # why (logged by the board)
    who: str = ""  # the asking process (host:pid), for logs


def keyframe_request_to_msg(r: KeyframeRequest) -> String:
    return _str(_dumps({"format": KEYFRAME_REQUEST_FORMAT, "session": r.session, "version": r.version,
                        "reason": r.reason[:500], "who": r.who[:256]}))


def keyframe_request_from_msg(msg: String) -> KeyframeRequest:
    w = KEYFRAME_REQUEST_FORMAT
    d = _obj(msg.data, w)
    v = _get(d, "version", int, w)
    if v < -1:
        raise DecodeError(f"{w}.version: expected a version >= -1, got {v}")
    return KeyframeRequest(_get(d, "session", str, w), v, _get(d, "reason", str, w, optional=True, default="")[:500],
                           _get(d, "who", str, w, optional=True, default="")[:256])


# ---------------------------------------------------------------------------------------------
# choice (agent -> board)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Choice:
    robot: str
    session: str  # the board session (mission run) this answers
    version: int  # the board version this answers
    node: int  # 0 = own depot, 1 + m = task m
    seq: int = 0  # the agent's own counter (for logs)
    compute_ms: float = 0.0  # board received -> choice published, measured by the agent
    # the decoded JSON object (signed messages: with ``counter`` and ``mac``), for verification
    payload: dict[str, Any] | None = field(default=None, compare=False, repr=False)


def _signed(d: dict[str, Any], signer: Any) -> dict[str, Any]:
    """``d`` signed by ``signer`` (an :class:`hmrta.keys.Signer`: adds ``counter`` and ``mac``)."""
    return d if signer is None else signer.sign(d)


def _check_signature_fields(d: dict[str, Any], what: str) -> None:
    """Optional ``counter`` (integer >= 0) and ``mac`` (object) of a signed message; their
    values are checked by :meth:`hmrta.keys.Verifier.verify`."""
    c = _get(d, "counter", int, what, optional=True)
    if c is not None and c < 0:
        raise DecodeError(f"{what}.counter: expected an integer >= 0, got {c}")
    _get(d, "mac", dict, what, optional=True)


def choice_to_msg(c: Choice, signer: Any = None) -> String:
    """With ``signer`` (:class:`hmrta.keys.Signer` holding the robot's key) the message carries
    ``counter`` and ``mac``."""
    return _str(_dumps(_signed({"format": CHOICE_FORMAT, "robot": c.robot, "session": c.session,
                                "version": c.version, "node": c.node, "seq": c.seq, "compute_ms": c.compute_ms},
                               signer)))


def choice_from_msg(msg: String) -> Choice:
    w = CHOICE_FORMAT
    d = _obj(msg.data, w)
    _check_signature_fields(d, w)
    return Choice(_name(d.get("robot"), f"{w}.robot"), _get(d, "session", str, w), _get(d, "version", int, w),
                  _get(d, "node", int, w),
                  _get(d, "seq", int, w, optional=True, default=0),
                  _num(d, "compute_ms", w, optional=True, default=0.0), d)


# ---------------------------------------------------------------------------------------------
# agent status (heartbeat; one message per agent process lists the robots it hosts)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Join:
    """A robot not in the mission that asks to join it (announced in the heartbeat): its name,
    its species (an index of the mission's species) or a new trait vector, and its position
    (mission coordinates) when its driver reports one."""
    robot: str
    species: int | None = None
    traits: tuple[float, ...] | None = None
    position: tuple[float, float] | None = None


@dataclass(frozen=True)
class Status:
    robots: tuple[str, ...]
    session: str  # the board session (mission run) the robots take part in
    seq: int
    host: str = ""
    # the decoded JSON object (signed messages: with ``counter`` and ``mac``), for verification
    payload: dict[str, Any] | None = field(default=None, compare=False, repr=False)
    joining: tuple[Join, ...] = ()  # robots of the process that are not in the mission yet
    refused: tuple["Refusal", ...] = ()  # robots of the process whose agents refuse the mission


@dataclass(frozen=True)
class Refusal:
    """A robot of the mission whose agent refuses to take part (its method cannot run the
    mission's, its species or index does not match): announced once in a heartbeat before the
    agent stops, so that the board says why at once instead of waiting out its start-up timeout."""
    robot: str
    why: str


REFUSAL_WHY_MAX = 1000  # characters of a refusal's reason (an agent's one-line error)


def _join_to_dict(j: Join) -> dict[str, Any]:
    d: dict[str, Any] = {"robot": j.robot}
    if j.species is not None:
        d["species"] = j.species
    if j.traits is not None:
        d["traits"] = [float(x) for x in j.traits]
    if j.position is not None:
        d["position"] = [float(x) for x in j.position]
    return d


def _join_from(v: Any, where: str) -> Join:
    if not isinstance(v, dict):
        raise DecodeError(f"{where}: expected an object {{robot, species | traits, position}}, got {_short(v)}")
    species = _get(v, "species", int, where, optional=True)
    if species is not None and species < 0:
        raise DecodeError(f"{where}.species: expected a species index >= 0, got {species}")
    traits = _get(v, "traits", list, where, optional=True)
    if (species is None) == (traits is None):
        raise DecodeError(f"{where}: expected exactly one of species and traits")
    def nums(xs: list, what: str) -> tuple[float, ...]:
        return tuple(_num({"v": x}, "v", f"{where}.{what}[{i}]") for i, x in enumerate(xs))

    if traits is not None:
        traits = nums(traits, "traits")
    pos = _get(v, "position", list, where, optional=True)
    if pos is not None:
        if len(pos) != 2:
            raise DecodeError(f"{where}.position: expected [x, y], got {_short(pos)}")
        pos = nums(pos, "position")
    return Join(_name(v.get("robot"), f"{where}.robot"), species, traits, pos)


def status_to_msg(s: Status, signer: Any = None) -> String:
    """With ``signer`` (holding the key of every robot listed) the message carries ``counter``
    and one MAC per robot (those of ``robots`` and of ``refused``). ``joining`` (robots asking to
    join the mission) and ``refused`` (robots whose agents refuse it) are written only when not
    empty."""
    d: dict[str, Any] = {"format": STATUS_FORMAT, "robots": list(s.robots), "session": s.session, "seq": s.seq,
                         "host": s.host}
    if s.joining:
        d["joining"] = [_join_to_dict(j) for j in s.joining]
    if s.refused:
        d["refused"] = [{"robot": r.robot, "why": r.why[:REFUSAL_WHY_MAX]} for r in s.refused]
    return _str(_dumps(_signed(d, signer)))


def _refusal_from(v: Any, where: str) -> Refusal:
    if not isinstance(v, dict):
        raise DecodeError(f"{where}: expected an object {{robot, why}}, got {_short(v)}")
    why = _get(v, "why", str, where)
    if len(why) > REFUSAL_WHY_MAX:
        raise DecodeError(f"{where}.why: expected at most {REFUSAL_WHY_MAX} characters, got {len(why)}")
    return Refusal(_name(v.get("robot"), f"{where}.robot"), why)


def status_from_msg(msg: String) -> Status:
    w = STATUS_FORMAT
    d = _obj(msg.data, w)
    _check_signature_fields(d, w)
    robots = _get(d, "robots", list, w)
    joining = _get(d, "joining", list, w, optional=True, default=[])
    refused = _get(d, "refused", list, w, optional=True, default=[])
    host = _get(d, "host", str, w, optional=True, default="")
    if len(host) > 256:
        raise DecodeError(f"{w}.host: expected a process name of at most 256 characters, got {_short(host)}")
    return Status(tuple(_name(r, f"{w}.robots[{i}]") for i, r in enumerate(robots)), _get(d, "session", str, w),
                  _get(d, "seq", int, w), host, d,
                  tuple(_join_from(j, f"{w}.joining[{i}]") for i, j in enumerate(joining)),
                  tuple(_refusal_from(r, f"{w}.refused[{i}]") for i, r in enumerate(refused)))


# ---------------------------------------------------------------------------------------------
# rejection (board -> anyone: why a message was refused)
# ---------------------------------------------------------------------------------------------
REJECTION_REASONS = ("malformed", "foreign_session", "unknown_robot", "lost", "duplicate", "stale", "not_released",
                     "not_your_turn", "masked", "join_refused",
                     # authenticated missions (hmrta.keys.rejection_code)
                     "unsigned", "forged", "replayed", "unauthenticated")


@dataclass(frozen=True)
class Rejection:
    reason: str  # one of REJECTION_REASONS (readers accept any string: a later board may add reasons)
    detail: str
    robot: str = ""
    version: int = -1


def rejection_to_msg(r: Rejection) -> String:
    return _str(_dumps({"format": REJECTION_FORMAT, "reason": r.reason, "detail": r.detail, "robot": r.robot,
                        "version": r.version}))


def rejection_from_msg(msg: String) -> Rejection:
    w = REJECTION_FORMAT
    d = _obj(msg.data, w)
    return Rejection(_get(d, "reason", str, w), _get(d, "detail", str, w),
                     _get(d, "robot", str, w, optional=True, default=""),
                     _get(d, "version", int, w, optional=True, default=-1))


# ---------------------------------------------------------------------------------------------
# operator task requests (anyone -> board) and task events (board -> anyone)
# ---------------------------------------------------------------------------------------------
TASK_OPS = ("add", "cancel")
TASK_EVENTS = ("accepted", "rejected", "started", "done", "cancelled")


@dataclass(frozen=True)
class TaskRequest:
    op: str  # add | cancel
    id: str  # client-chosen task id
    task: dict[str, Any] | None = None  # add: {location: [x, y], requirements: [...], duration}
    request_id: str = ""  # client-generated nonce, echoed in the board's answer (empty: none)


def _request_id(d: dict[str, Any], w: str) -> str:
    rq = _get(d, "request_id", str, w, optional=True, default="")
    if len(rq) > 256:
        raise DecodeError(f"{w}.request_id: expected at most 256 characters")
    return rq


def task_request_to_msg(r: TaskRequest) -> String:
    d: dict[str, Any] = {"format": TASK_REQUEST_FORMAT, "op": r.op, "id": r.id}
    if r.task is not None:
        d["task"] = r.task
    if r.request_id:
        d["request_id"] = r.request_id
    return _str(_dumps(d))


def task_request_from_msg(msg: String) -> TaskRequest:
    """Shape only; the task's values are checked when the board applies it (hmrta.core)."""
    w = TASK_REQUEST_FORMAT
    d = _obj(msg.data, w)
    op = _get(d, "op", str, w)
    if op not in TASK_OPS:
        raise DecodeError(f"{w}.op: expected one of {TASK_OPS}, got {_short(op)}")
    rid = _get(d, "id", str, w)
    if not rid or len(rid) > 256:
        raise DecodeError(f"{w}.id: expected a non-empty id of at most 256 characters")
    if CONTROL.search(rid):  # (ids are printed in logs, answers and the operator's console)
        raise DecodeError(f"{w}.id: expected an id on one line, got a control character in {_short(rid)}")
    task = _get(d, "task", dict, w, optional=(op == "cancel"))
    return TaskRequest(op, rid, task, _request_id(d, w))


def request_id_of(text: Any) -> str:
    """The ``request_id`` of a task request that may not decode (for the rejection's answer);
    '' when it has none or it is unreadable."""
    try:
        d = json.loads(text)
    except (TypeError, ValueError, RecursionError):
        return ""
    rq = d.get("request_id") if isinstance(d, dict) else None
    return rq if isinstance(rq, str) and len(rq) <= 256 else ""


@dataclass(frozen=True)
class TaskEvent:
    id: str
    event: str  # accepted | rejected | started | done | cancelled
    t: float = 0.0  # mission time
    task: int | None = None  # task index on the board
    reason: str = ""  # rejected: why
    op: str = ""  # accepted / rejected: the request's op
    request_id: str = ""  # accepted / rejected: the request's request_id (empty: it had none)


def task_event_to_msg(e: TaskEvent) -> String:
    d: dict[str, Any] = {"format": TASK_EVENT_FORMAT, "id": e.id, "event": e.event, "t": e.t}
    if e.task is not None:
        d["task"] = e.task
    if e.reason:
        d["reason"] = e.reason
    if e.op:
        d["op"] = e.op
    if e.request_id:
        d["request_id"] = e.request_id
    return _str(_dumps(d))


def task_event_from_msg(msg: String) -> TaskEvent:
    w = TASK_EVENT_FORMAT
    d = _obj(msg.data, w)
    return TaskEvent(_get(d, "id", str, w), _get(d, "event", str, w), _num(d, "t", w),
                     _get(d, "task", int, w, optional=True), _get(d, "reason", str, w, optional=True, default=""),
                     _get(d, "op", str, w, optional=True, default=""), _request_id(d, w))


# ---------------------------------------------------------------------------------------------
# mission result (the hmrta-solution/1 JSON; transient local)
# ---------------------------------------------------------------------------------------------
def result_to_msg(solution: dict[str, Any]) -> String:
    if solution.get("format") != RESULT_FORMAT:
        raise ValueError(f"expected an {RESULT_FORMAT} mapping")
    return _str(json.dumps(solution))  # NaN-free: Solution.to_dict writes null for non-finite values


def result_from_msg(msg: String) -> dict[str, Any]:
    d = _obj(msg.data, RESULT_FORMAT)
    for k in ("routes", "tasks", "agents", "success"):
        if k not in d:
            raise DecodeError(f"{RESULT_FORMAT}: missing field {k!r}")
    return d


# ---------------------------------------------------------------------------------------------
# RViz markers (visualization_msgs/MarkerArray)
# ---------------------------------------------------------------------------------------------
STATUS_COLORS = {  # task status name -> RGBA
    "empty": (0.6, 0.6, 0.6, 0.8), "open": (1.0, 0.6, 0.0, 0.9), "in_progress": (0.1, 0.5, 1.0, 0.9),
    "done": (0.1, 0.8, 0.2, 0.9), "cancelled": (0.8, 0.1, 0.1, 0.9),
}


@dataclass(frozen=True)
class MarkerView:
    tasks: tuple[tuple[float, float, str], ...]  # (x, y, status name)
    robots: tuple[tuple[str, float, float, bool], ...]  # (name, x, y, lost)
    legs: tuple[tuple[float, float, float, float], ...] = ()  # (x0, y0, x1, y1) current moves


def markers_to_msg(v: MarkerView, stamp: float, frame_id: str = "map", scale: float = 1.0) -> MarkerArray:
    out = MarkerArray()

    def marker(ns: str, i: int, kind: int, x: float, y: float, size: float, rgba, text: str = "") -> Marker:
        m = Marker()
        m.header.stamp = time_to_stamp(stamp)
        m.header.frame_id = frame_id
        m.ns, m.id, m.type, m.action = ns, i, kind, Marker.ADD
        m.pose.position.x, m.pose.position.y = x * scale, y * scale
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = size * scale
        m.color.r, m.color.g, m.color.b, m.color.a = rgba
        m.text = text
        return m

    for i, (x, y, status) in enumerate(v.tasks):
        out.markers.append(marker("tasks", i, Marker.CYLINDER, x, y, 0.03, STATUS_COLORS.get(status, (1, 1, 1, 1)),
                                  status))
    for i, (name, x, y, lost) in enumerate(v.robots):
        rgba = (0.3, 0.3, 0.3, 0.6) if lost else (0.9, 0.9, 0.1, 1.0)
        out.markers.append(marker("robots", i, Marker.SPHERE, x, y, 0.02, rgba, name + (" (lost)" if lost else "")))
    legs = marker("legs", 0, Marker.LINE_LIST, 0.0, 0.0, 0.004, (1.0, 1.0, 1.0, 0.5))
    legs.scale.y = legs.scale.z = 0.0
    for x0, y0, x1, y1 in v.legs:
        legs.points.append(Point(x=x0 * scale, y=y0 * scale, z=0.0))
        legs.points.append(Point(x=x1 * scale, y=y1 * scale, z=0.0))
    out.markers.append(legs)
    return out


def markers_from_msg(msg: MarkerArray, scale: float = 1.0) -> MarkerView:
    tasks, robots, legs = [], [], []
    for m in msg.markers:
        x, y = m.pose.position.x / scale, m.pose.position.y / scale
        if m.ns == "tasks":
            tasks.append((m.id, (x, y, m.text)))
        elif m.ns == "robots":
            lost = m.text.endswith(" (lost)")
            robots.append((m.id, (m.text[:-7] if lost else m.text, x, y, lost)))
        elif m.ns == "legs":
            p = m.points
            legs += [(p[i].x / scale, p[i].y / scale, p[i + 1].x / scale, p[i + 1].y / scale)
                     for i in range(0, len(p) - 1, 2)]
    return MarkerView(tuple(t for _, t in sorted(tasks)), tuple(r for _, r in sorted(robots)), tuple(legs))
