"""hmrta.replay: reading a recorded mission (MCAP, ROS 2 CDR) back without ROS, on small
recordings written here with mcap-ros2-support, and its errors (``hmrta render --from``)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

pytest.importorskip("mcap_ros2")
pytest.importorskip("matplotlib")

from mcap_ros2.writer import Writer  # noqa: E402

from hmrta.cli import main as cli_main  # noqa: E402
from hmrta.core import MissionState  # noqa: E402
from hmrta.formats import load_instance  # noqa: E402
from hmrta.generators import ScenarioGenerator  # noqa: E402
from hmrta.methods import solve  # noqa: E402
from hmrta.render import agent_timeline  # noqa: E402
from hmrta.replay import ReplayError, read_recording, render_recording  # noqa: E402
from hmrta.solution import solution_from_state  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[2] / "policy" / "hmrta" / "data" / "example.yaml"
STRING = "string data\n"
TIME = "int32 sec\nuint32 nanosec\n"
SEP = "=" * 80
CLOCK = f"builtin_interfaces/Time clock\n{SEP}\nMSG: builtin_interfaces/Time\n{TIME}"
POSE = (f"std_msgs/Header header\nPose pose\n{SEP}\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\n"
        f"string frame_id\n{SEP}\nMSG: builtin_interfaces/Time\n{TIME}{SEP}\nMSG: geometry_msgs/Pose\n"
        f"Point position\nQuaternion orientation\n{SEP}\nMSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n"
        f"{SEP}\nMSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n")
T0 = 1_700_000_000_000_000_000  # receive times (wall ns)
SCALE = 10.0  # frame units (metres) per mission unit


def _stamp(t: float) -> dict:
    ns = int(round(t * 1e9))
    return {"sec": ns // 10**9, "nanosec": ns % 10**9}


def _pose(t: float, x: float, y: float) -> dict:
    return {"header": {"stamp": _stamp(t), "frame_id": "map"},
            "pose": {"position": {"x": x * SCALE, "y": y * SCALE, "z": 0.0},
                     "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}


def mission_payload(inst, robots) -> str:
    return json.dumps({"format": "hmrta-mission/1", "session": "s1", "instance": inst.to_dict(), "robots": robots,
                       "seed": 0, "method": "greedy", "frame_id": "map", "scale": SCALE, "rules": {}})


def write_recording(path: Path, *, mission=True, result=True, board=False, poses=True, wall_stamps=False,
                    late: float = 0.0, namespace: str = "", extra: tuple = (), grown: tuple | None = None) -> tuple:
    """A recording of the greedy plan of the example, its robots arriving on time (+ ``late``):
    poses stamped with the mission clock, or (``wall_stamps``) with wall time, clocks on /clock;
    the mission's topics in the mission namespace ``namespace`` ('/fleet1'; '' the root), plus
    the messages ``extra`` ((mission time, topic, schema, message)). ``grown``: (the mission the
    board published, the result, the mission as it ended) of a mission that changed while it ran."""
    if grown is None:
        inst = load_instance(EXAMPLE)
        sol = solve(inst, "greedy", 0)
        published = inst
    else:
        published, sol, inst = grown
    robots = [f"robot_{a}" for a in range(inst.n_agents)]
    msgs: list[tuple[float, str, str, dict]] = []  # (mission time, topic, schema, message)
    if mission:
        msgs.append((-1.0, "/hmrta/mission", "std_msgs/msg/String", {"data": mission_payload(published, robots)}))
    if board == "v1":  # a recording made before the board stream: a full board on every version
        snap = MissionState(inst, seed=0).snapshot()
        head = {"format": "hmrta-board/1", "session": "s1", "version": 1, "rev": 0, "phase": "wait", "clock": 0.0}
        msgs.append((0.0, "/hmrta/board", "std_msgs/msg/String",
                     {"data": "\n".join((json.dumps(head), "[]", json.dumps(snap)))}))
    elif board:  # the board stream and its keyframes, up to the board's version ``board``
        msgs += board_messages(inst, board)
    for a, segs in enumerate(agent_timeline(inst, sol)):
        if poses:  # where each robot is when the recording starts (a simulated robot publishes at once)
            msgs.append((0.0, f"/{robots[a]}/pose", "geometry_msgs/msg/PoseStamped",
                         _pose(T0 * 1e-9 if wall_stamps else 0.0, *inst.depots[a])))
        for s in segs:
            if s["kind"] == "travel" and poses:
                t = s["t1"] + late
                stamp = (T0 * 1e-9 + t) if wall_stamps else t
                msgs.append((s["t0"], f"/{robots[a]}/goal_pose", "geometry_msgs/msg/PoseStamped", _pose(s["t0"], *s["p1"])))
                msgs.append((t, f"/{robots[a]}/pose", "geometry_msgs/msg/PoseStamped", _pose(stamp, *s["p1"])))
    msgs = [(t, namespace + topic, schema, m) for t, topic, schema, m in msgs] + list(extra)
    ticks = sorted({m[0] for m in msgs if m[0] >= 0} | {0.0})
    msgs += [(t, "/clock", "rosgraph_msgs/msg/Clock", {"clock": _stamp(t)}) for t in ticks]
    if result:
        msgs.append((sol.makespan + 1, namespace + "/hmrta/result", "std_msgs/msg/String",
                     {"data": json.dumps(sol.to_dict())}))
    msgs.sort(key=lambda m: (m[0], m[2] != "rosgraph_msgs/msg/Clock"))  # a clock tick before what happens at it
    defs = {"std_msgs/msg/String": STRING, "geometry_msgs/msg/PoseStamped": POSE, "rosgraph_msgs/msg/Clock": CLOCK}
    with open(path, "wb") as f, Writer(f) as w:
        schemas = {name: w.register_msgdef(name, text) for name, text in defs.items()}
        for i, (t, topic, schema, msg) in enumerate(msgs):
            w.write_message(topic, schemas[schema], msg, log_time=T0 + int(max(t + 1.0, 0) * 1e9) + i)
    return inst, sol, robots


def board_messages(inst, until: int) -> list:
    """What a board publishes (stream headers, keyframes) running greedy on ``inst`` up to its
    version ``until``; the board is kept in ``board_messages.board``."""
    from hmrta.board import MissionBoard, board_header
    from hmrta.baselines import GREEDY_RULES
    from test_board import greedy_turn

    b = MissionBoard(inst, seed=0, rules=GREEDY_RULES, wait_for_robots=False, tolerance=1e9, keyframe_period=7,
                     session="s1")
    for a in range(inst.n_agents):
        b.pose(a, *inst.depots[a])
    out = []
    while b.version < until:
        v = b.poll()
        if v is not None:
            head = json.dumps(board_header(v))
            out.append((v.clock, "/hmrta/board", "std_msgs/msg/String", {"data": head}))
            if v.keyframe:
                text = "\n".join((json.dumps(board_header(v)), json.dumps(v.legs), v.state_json))
                out.append((v.clock, "/hmrta/board_keyframe", "std_msgs/msg/String", {"data": text}))
        if b.version >= until:
            break
        greedy_turn(b)
    board_messages.board = b
    return out


def test_reads_back_mission_plan_tracks_and_counts(tmp_path):
    inst, sol, robots = write_recording(tmp_path / "r.mcap")
    rec = read_recording(tmp_path / "r.mcap")
    assert rec.instance.to_dict() == inst.to_dict() and rec.robots == robots and rec.scale == SCALE
    assert rec.plan_source == "result" and rec.routes == sol.routes and rec.plan.makespan == sol.makespan
    assert rec.counts["/hmrta/mission"] == 1 and rec.counts["/hmrta/result"] == 1
    assert rec.types["/robot_0/pose"] == "geometry_msgs/msg/PoseStamped"
    n_travel = sum(s["kind"] == "travel" for segs in agent_timeline(inst, sol) for s in segs)
    assert sum(rec.counts[f"/{r}/pose"] for r in robots if f"/{r}/pose" in rec.counts) == n_travel + inst.n_agents
    # tracks in mission coordinates (the wire carries x scale) and mission time
    assert rec.tracks["robot_0"][0] == pytest.approx((0.0, *inst.depots[0]))
    t, x, y = rec.tracks["robot_0"][1]
    first = agent_timeline(inst, sol)[0][0]
    assert (x, y) == pytest.approx(first["p1"]) and t == pytest.approx(first["t1"], abs=1e-9)
    visits = rec.visits()
    assert [[v["task"] for v in rows] for rows in visits] == sol.routes
    for rows in visits:
        for v in rows:
            assert v["actual_arrival"] == pytest.approx(v["arrival"], abs=1e-6)


def test_a_mission_in_a_namespace_reads_back_from_its_own_topics(tmp_path):
    """A mission run with mission_namespace /fleet1: its topics are /fleet1/hmrta/... and
    /fleet1/<robot>/...; another robot's topic outside it is not its robot's; a file holding the
    mission topics of two namespaces is refused (one line naming them)."""
    stray = ((0.5, "/robot_0/pose", "geometry_msgs/msg/PoseStamped", _pose(0.5, 0.9, 0.9)),)
    inst, sol, robots = write_recording(tmp_path / "ns.mcap", namespace="/fleet1", extra=stray)
    rec = read_recording(tmp_path / "ns.mcap")
    assert rec.plan_source == "result" and rec.routes == sol.routes and rec.robots == robots
    ref = read_recording(write_recording(tmp_path / "root.mcap")[0] and tmp_path / "root.mcap")
    assert rec.tracks == ref.tracks and rec.goals == ref.goals  # the stray /robot_0/pose is not fleet1's robot_0
    assert rec.counts["/fleet1/hmrta/mission"] == 1 and rec.counts["/robot_0/pose"] == 1
    other = ((0.5, "/fleet2/hmrta/board", "std_msgs/msg/String", {"data": "{}"}),)
    write_recording(tmp_path / "two.mcap", namespace="/fleet1", extra=other)
    with pytest.raises(ReplayError, match=r"two\.mcap: holds the topics of several missions \(mission namespaces "
                                          r"/fleet1, /fleet2\); record one mission per file"):
        read_recording(tmp_path / "two.mcap")


def test_the_latest_mission_message_is_the_mission(tmp_path):
    """The board publishes the mission again when robots join (same session, more robots): the
    recording is read with the latest one of the session whose board it recorded."""
    other = ScenarioGenerator("MA-AT", 4, 2, 5, 3).instance(1, 0)
    early = ((-2.0, "/hmrta/mission", "std_msgs/msg/String",
              {"data": mission_payload(other, [f"robot_{a}" for a in range(other.n_agents)])}),)
    inst, sol, robots = write_recording(tmp_path / "r.mcap", extra=early)
    rec = read_recording(tmp_path / "r.mcap")
    assert rec.instance.to_dict() == inst.to_dict() and rec.robots == robots and rec.routes == sol.routes
    # a mission of another session published later (a second board in the namespace, which gave
    # way): the recording follows the board whose stream it holds
    stray = json.loads(mission_payload(other, [f"robot_{a}" for a in range(other.n_agents)]))
    stray["session"] = "s2"
    late = ((0.5, "/hmrta/mission", "std_msgs/msg/String", {"data": json.dumps(stray)}),)
    inst, sol, robots = write_recording(tmp_path / "s.mcap", board=6, extra=late)
    rec = read_recording(tmp_path / "s.mcap")
    assert rec.instance.to_dict() == inst.to_dict() and rec.routes == sol.routes


def test_no_arrival_is_read_from_a_robot_first_heard_at_its_task(tmp_path):
    """A recorder that hears a robot first when it is already at its task (it subscribed late)
    saw no arrival: that visit's is NaN, the robot's later visits are seen."""
    inst, sol, robots = write_recording(tmp_path / "r.mcap")
    rec = read_recording(tmp_path / "r.mcap")
    a = next(a for a, route in enumerate(sol.routes) if len(route) >= 2)
    track = rec.tracks[robots[a]]
    rec.tracks[robots[a]] = [(t + 5.0, x, y) for t, x, y in track[1:2]] + track[2:]  # heard first at its task, late
    rows = rec.visits()[a]
    assert math.isnan(rows[0]["actual_arrival"])
    assert rows[1]["actual_arrival"] == pytest.approx(rows[1]["arrival"], abs=1e-6)
    assert all(v["actual_arrival"] == pytest.approx(v["arrival"], abs=1e-6) for b, vs in enumerate(rec.visits())
               if b != a for v in vs)


def test_late_robots_and_wall_clock_stamps_map_through_the_clock(tmp_path):
    """Poses stamped with wall time (a real robot) take the mission clock of their receive time;
    arrivals 0.5 late show as late."""
    inst, sol, _ = write_recording(tmp_path / "r.mcap", wall_stamps=True, late=0.5)
    rec = read_recording(tmp_path / "r.mcap")
    lates = [v["actual_arrival"] - v["arrival"] for rows in rec.visits() for v in rows]
    assert lates and all(0.0 <= d <= 0.5 + 1e-6 for d in lates)
    assert max(lates) == pytest.approx(0.5, abs=1e-6)  # a pose received at a clock tick of its own


def test_without_result_the_plan_comes_from_the_board(tmp_path):
    write_recording(tmp_path / "r.mcap", result=False, board="v1")
    rec = read_recording(tmp_path / "r.mcap")
    assert rec.plan_source == "board" and rec.plan.extra["partial"] and not rec.plan.success
    # the board stream: the latest keyframe with the versions streamed after it applied
    write_recording(tmp_path / "s.mcap", result=False, board=40)
    b = board_messages.board
    rec = read_recording(tmp_path / "s.mcap")
    assert rec.plan_source == "board" and rec.plan.extra["partial"]
    assert rec.counts["/hmrta/board"] == 40 and 1 < rec.counts["/hmrta/board_keyframe"] < 40
    assert rec.routes == [list(map(int, r)) for r in b.state.routes] and any(rec.routes)
    want = json.loads(json.dumps(solution_from_state(b.state, "greedy", 0, 0.0).to_dict()))["tasks"]
    assert json.loads(json.dumps(rec.plan.to_dict()))["tasks"] == want
    write_recording(tmp_path / "n.mcap", result=False, board=False, poses=False)
    rec = read_recording(tmp_path / "n.mcap")
    assert rec.plan is None and rec.plan_source == "none" and rec.visits() == [[] for _ in rec.robots]
    assert render_recording(rec, tmp_path / "n.png").stat().st_size > 0


def test_render_from_recording(tmp_path, capsys):
    _, sol, _ = write_recording(tmp_path / "r.mcap", late=0.25)
    n = sum(map(len, sol.routes))
    out = tmp_path / "fig" / "replay.png"
    assert cli_main(["render", "--from", str(tmp_path / "r.mcap"), "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    assert cli_main(["render", str(EXAMPLE), "--from", str(tmp_path / "r.mcap"), "--out", str(out)]) == 0
    assert f"{n}/{n} arrivals" in capsys.readouterr().out


def test_a_mission_that_changed_while_it_ran_reads_back_and_draws(tmp_path, capsys):
    """Tasks added and a robot joined while it ran: the board published the mission with the robot
    that joined (not the added tasks); the result indexes the mission as it ended, which the
    recording reads back (``instance``) and draws, also checked against the mission's own file."""
    import dataclasses

    from hmrta.solution import final_instance

    (tmp_path / "mission.yaml").write_text(EXAMPLE.read_text())
    scen = tmp_path / "scen.yaml"
    scen.write_text("format: hmrta-scenario/1\ninstance: mission.yaml\nevents:\n"
                    "  - {t: 1.0, type: add_robot, species: 0}\n"
                    "  - {t: 2.0, type: add_task, id: extra, location: [0.5, 0.5], requirements: [1, 0, 0, 0, 0], "
                    "duration: 2}\n")
    base = load_instance(scen)
    sol = solve(base, "greedy", 0)
    ended = final_instance(base, sol)
    mission = load_instance(tmp_path / "mission.yaml")
    assert (ended.n_agents, ended.n_tasks) == (mission.n_agents + 1, mission.n_tasks + 1)
    published = dataclasses.replace(ended, tasks=mission.tasks, _cache={})  # robots that joined, not added tasks
    write_recording(tmp_path / "g.mcap", grown=(published, sol, ended))
    rec = read_recording(tmp_path / "g.mcap")
    assert rec.instance.to_dict() == ended.to_dict() and rec.recorded.to_dict() == published.to_dict()
    n = sum(map(len, sol.routes))
    out = tmp_path / "g.png"
    assert cli_main(["render", "--from", str(tmp_path / "g.mcap"), "--out", str(out)]) == 0
    assert cli_main(["render", str(tmp_path / "mission.yaml"), "--from", str(tmp_path / "g.mcap"), "--out", str(out)]) == 0
    assert f"{n}/{n} arrivals" in capsys.readouterr().out and out.stat().st_size > 10_000
    other = ScenarioGenerator("MA-AT", 4, 2, 5, 3).instance(1, 0)
    other.save(tmp_path / "other.yaml")
    short = dataclasses.replace(mission, tasks=mission.tasks[:3], _cache={})  # the mission's first tasks only
    short.save(tmp_path / "short.yaml")
    for wrong in ("other.yaml", "short.yaml"):
        assert "is not the instance" in _one_line_error(
            ["render", str(tmp_path / wrong), "--from", str(tmp_path / "g.mcap"), "--out", str(out)], capsys)


