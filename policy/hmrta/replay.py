"""Read a recorded mission (MCAP, as written by the ``recorder`` node / ``hmrta-mission --record``)
back into what was planned and what was executed, without ROS.

:func:`read_recording` decodes the ROS 2 CDR messages with ``mcap-ros2-support`` (the schemas
are in the file) and returns a :class:`Recording`: the mission (``hmrta-mission/1``: instance,
robot names, method, seed, scale), the plan (the ``hmrta-solution/1`` result, or else the
schedule of the latest board: the latest keyframe with the versions streamed after it applied by a
:class:`hmrta.replica.Replica`), each robot's pose track and goals in mission coordinates and
mission time, and the message count of every topic. :meth:`Recording.visits` compares, per
robot and task, the planned arrival, start and finish with the actual arrival (the first pose
within ``tolerance`` of the task). :func:`render_recording` draws both (``hmrta render --from``).

A mission in a namespace (``mission_namespace``: its topics ``<ns>/hmrta/...`` and
``<ns>/<robot>/pose``) is read from its own topics; a recording holding the topics of several
missions is refused.

Mission time of a pose: its header stamp when it lies on the mission clock (simulated
missions stamp poses with the mission clock), else its receive time mapped through the
mission clock messages recorded (``rosgraph_msgs/Clock`` topics, board headers).
"""
from __future__ import annotations

import bisect
import errno
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from .deps import MissingDependency
from .instance import Instance, InstanceError, instance_from_dict
from .solution import Solution, SolutionError

# the mission-wide topics, in the root namespace; a mission in namespace <ns> has <ns> before each
MISSION_TOPIC = "/hmrta/mission"
BOARD_TOPIC = "/hmrta/board"
KEYFRAME_TOPIC = "/hmrta/board_keyframe"
RESULT_TOPIC = "/hmrta/result"
GOAL_LEAF = "goal_pose"
CLOCK_TYPES = ("rosgraph_msgs/msg/Clock", "rosgraph_msgs/Clock")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry")
MAGIC = b"\x89MCAP0\r\n"


class ReplayError(ValueError):
    """A recording that cannot be replayed (not MCAP, no mission, malformed payload): a user
    error, one line naming the file."""


@dataclass
class Recording:
    path: Path
    mission: dict[str, Any]  # the hmrta-mission/1 payload
    instance: Instance  # the mission as it ended: with the tasks added while it ran (the plan's final instance)
    robots: list[str]
    scale: float
    plan: Solution | None  # the result, else the latest board's schedule; None if neither was recorded
    plan_source: str  # "result", "board" or "none"
    tracks: dict[str, list[tuple[float, float, float]]]  # robot -> [(mission time, x, y)], time order
    goals: dict[str, list[tuple[float, float, float]]]  # robot -> [(departure, x, y)], receive order
    counts: dict[str, int]  # topic -> messages
    types: dict[str, str]  # topic -> message type
    clock: list[tuple[int, float]] = field(default_factory=list)  # (receive ns, mission clock), receive order
    recorded: Instance | None = None  # the mission message's instance (None: ``instance``)

    @property
    def routes(self) -> list[list[int]] | None:
        return None if self.plan is None else self.plan.routes

    def visits(self, tolerance: float | None = None) -> list[list[dict[str, Any]]]:
        """Per robot (mission agent order), per task of its planned route: ``task``, planned
        ``arrival`` / ``start`` / ``finish`` (NaN when unknown) and ``actual_arrival`` (the first
        pose within ``tolerance`` mission units of the task after the previous visit's; NaN if
        none, and NaN when no pose of the robot away from the task was recorded before it, unless
        it set off from within the tolerance of the task: a recorder that heard the robot first
        when it was already there saw no arrival).
        ``tolerance`` defaults to 1 % of the mission area's diagonal."""
        if self.plan is None:
            return [[] for _ in self.robots]
        from .render import agent_timeline

        tol = self.default_tolerance() if tolerance is None else float(tolerance)
        timeline = agent_timeline(self.instance, self.plan)
        out = []
        for a, route in enumerate(self.plan.routes):
            legs = [s for s in timeline[a] if s["kind"] == "travel" and s["task"] is not None]
            arrive = {s["task"]: s["t1"] for s in legs}
            leaves = {s["task"]: s["p0"] for s in legs}  # where the robot set off for each task
            track = self.tracks.get(self.robots[a], [])
            i, rows = 0, []
            for m in route:
                tk = self.plan.tasks[m]
                loc = self.instance.task_locations[m]
                # away: a pose on the way here was recorded (or there is no way: it set off within
                # the tolerance of the task, from a task or depot at the same place)
                p0 = leaves.get(m)
                actual, away = math.nan, p0 is not None and math.hypot(p0[0] - loc[0], p0[1] - loc[1]) <= tol
                while i < len(track):
                    t, x, y = track[i]
                    if math.hypot(x - loc[0], y - loc[1]) <= tol:
                        actual = t if away else math.nan
                        break
                    away = True
                    i += 1
                rows.append({"task": m, "arrival": arrive.get(m, math.nan), "start": _num(tk.get("start")),
                             "finish": _num(tk.get("finish")), "actual_arrival": actual})
            out.append(rows)
        return out

    def default_tolerance(self) -> float:
        pts = [*map(tuple, self.instance.depots), *map(tuple, self.instance.task_locations)]
        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        return 0.01 * max(math.hypot(max(xs) - min(xs), max(ys) - min(ys)), 1e-9)


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan


def _modules():
    try:
        from mcap.exceptions import McapError
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
    except ImportError as e:
        raise MissingDependency(f"reading MCAP recordings needs {e.name or 'mcap'}, which is not installed "
                                "(pip install 'hmrta[replay]')") from None
    return make_reader, DecoderFactory, McapError


def _messages(path: Path) -> Iterator[tuple[str, str, int, Any]]:
    """(topic, type, receive ns, decoded message) of every message in log-time order."""
    make_reader, DecoderFactory, McapError = _modules()
    try:
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise ReplayError(f"{path}: not an MCAP file (expected the MCAP magic bytes at its start)")
            f.seek(0)
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for schema, channel, msg, decoded in reader.iter_decoded_messages(log_time_order=True):
                yield channel.topic, schema.name if schema else "", msg.log_time, decoded
    except ReplayError:
        raise
    except OSError as e:
        if e.errno == errno.EINVAL:  # the reader seeks to a summary before the file's start: cut short
            raise ReplayError(f"{path}: damaged or cut short MCAP (too short for its own index)") from None
        raise ReplayError(f"{path}: cannot read ({e.strerror or e})") from None
    except (McapError, ValueError, KeyError, EOFError, NotImplementedError) as e:
        raise ReplayError(f"{path}: damaged or unreadable MCAP ({' '.join(str(e).splitlines()) or type(e).__name__})") from None


def _stamp(m: Any) -> float:
    return float(m.sec) + float(m.nanosec) * 1e-9


def _position(msg: Any) -> tuple[float, float] | None:
    p = getattr(msg, "pose", None)
    if p is not None and hasattr(p, "pose"):  # PoseWithCovarianceStamped, Odometry
        p = p.pose
    pos = getattr(p, "position", None)
    if pos is None:
        return None
    x, y = float(pos.x), float(pos.y)
    return (x, y) if math.isfinite(x) and math.isfinite(y) else None


def _json(text: Any, what: str, path: Path) -> Any:
    try:
        return json.loads(text)
    except (TypeError, ValueError):
        raise ReplayError(f"{path}: {what} is not valid JSON") from None


def _namespace_of(topic: str, leaf: str) -> str | None:
    """The mission namespace of ``topic`` if it is the mission-wide topic ``leaf``
    ('/hmrta/board' in '/fleet1/hmrta/board' -> '/fleet1'; in the root namespace '/'), else None."""
    if topic == leaf:
        return "/"
    return topic[:-len(leaf)] if topic.endswith(leaf) and topic.startswith("/") else None


