"""recorder: record a mission to MCAP (rosbag2's default storage format), for Foxglove, rosbag2 and ``hmrta render --from``.

Records every ``<ns>/hmrta/*`` topic of the mission (``<ns>``: ``mission_namespace``, default ``/``;
mission, board, choices, heartbeats, rejections, result, task requests and events, the mission
clock ``clock_topic``; ``<ns>/hmrta/markers`` only with ``markers:=true``; another node's
``/clock`` only when listed in ``topics``), and each robot's goals and poses
(``<ns>/<robot>/goal_pose``, ``<ns>/<robot>/pose``; the
robots are named by the ``robots`` parameter or taken from the recorded mission message), plus
any topic listed in ``topics``. Messages are stored as received (ROS 2 CDR, message encoding
``cdr``) with their message definitions as ``ros2msg`` schemas, read from the installed ``.msg``
files. Each message carries its receive time (``log_time``) and its publisher's send time
(``publish_time``), both wall-clock nanoseconds; the mission clock is in the recorded clock and
board messages (``hmrta.replay`` maps receive times to it).

Topics are subscribed at start (the HMRTA topics, with the QoS of their publishers: transient
local for the latched ones) and whenever a matching topic appears (every ``discovery_period``
seconds), with a QoS compatible with its publishers. The file is written as ``OUTPUT.part`` and
renamed to ``OUTPUT`` when the recorder stops (Ctrl-C, SIGTERM): a recording that is complete is
never half-written; a ``.part`` left by a killed recorder holds the chunks written so far.

Beside it, ``OUTPUT`` with the suffix ``.qos.yaml`` holds the QoS each recorded topic is published
with, in the form of rosbag2's QoS overrides (``ros2 bag play OUTPUT --qos-profile-overrides-path
OUTPUT.qos.yaml``): played back without it, the latched topics (mission, keyframe, result, clock)
would be republished volatile, and the product's own transient-local subscribers would never match.
"""
from __future__ import annotations

import importlib
import json
import os
import re
import sys
import time
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from hmrta_msgs_py import topics
from hmrta_msgs_py.runtime import check_period, parameters_read_at_start, spin_nodes, starting, writable_file

RECORDING_FORMAT = "hmrta-recording/1"  # the MCAP metadata record "hmrta" names it
DRAIN_SECONDS = 0.5  # on a stop signal: the messages already received are recorded for up to this long
HEARD = "recorder: heard the mission on"  # printed (stdout) once the first mission message is recorded
PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
              "int64", "uint64", "string", "wstring"}
SEPARATOR = "=" * 80
COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class DefinitionError(LookupError):
    """A message definition (``.msg`` file) is not installed."""


def share_dirs() -> list[Path]:
    """Where ``<pkg>/msg/<Type>.msg`` files are looked for: each ``AMENT_PREFIX_PATH`` prefix's
    ``share`` folder, then this interpreter's (ROS installed from wheels into a venv)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    out = []
    for p in [*prefixes, sys.prefix]:
        d = Path(p) / "share"
        if d.is_dir() and d not in out:
            out.append(d)
    return out


def _msg_text(pkg: str, name: str, dirs: list[Path]) -> str:
    for d in dirs:
        f = d / pkg / "msg" / f"{name}.msg"
        if f.is_file():
            return f.read_text()
    raise DefinitionError(f"{pkg}/msg/{name}.msg is not installed (looked in {', '.join(map(str, dirs)) or 'nothing'})")


def _field_types(text: str, pkg: str) -> list[str]:
    """The non-primitive field types of a .msg text, as 'pkg/Type'."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        typ = line.split()[0]  # constants and defaults are of primitive types
        base = re.sub(r"\[.*?\]$", "", typ)
        base = re.sub(r"<=\d+$", "", base)  # bounded string
        if base in PRIMITIVES:
            continue
        if "/" not in base:
            base = "std_msgs/Header" if base == "Header" else f"{pkg}/{base}"
        p, _, n = base.rpartition("/")
        out.append(f"{p.split('/')[0]}/{n}")
    return out


def message_definition(type_name: str, dirs: list[Path] | None = None) -> str:
    """The ``ros2msg`` schema text of a message type (``std_msgs/msg/String``): its ``.msg`` text
    followed by the definition of every type it uses, each after a separator line and
    ``MSG: pkg/Type`` (the concatenated form rosbag2 writes). Raises DefinitionError."""
    dirs = share_dirs() if dirs is None else dirs
    pkg, _, name = type_name.rpartition("/")
    pkg = pkg.split("/")[0]
    main = _msg_text(pkg, name, dirs)
    parts, seen = [main.rstrip("\n")], {f"{pkg}/{name}"}
    todo = _field_types(main, pkg)
    while todo:
        dep = todo.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        p, n = dep.split("/")
        text = _msg_text(p, n, dirs)
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n{text.rstrip(chr(10))}")
        todo += _field_types(text, p)
    return "\n".join(parts) + "\n"