def _one_line_error(args, capsys) -> str:
    assert cli_main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hmrta: error: "), err
    return err


def test_errors_are_one_line(tmp_path, capsys):
    out = str(tmp_path / "x.png")
    (tmp_path / "t.mcap").write_text("hello")
    assert "not an MCAP file" in _one_line_error(["render", "--from", str(tmp_path / "t.mcap"), "--out", out], capsys)
    assert "no such file" in _one_line_error(["render", "--from", str(tmp_path / "no.mcap"), "--out", out], capsys)
    write_recording(tmp_path / "nm.mcap", mission=False)
    assert "no mission message" in _one_line_error(["render", "--from", str(tmp_path / "nm.mcap"), "--out", out],
                                                  capsys)
    write_recording(tmp_path / "r.mcap")
    data = (tmp_path / "r.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    err = _one_line_error(["render", "--from", str(tmp_path / "cut.mcap"), "--out", out], capsys)
    assert "cut.mcap" in err
    other = tmp_path / "other.yaml"
    other.write_text(EXAMPLE.read_text().replace("velocity: 0.2", "velocity: 0.3", 1))
    assert "is not the instance" in _one_line_error(
        ["render", str(other), "--from", str(tmp_path / "r.mcap"), "--out", out], capsys)
    assert "not a solution file" in _one_line_error(
        ["render", str(EXAMPLE), "s.json", "--from", str(tmp_path / "r.mcap"), "--out", out], capsys)
    assert "INSTANCE and SOLUTION" in _one_line_error(["render", "--out", out], capsys)
    assert not (tmp_path / "x.png").exists()  # nothing drawn for a refused recording


def test_malformed_mission_payload(tmp_path):
    with open(tmp_path / "b.mcap", "wb") as f, Writer(f) as w:
        s = w.register_msgdef("std_msgs/msg/String", STRING)
        w.write_message("/hmrta/mission", s, {"data": "{not json"}, log_time=T0)
    with pytest.raises(ReplayError, match=r"b\.mcap: the /hmrta/mission message is not valid JSON"):
        read_recording(tmp_path / "b.mcap")
    with open(tmp_path / "c.mcap", "wb") as f, Writer(f) as w:
        s = w.register_msgdef("std_msgs/msg/String", STRING)
        w.write_message("/hmrta/mission", s, {"data": json.dumps({"format": "hmrta-mission/9"})}, log_time=T0)
    with pytest.raises(ReplayError, match="is not hmrta-mission/1"):
        read_recording(tmp_path / "c.mcap")
    assert math.isfinite(T0)


def test_a_recording_path_that_is_no_file_says_what_it_is(tmp_path):
    import os

    from hmrta.replay import ReplayError, read_recording

    os.mkfifo(tmp_path / "fifo.mcap")
    (tmp_path / "dir.mcap").mkdir()
    for name, what in (("fifo.mcap", "not a regular file"), ("dir.mcap", "is a folder"), ("none.mcap", "no such file")):
        with pytest.raises(ReplayError, match=f"{name}: {what} .expected an MCAP recording.$"):
            read_recording(tmp_path / name)


def test_a_cut_short_recording_is_named_damaged(tmp_path):
    from hmrta.replay import MAGIC, ReplayError, read_recording

    (tmp_path / "short.mcap").write_bytes(MAGIC + b"x" * 8)
    with pytest.raises(ReplayError, match="short.mcap: damaged or cut short MCAP"):
        read_recording(tmp_path / "short.mcap")