def read_recording(path: str | Path) -> Recording:
    """Read a recording; :class:`ReplayError` (one line naming the file) for a file that is not
    MCAP, holds no mission message or a malformed one."""
    path = Path(path)
    if not path.is_file():
        what = ("is a folder" if path.is_dir() else "not a regular file" if path.exists() else "no such file")
        raise ReplayError(f"{path}: {what} (expected an MCAP recording)")
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    mission_text = result_text = keyframe_text = None
    heads: list[str] = []  # board stream headers (the latest ones)
    # (mission namespace, robot) -> (recv ns, stamp, x, y) in frame units; goals: (departure, x, y)
    poses: dict[tuple[str, str], list[tuple[int, float, float, float]]] = {}
    goals: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    clock: list[tuple[int, float]] = []
    spaces: set[str] = set()  # the mission namespaces of the mission-wide topics recorded
    missions: dict[str, str] = {}  # session -> its latest mission message
    sessions: dict[str, int] = {}  # session -> board messages recorded
    for topic, typ, t, msg in _messages(path):
        counts[topic] = counts.get(topic, 0) + 1
        types.setdefault(topic, typ)
        ns = next((n for leaf in (MISSION_TOPIC, RESULT_TOPIC, BOARD_TOPIC, KEYFRAME_TOPIC)
                   if (n := _namespace_of(topic, leaf)) is not None), None)
        if ns is not None:
            spaces.add(ns)
            if len(spaces) > 1:
                raise ReplayError(f"{path}: holds the topics of several missions (mission namespaces "
                                  f"{', '.join(sorted(spaces))}); record one mission per file")
        if ns is not None and topic.endswith(MISSION_TOPIC):  # the latest of a session: robots that joined
            text = getattr(msg, "data", None)
            try:
                missions[str(json.loads(text).get("session"))] = text
            except (TypeError, ValueError, AttributeError):
                missions[""] = text  # (malformed: reported below if it is the one read)
            mission_text = text
        elif ns is not None and topic.endswith(RESULT_TOPIC):
            result_text = getattr(msg, "data", None)
        elif ns is not None:  # the board stream or a keyframe
            text = getattr(msg, "data", None)
            head = _board_header(text)
            if head is not None:
                sessions[str(head.get("session"))] = sessions.get(str(head.get("session")), 0) + 1
            if head is not None and isinstance(head.get("clock"), (int, float)):
                clock.append((t, float(head["clock"])))
            if isinstance(text, str) and text.count("\n") == 2:  # a keyframe (or an hmrta-board/1 board)
                keyframe_text = text
            elif isinstance(text, str):
                heads.append(text)
                del heads[:-50000]
        elif typ in CLOCK_TYPES:
            clock.append((t, _stamp(msg.clock)))
        elif typ in POSE_TYPES and topic.count("/") >= 2:  # <ns>/<robot>/<leaf>
            where, robot, leaf = topic.rsplit("/", 2)
            xy = _position(msg)
            if xy is None:
                continue
            header = getattr(msg, "header", None)
            stamp = _stamp(header.stamp) if header is not None else math.nan
            if leaf == GOAL_LEAF:
                goals.setdefault((where or "/", robot), []).append((stamp, *xy))
            else:
                poses.setdefault((where or "/", robot), []).append((t, stamp, *xy))
    if mission_text is None:
        where = (next(iter(spaces)) if spaces else "/").rstrip("/") + MISSION_TOPIC  # the namespace of its board
        raise ReplayError(f"{path}: no mission message on {where} (record from the mission's start, "
                          f"or with the board running: it is latched)")
    if sessions:  # the mission whose board the recording follows (another board may have published one briefly:
        # a second mission in the namespace, which gave way)
        ran = max(sessions, key=sessions.get)
        mission_text = missions.get(ran, mission_text)
    space = spaces.pop()  # the one mission's namespace: its robots' topics are <space>/<robot>/...
    mission = _json(mission_text, f"the {MISSION_TOPIC} message", path)
    try:
        if not isinstance(mission, dict) or mission.get("format") != "hmrta-mission/1":
            raise ReplayError(f"{path}: the {MISSION_TOPIC} message is not hmrta-mission/1")
        inst = instance_from_dict(mission.get("instance"), source=f"{path} {MISSION_TOPIC}.instance")
    except InstanceError as e:
        raise ReplayError(str(e)) from None
    robots = mission.get("robots")
    if not isinstance(robots, list) or len(robots) != inst.n_agents or not all(isinstance(r, str) for r in robots):
        raise ReplayError(f"{path}: {MISSION_TOPIC}.robots: expected {inst.n_agents} robot names")
    scale = mission.get("scale", 1.0)
    scale = float(scale) if isinstance(scale, (int, float)) and scale > 0 else 1.0
    plan, source = _plan(inst, mission, result_text, keyframe_text, heads, path)
    final = inst
    if plan is not None:  # a mission that changed while it ran: the plan indexes its tasks as it ended
        from .solution import final_instance

        try:
            final = final_instance(inst, plan, f"{path} (recorded {source})")
        except SolutionError as e:
            raise ReplayError(str(e)) from None
        if final.n_agents != len(robots):
            raise ReplayError(f"{path}: the recorded {source} has {final.n_agents} robots, the "
                              f"{MISSION_TOPIC} message names {len(robots)}")
    clock.sort()
    horizon = max((c for _, c in clock), default=math.nan)
    tracks = {r: _track(p, clock, horizon, scale) for (n, r), p in poses.items() if n == space and r in robots}
    goals = {r: [(d, x / scale, y / scale) for d, x, y in g] for (n, r), g in goals.items() if n == space and r in robots}
    return Recording(path, mission, final, list(robots), scale, plan, source, tracks, goals, counts, types, clock,
                     recorded=inst)