def message_class(type_name: str):
    """``std_msgs/msg/String`` -> the Python message class (ImportError/AttributeError if not installed)."""
    pkg, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


_S = "std_msgs/msg/String"
# the mission-wide topics: MissionTopics attribute (None: the clock topic), message type, the
# recorder's receive depth, and the QoS the mission's nodes publish it with
_MISSION_TOPICS = (
    ("mission", _S, 10, topics.MISSION_QOS), ("board", _S, 1000, topics.BOARD_QOS),
    ("keyframe", _S, 10, topics.KEYFRAME_QOS), ("keyframe_requests", _S, 1000, topics.KEYFRAME_REQUEST_QOS),
    ("result", _S, 1, topics.RESULT_QOS), ("choice", _S, 1000, topics.CHOICE_QOS),
    ("status", _S, 1000, topics.STATUS_QOS), ("rejections", _S, 1000, topics.REJECTION_QOS),
    ("task_requests", _S, 1000, topics.TASK_REQUEST_QOS), ("task_events", _S, 100, topics.TASK_EVENT_QOS),
    (None, "rosgraph_msgs/msg/Clock", 100, topics.CLOCK_QOS),
)
_MARKERS = ("markers", "visualization_msgs/msg/MarkerArray", 10, topics.MARKER_QOS)


def _mission_topics(markers: bool, clock_topic: str, T: topics.MissionTopics) -> dict[str, tuple[str, int, QoSProfile]]:
    """name -> (type, receive depth, offered QoS) of the mission-wide topics of ``T``'s namespace."""
    rows = _MISSION_TOPICS + ((_MARKERS,) if markers else ())
    return {(clock_topic if attr is None else getattr(T, attr)): (typ, depth, offered)
            for attr, typ, depth, offered in rows}


def known_topics(markers: bool, clock_topic: str = topics.CLOCK,
                 T: topics.MissionTopics = topics.MissionTopics()) -> dict[str, tuple[str, QoSProfile]]:
    """The mission-wide HMRTA topics of the mission namespace of ``T``: name -> (type, a QoS
    compatible with their publishers). Latched topics are subscribed transient local (the latest
    sample arrives even when the recorder starts late); the rest reliable and deep enough for bursts."""
    return {name: (typ, topics.qos(depth, offered.reliability == ReliabilityPolicy.RELIABLE,
                             offered.durability == DurabilityPolicy.TRANSIENT_LOCAL))
            for name, (typ, depth, offered) in _mission_topics(markers, clock_topic, T).items()}


def offered_qos(markers: bool, clock_topic: str = topics.CLOCK,
                T: topics.MissionTopics = topics.MissionTopics()) -> dict[str, QoSProfile]:
    """The QoS the mission's nodes publish its topics with (what a playback should offer)."""
    return {name: offered for name, (_, _, offered) in _mission_topics(markers, clock_topic, T).items()}


def robot_topics(robot: str, namespace: str = topics.ROOT) -> dict[str, tuple[str, QoSProfile]]:
    """A robot's goal (reliable, as agents publish it) and pose (best effort: any driver's QoS)."""
    P = "geometry_msgs/msg/PoseStamped"
    return {topics.robot_topic(robot, topics.GOAL, namespace): (P, topics.qos(100, True, False)),
            topics.robot_topic(robot, topics.POSE, namespace): (P, topics.qos(100, False, False))}


def string_payload(data: bytes) -> str | None:
    """The text of a CDR-serialised ``std_msgs/String`` (None if it is not one)."""
    if len(data) < 8:
        return None
    little = data[1] in (1, 3)
    n = int.from_bytes(data[4:8], "little" if little else "big")
    if n < 1 or 8 + n > len(data):
        return None
    return data[8:8 + n - 1].decode("utf-8", errors="replace")