def _board_header(text: Any) -> dict[str, Any] | None:
    if not isinstance(text, str):
        return None
    try:
        d = json.loads(text.split("\n", 1)[0])
    except ValueError:
        return None
    return d if isinstance(d, dict) else None


def _plan(inst: Instance, mission: dict, result_text: Any, keyframe_text: Any, heads: list[str],
          path: Path) -> tuple[Solution | None, str]:
    if result_text is not None:
        try:
            return Solution.from_dict(_json(result_text, f"the {RESULT_TOPIC} message", path),
                                      f"{path} {RESULT_TOPIC}"), "result"
        except SolutionError as e:
            raise ReplayError(str(e)) from None
    if keyframe_text is not None:  # no result (the mission did not finish): the latest board's schedule
        from .solution import solution_from_state

        try:
            state = _latest_state(inst, keyframe_text, heads)
            sol = solution_from_state(state, str(mission.get("method", "")), int(mission.get("seed", 0)), 0.0)
            sol.success = False
            sol.extra["partial"] = True
            return sol, "board"
        except (ValueError, KeyError, TypeError, IndexError) as e:
            raise ReplayError(f"{path}: the latest board keyframe: {e}") from None
    return None, "none"


def _latest_state(inst: Instance, keyframe_text: str, heads: list[str]):
    """The board's latest state: the keyframe's, with the versions streamed after it applied (as
    far as they follow on from it); an hmrta-board/1 board's snapshot as it is."""
    from .core import MissionState
    from .replica import Frame, Replica

    head, legs, snap = (json.loads(x) for x in keyframe_text.split("\n", 2))
    if not isinstance(head, dict) or head.get("format") != "hmrta-board/2":
        return MissionState.from_snapshot(inst, snap)
    rep = Replica()
    rep.receive(Frame.from_header(head), lambda: (legs, snap), inst)
    if rep.state is None:
        raise ValueError(rep.why)
    for text in heads:
        try:
            rep.receive(Frame.from_header(json.loads(text)))
        except (ValueError, KeyError, TypeError):
            continue  # not a board header
        if rep.state is None:  # diverged: the keyframe's state is what is known for sure
            rep.receive(Frame.from_header(head), lambda: (legs, snap), inst)
            break
    return rep.state


def _track(poses: list[tuple[int, float, float, float]], clock: list[tuple[int, float]], horizon: float,
           scale: float) -> list[tuple[float, float, float]]:
    """Poses as (mission time, x, y): the header stamp when it lies on the mission clock, else
    the receive time mapped through the clock messages (the latest one received before)."""
    times = [t for t, _ in clock]
    out = []
    for t, stamp, x, y in poses:
        if math.isfinite(stamp) and math.isfinite(horizon) and 0.0 <= stamp <= horizon + 1e-6:
            mt = stamp
        else:
            i = bisect.bisect_right(times, t) - 1
            mt = clock[i][1] if i >= 0 else math.nan
        if math.isfinite(mt):
            out.append((mt, x / scale, y / scale))
    out.sort(key=lambda p: p[0])
    return out


# ---------------------------------------------------------------------------------------------
def render_recording(rec: Recording, out_path: str | Path, tolerance: float | None = None, dpi: int = 110) -> Path:
    """Draw the executed mission: the map with planned routes and the recorded pose tracks, and
    per robot the planned schedule (travel / wait / work bars) with the actual arrivals
    (triangles, joined to the planned arrival). Written atomically; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from .render import _atomic, _draw_gantt, _draw_map, _species_colors, agent_timeline

    inst = rec.instance
    plan = rec.plan if rec.plan is not None else Solution(
        inst.name, str(rec.mission.get("method", "")), 0, False, math.nan, math.nan, math.nan, 0.0,
        [[] for _ in range(inst.n_agents)], [{"start": None, "finish": None, "members": []}] * inst.n_tasks,
        [{"species": int(s), "return_time": math.nan} for s in inst.agent_species])
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    colors = _species_colors(inst.n_species)
    fig = plt.figure(figsize=(15, 7.2))
    gs = fig.add_gridspec(1, 2, width_ratios=[1, 1.45], wspace=0.18)
    ax_map, ax_g = fig.add_subplot(gs[0]), fig.add_subplot(gs[1])
    _draw_map(ax_map, inst, plan, colors)
    _draw_gantt(ax_g, inst, plan, colors, agent_timeline(inst, plan))
    for a, r in enumerate(rec.robots):  # actual tracks
        tr = rec.tracks.get(r, [])
        if tr:
            s = int(inst.agent_species[a])
            ax_map.plot([p[1] for p in tr], [p[2] for p in tr], color=colors[s], lw=0.8, alpha=0.9, marker=".",
                        ms=2.5, zorder=3)
    visits = rec.visits(tolerance)
    late = []
    A = inst.n_agents
    for a, rows in enumerate(visits):
        y = A - 1 - a
        for v in rows:
            if math.isfinite(v["actual_arrival"]):
                ax_g.plot([v["actual_arrival"]], [y + 0.38], marker="v", color="black", ms=4, zorder=6)
                if math.isfinite(v["arrival"]):
                    ax_g.plot([v["arrival"], v["actual_arrival"]], [y + 0.38, y + 0.38], color="black", lw=0.6, zorder=5)
                    late.append(v["actual_arrival"] - v["arrival"])
    ax_g.set_title("planned schedule (bars) vs actual arrivals from the recorded poses (triangles)")
    ax_g.legend(handles=[Line2D([], [], marker="v", color="black", ls="", label="actual arrival (pose)")],
                fontsize=7, loc="upper right", bbox_to_anchor=(1.0, -0.08), frameon=False)
    n_act = sum(math.isfinite(v["actual_arrival"]) for rows in visits for v in rows)
    n_vis = sum(len(rows) for rows in visits)
    title = (f"{inst.name} — recorded mission ({rec.mission.get('method', '?')}, seed {rec.mission.get('seed', '?')}): "
             f"plan from the {rec.plan_source}; {n_act}/{n_vis} arrivals seen")
    if late:
        title += f"; arrival vs plan: max {max(late):+.3f}, mean {sum(late) / len(late):+.3f}"
    if rec.plan is not None and rec.plan.success and math.isfinite(rec.plan.makespan):
        title += f"; makespan {rec.plan.makespan:.3f}"
    fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.04, right=0.98, top=0.91, bottom=0.17)
    with _atomic(out) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return out


def summary(rec: Recording) -> str:
    """A few lines: topics and counts, the plan, the arrivals seen."""
    visits = rec.visits()
    n_act = sum(math.isfinite(v["actual_arrival"]) for rows in visits for v in rows)
    lines = [f"{rec.path}: mission {rec.instance.name}, {len(rec.robots)} robots, {rec.instance.n_tasks} tasks; "
             f"plan from the {rec.plan_source}; {n_act}/{sum(len(r) for r in visits)} arrivals seen in the poses"]
    lines += [f"  {t} ({rec.types.get(t, '?')}): {n}" for t, n in sorted(rec.counts.items())]
    return "\n".join(lines)