@parameters_read_at_start
class Recorder(Node):
    def __init__(self) -> None:
        super().__init__("hmrta_recorder")
        P = self.declare_parameter
        output = P("output", "").value
        self.robot_names: list[str] = list(P("robots", Parameter.Type.STRING_ARRAY).value or [])
        self.extra: list[str] = list(P("topics", Parameter.Type.STRING_ARRAY).value or [])
        self.markers = bool(P("markers", False).value)
        period = float(P("discovery_period", 1.0).value)
        compression = str(P("compression", "zstd").value)
        self.topics = topics.mission_topics(P("mission_namespace", "/").value)
        self.clock_topic = self.topics.clock_topic(str(P("clock_topic", "").value))
        if compression not in COMPRESSION:
            raise ValueError(f"compression: expected one of {', '.join(COMPRESSION)}, got {compression!r}")
        check_period("discovery_period", period)  # (at least 0.05 is used)
        for r in self.robot_names:  # each names topics <ns>/<robot>/...: refused here, by the parameter's name
            topics.check_robot_name(r, "robots")
        for t in self.extra:  # (matched against the graph's names, which are absolute: another never records)
            topics.check_absolute_topic(t, "topics")
        self.output = writable_file("output", output or time.strftime("hmrta_%Y%m%d_%H%M%S.mcap"))
        self.part = part_path(self.output)
        try:
            self.output.parent.mkdir(parents=True, exist_ok=True)
            self._fh = open(self.part, "wb")
        except OSError as e:
            raise ValueError(f"output: cannot write {self.part} ({e.strerror or type(e).__name__})") from None
        try:
            self._start(compression, period)
        except BaseException:  # nothing is left behind by a node that did not start
            self._fh.close()
            self.part.unlink(missing_ok=True)
            raise

    def _start(self, compression: str, period: float) -> None:
        self.writer = Writer(self._fh, compression=COMPRESSION[compression])
        self.writer.start(profile="ros2", library="hmrta recorder")
        self.schemas: dict[str, int] = {}  # type -> schema id
        self.channels: dict[str, int] = {}  # topic -> channel id
        self.counts: dict[str, int] = {}
        self.types: dict[str, str] = {}  # topic -> type
        self.subs: dict[str, Any] = {}
        self.qos: dict[str, QoSProfile] = {}  # topic -> the QoS it is recorded with (its publishers')
        self.skipped: set[str] = set()
        self.session: str | None = None
        self.heard = False  # the mission message has been received (the board's latched topics are matched)
        self.closed = False
        known = known_topics(self.markers, self.clock_topic, self.topics)
        self.offered = offered_qos(self.markers, self.clock_topic, self.topics)  # (others: as subscribed)
        self.known = set(known)  # this mission's topics: exactly these names (another mission may be in <ns>/hmrta)
        for name, (typ, qos) in known.items():
            self._subscribe(name, typ, qos)
        for r in self.robot_names:
            for name, (typ, qos) in robot_topics(r, self.topics.namespace).items():
                self._subscribe(name, typ, qos)
        self.timer = self.create_timer(max(period, 0.05), self._discover)
        self.get_logger().info(f"recording to {self.output} ({len(self.subs)} topics so far)")

    # -- subscriptions ----------------------------------------------------------------------------
    def _subscribe(self, name: str, typ: str, qos: QoSProfile) -> None:
        if name in self.subs or (name, typ) in self.skipped:
            return
        try:
            cls = message_class(typ)
            definition = message_definition(typ)
        except (ImportError, AttributeError, ValueError, DefinitionError) as e:
            self.skipped.add((name, typ))
            self.get_logger().warning(f"not recording {name} ({typ}): {e}")
            return
        if typ not in self.schemas:
            self.schemas[typ] = self.writer.register_schema(typ, "ros2msg", definition.encode())
        self.types[name] = typ
        self.counts.setdefault(name, 0)
        self.subs[name] = self.create_subscription(cls, name, lambda data, info, n=name: self._on(n, data, info),
                                                   qos, raw=True)
        self.qos[name] = self.offered.get(name, qos)

    def _wanted(self, name: str) -> bool:
        if name in self.extra:
            return True
        if name in self.known:
            return True
        return any(name in robot_topics(r, self.topics.namespace) for r in self.robot_names)

    def _discover(self) -> None:
        """Subscribe to matching topics that appeared, with a QoS their publishers offer."""
        try:
            found = self.get_topic_names_and_types()
        except Exception:  # noqa: BLE001 (the context is shutting down)
            return
        for name, types in found:
            if name in self.subs or not types or not self._wanted(name):
                continue
            pubs = self.get_publishers_info_by_topic(name)
            if not pubs:
                continue
            reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
            latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
            self._subscribe(name, types[0], topics.qos(100, reliable, latched))

    # -- writing ----------------------------------------------------------------------------------
    def _on(self, name: str, data: bytes, info: Any) -> None:
        if self.closed:
            return
        now = time.time_ns()
        ch = self.channels.get(name)
        if ch is None:
            ch = self.channels[name] = self.writer.register_channel(name, "cdr", self.schemas[self.types[name]])
        sent = info.get("source_timestamp") if isinstance(info, dict) else None
        seq = self.counts[name]
        self.writer.add_message(ch, log_time=now, data=bytes(data), publish_time=int(sent or now),
                                sequence=seq & 0xFFFFFFFF)
        self.counts[name] = seq + 1
        if name == self.topics.mission:
            if not self.heard:  # hmrta-mission waits for this line before it starts the robots (MissionProcesses)
                self.heard = True
                print(f"{HEARD} {name}", flush=True)
            self._learn_robots(data)

    def _learn_robots(self, data: bytes) -> None:
        """Record the goal and pose topics of the robots the mission names."""
        try:
            d = json.loads(string_payload(bytes(data)) or "")
            robots = [r for r in d.get("robots", []) if isinstance(r, str) and r]
            self.session = d.get("session") if isinstance(d.get("session"), str) else self.session
        except (ValueError, AttributeError):
            return
        for r in robots:
            if r not in self.robot_names:
                self.robot_names.append(r)
                for name, (typ, qos) in robot_topics(r, self.topics.namespace).items():
                    self._subscribe(name, typ, qos)

    def close(self) -> None:
        """Finish the file (summary, metadata) and rename it into place. Idempotent."""
        if self.closed:
            return
        self.closed = True
        meta = {"format": RECORDING_FORMAT, "robots": ",".join(self.robot_names), "session": self.session or "",
                "message_counts": json.dumps(self.counts, sort_keys=True)}
        self.writer.add_metadata("hmrta", meta)
        self.writer.finish()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        self.part.replace(self.output)
        qos_file = qos_path(self.output)
        recorded = {n: self.qos[n] for n in sorted(self.counts) if self.counts[n] and n in self.qos}
        tmp = qos_file.with_name(qos_file.name + ".part")
        tmp.write_text(qos_overrides(recorded))
        tmp.replace(qos_file)
        total = sum(self.counts.values())
        print(f"recorder: wrote {self.output} ({total} messages on {sum(1 for c in self.counts.values() if c)} topics, "
              f"{self.output.stat().st_size} bytes) and its topics' QoS {qos_file.name}", flush=True)


def qos_path(output: Path) -> Path:
    """Where the recorded topics' QoS is written: ``run.mcap`` -> ``run.qos.yaml``."""
    return output.with_suffix(".qos.yaml")


def qos_overrides(qos: dict[str, QoSProfile]) -> str:
    """rosbag2's QoS overrides YAML (``ros2 bag play --qos-profile-overrides-path``) of ``qos``:
    per topic its history, depth, reliability and durability, as their publishers offer them."""
    lines = ["# the QoS of each recorded topic: ros2 bag play RECORDING.mcap --qos-profile-overrides-path THIS_FILE"]
    for name, q in qos.items():
        lines += [f"{name}:", "  history: keep_last", f"  depth: {int(q.depth)}",
                  f"  reliability: {'reliable' if q.reliability == ReliabilityPolicy.RELIABLE else 'best_effort'}",
                  f"  durability: {'transient_local' if q.durability == DurabilityPolicy.TRANSIENT_LOCAL else 'volatile'}"]
    return "\n".join(lines) + "\n"


def part_path(output: Path) -> Path:
    """Where the recording is written until it is complete."""
    return output.with_name(output.name + ".part")


def main(args: list[str] | None = None) -> None:
    argv = sys.argv if args is None else args
    from hmrta_msgs_py.params import node_parameters
    from hmrta_msgs_py.runtime import help_requested, no_own_arguments

    help_requested(argv, "recorder", __doc__.split("\n\n")[0], node_parameters("recorder"))
    no_own_arguments("recorder", argv)
    with starting("recorder", (ValueError, OSError), args=argv):  # a bad parameter or output path: a user error
        node = Recorder()
    # the single-threaded executor: the experimental events executor does not deliver raw messages
    os.environ["HMRTA_EXECUTOR"] = "single"
    # on Ctrl-C / SIGTERM the messages its readers already hold are recorded first (0.5 s at most)
    spin_nodes([node], on_exit=node.close, drain=DRAIN_SECONDS)


if __name__ == "__main__":
    sys.exit(main())
