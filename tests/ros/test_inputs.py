"""Standard robot inputs and the mission clock: poses as PoseStamped, PoseWithCovarianceStamped
(``amcl_pose``, silent between filter updates) or nav_msgs/Odometry (the board's ``pose_type`` /
``pose_types``); liveness from the agent heartbeat only; poses in another frame rejected with a
logged reason; the mission clock on ``/hmrta/clock``, never moved by another node's ``/clock``."""
from __future__ import annotations

import dataclasses
import json
import time

import pytest

from conftest import save_instance
from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.board import MissionBoard
from hmrta.generators import ScenarioGenerator
from hmrta.sim import simulate

rclpy = pytest.importorskip("rclpy")
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from hmrta_coordinator.launching import POSE_TYPES as FLEET_POSE_TYPES  # noqa: E402
from hmrta_coordinator.launching import FleetRobot, board_pose_types  # noqa: E402
from hmrta_coordinator.task_board import _pose_types, _waiting_text  # noqa: E402
from hmrta_msgs_py import codec as C  # noqa: E402
from hmrta_msgs_py import topics  # noqa: E402
from test_mission import assert_same_as_offline, robots_of, wait_board_exit  # noqa: E402

HEARTBEAT_TIMEOUT, DRIVE = 5.0, 6.5  # the board's heartbeat_timeout; robot_1's silent drive to each goal (s)
# Nav2's amcl publishes amcl_pose reliable + transient local, depth 1, only on filter updates
AMCL_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


# ---- without DDS ------------------------------------------------------------------------------
def test_pose_types_decode_alike():
    xy, t = (0.25, 0.75), 3.5
    ps = C.pose_to_msg(xy, t, "map", scale=20.0)
    amcl = PoseWithCovarianceStamped(header=ps.header)
    amcl.pose.pose = ps.pose
    odom = Odometry(header=ps.header)
    odom.pose.pose = ps.pose
    for msg in (ps, amcl, odom):
        assert C.pose_from_msg(msg, 20.0) == (0.25, 0.75, 3.5)
    amcl.pose.pose.position.x = float("nan")
    with pytest.raises(C.DecodeError, match="non-finite"):
        C.pose_from_msg(amcl)
    assert set(C.POSE_TYPES) == set(FLEET_POSE_TYPES)  # the fleet file offers what the board reads
    assert [C.pose_type(s) for s in ("odometry", "nav_msgs/msg/Odometry", "PoseWithCovarianceStamped")] == \
        ["Odometry", "Odometry", "PoseWithCovarianceStamped"]
    with pytest.raises(ValueError, match="expected a pose type"):
        C.pose_type("Twist")


def test_start_up_wait_says_how_many_are_missing_and_what_happens_at_the_timeout():
    names = [f"robot_{a}" for a in range(15)]
    text = _waiting_text(names, names, names[:2], 12.4, 120.0)
    assert text == ("waiting for 15 of 15 agents (robot_0, robot_1, robot_2, robot_3, robot_4, robot_5, ..., "
                    "robot_14) and 2 of 15 poses (robot_0, robot_1) for 12 s; at 120 s "
                    "(startup_timeout) the mission starts without the robots still missing")
    assert _waiting_text(names, [], ["robot_3"], 5, 0.0) == \
        "waiting for 1 of 15 poses (robot_3) for 5 s (every agent heard); no limit (startup_timeout 0)"


def test_pose_types_parameter_and_fleet():
    assert _pose_types(["robot_1:odometry", "/robot_2:PoseWithCovarianceStamped"]) == \
        {"robot_1": "Odometry", "robot_2": "PoseWithCovarianceStamped"}
    for bad, why in (("robot_1", "expected ROBOT:TYPE"), ("robot_1:Twist", "expected a pose type")):
        with pytest.raises(ValueError, match=f"pose_types: .*{why}"):
            _pose_types([bad])
    fleet = [FleetRobot("robot_1", "/tb3_1", "/tb3_1/amcl_pose", "PoseWithCovarianceStamped"),
             FleetRobot("robot_2", "/tb3_2", "/tb3_2/pose")]
    assert board_pose_types(fleet, ["robot_1:Odometry", "robot_3:Odometry"]) == \
        ["robot_3:Odometry", "robot_1:PoseWithCovarianceStamped"]


def test_silent_pose_drops_nobody_but_a_silent_agent_does():
    inst = ScenarioGenerator("MA-AT", 4, 2, 6, 3).instance(0, 0)
    now = [0.0]
    b = MissionBoard(inst, seed=0, heartbeat_timeout=5.0, now=lambda: now[0])
    for a in range(inst.n_agents):
        b.heartbeat(b.session, [b.names[a]])
        b.pose(a, *inst.depots[a])
    assert b.started
    for k in range(120):  # 12 s of a board ticking every 0.1 s: every pose silent, robot_1's agent silent too
        now[0] += 0.1
        if k % 10 == 9:
            b.heartbeat(b.session, [n for n in b.names if n != "robot_1"])
        b.tick()
    assert list(b.lost) == [1] and "agent heartbeat" in b.lost[1]


# ---- over DDS ---------------------------------------------------------------------------------
def test_amcl_and_odometry_robots_complete_and_wrong_frames_are_rejected(tmp_path, graph, mission_procs):
    """robot_1 reports PoseWithCovarianceStamped only when it arrives (silent for longer than the
    heartbeat timeout in between): never dropped. robot_2 streams nav_msgs/Odometry. A stray
    publisher sends robot_0's pose in frame 'odom': rejected (logged, counted), nothing changes.
    The heartbeat timeout is the default, 5 s (ten agent heartbeat periods): at 1 s, an agent
    process paused for a moment on a loaded machine is dropped (as test_mission.py's were at
    1.5 s, once in CI). robot_1's drive is longer still, and the leg timeout well above the
    drive (a re-sent goal would repeat one in robot_1's goals)."""
    inst = ScenarioGenerator("SA-AT", 9, 3, 12, 3).instance(1, 0)
    robots = robots_of(inst)
    seed = 5
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots, seed=seed,
                          external=["robot_1", "robot_2"], agents_per_process=4,
                          agent_ros_args={"robot_1": ["-r", "goal_pose:=/tb3_1/goal_pose"],
                                          "robot_2": ["-r", "goal_pose:=/tb3_2/goal_pose"]},
                          board_ros_args=["-r", "/robot_1/pose:=/tb3_1/amcl_pose", "-r", "/robot_2/pose:=/tb3_2/odom"],
                          board_params={"arrival_tolerance": 0.01, "progress_period": 0.0,
                                        "heartbeat_timeout": HEARTBEAT_TIMEOUT, "leg_timeout_floor": 60.0,
                                        "real_time_departures": True,
                                        "pose_types": ["robot_1:PoseWithCovarianceStamped", "robot_2:odometry"]})
    node = graph.node("fake_drivers")
    rejections: list[C.Rejection] = []
    node.create_subscription(String, topics.REJECTIONS, lambda m: rejections.append(C.rejection_from_msg(m)),
                             topics.REJECTION_QOS)
    where = {1: tuple(inst.depots[1]), 2: tuple(inst.depots[2])}
    goals: dict[int, list] = {1: [], 2: []}
    amcl = node.create_publisher(PoseWithCovarianceStamped, "/tb3_1/amcl_pose", AMCL_QOS)
    odom = node.create_publisher(Odometry, "/tb3_2/odom", qos_profile_sensor_data)
    stray = node.create_publisher(PoseStamped, "/robot_0/pose", topics.POSE_PUB_QOS)

    def publish(pub, cls, a: int) -> None:
        ps = C.pose_to_msg(where[a], 0.0)
        msg = cls(header=ps.header)
        msg.pose.pose = ps.pose
        pub.publish(msg)

    amcl_reports: list[float] = []  # when robot_1's pose was published (monotonic s)

    def amcl_update() -> None:
        amcl_reports.append(time.monotonic())
        publish(amcl, PoseWithCovarianceStamped, 1)

    def on_goal(a: int, msg: PoseStamped) -> None:
        x, y, _ = C.pose_from_msg(msg)
        goals[a].append((x, y))
        if a == 1:  # drives for DRIVE s (longer than the heartbeat timeout), one amcl update on arrival
            timer: list = []

            def arrive(xy=(x + 0.002, y - 0.002)) -> None:
                timer[0].cancel()
                where[1] = xy
                amcl_update()
            timer.append(node.create_timer(DRIVE, arrive))
        else:
            where[2] = (x - 0.002, y + 0.002)

    node.create_subscription(PoseStamped, "/tb3_1/goal_pose", lambda m: on_goal(1, m), 10)
    node.create_subscription(PoseStamped, "/tb3_2/goal_pose", lambda m: on_goal(2, m), 10)
    amcl_update()  # amcl's initial pose (latched: the board gets it whenever it subscribes)
    node.create_timer(0.2, lambda: publish(odom, Odometry, 2))
    node.create_timer(0.5, lambda: stray.publish(C.pose_to_msg((0.5, 0.5), 0.0, "odom")))
    wait_board_exit(graph, procs, 150)

    result = json.loads((tmp_path / "result.json").read_text())
    assert result["lost_robots"] == [], result.get("lost_reasons")
    assert_same_as_offline(result, inst, seed,
                           ref=simulate(inst, Greedy(), seed, dataclasses.replace(GREEDY_RULES, backdate=False)))
    for a in (1, 2):
        route = [tuple(inst.task_locations[m]) for m in result["routes"][a]]
        assert [g for g in goals[a] if g != tuple(inst.depots[a])] == route and goals[a][-1] == tuple(inst.depots[a])
    assert len(goals[1]) >= 2 and len(amcl_reports) <= len(goals[1]) + 1  # silent but for its arrivals
    silences = [b - a for a, b in zip(amcl_reports, amcl_reports[1:])]
    assert silences and min(silences) > HEARTBEAT_TIMEOUT, silences  # each longer than the heartbeat timeout
    assert result["rejected_messages"].get("wrong_frame", 0) > 0
    assert rejections and {r.reason for r in rejections} == {"wrong_frame"} and rejections[0].robot == "robot_0"
    log = procs.board.log.read_text()
    assert "pose of robot_0 in frame 'odom', expected 'map'" in log


def test_foreign_clock_moves_nothing(tmp_path, graph, mission_procs):
    """A simulator's /clock (t = 1004, over and over) during a sim-time mission: the mission runs
    on /hmrta/clock, completes, and equals the offline rollout."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    seed = 3
    node = graph.node("gazebo")
    clock = node.create_publisher(Clock, "/clock", topics.CLOCK_QOS)
    sent = [0]

    def tick() -> None:
        clock.publish(C.clock_to_msg(1004.0))
        sent[0] += 1

    node.create_timer(0.05, tick)
    boards: list[C.Board] = []  # the stream's headers and keyframes this node hears (the mission lasts
    # about a second: the board may finish and exit before DDS discovery matched this node, so the
    # result is the evidence and the boards heard, if any, a second look)
    for name, qos in ((topics.BOARD, topics.BOARD_QOS), (topics.KEYFRAME, topics.KEYFRAME_QOS)):
        node.create_subscription(String, name, lambda m: boards.append(C.board_from_msg(m, state=False)), qos)
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots_of(inst), seed=seed,
                          agents_per_process=6, board_params={"progress_period": 0.0})
    wait_board_exit(graph, procs, 150)
    assert sent[0] > 10  # the foreign clock ran through the mission
    result = json.loads((tmp_path / "result.json").read_text())
    assert_same_as_offline(result, inst, seed)  # a clock taken from /clock would end it past t=1004
    assert result["lost_robots"] == [] and result["makespan"] < 1004.0
    assert all(b.clock < 1004.0 for b in boards)


def test_a_stray_clock_on_the_mission_clock_topic_cannot_run_the_mission_ahead(tmp_path, graph, mission_procs):
    """Another node publishes t = 100000 on /hmrta/clock itself (a recording played back, another
    mission's sim_robot) through a paced mission: the board and the agents follow it only up to
    the horizons the board published (the board warns); the mission equals the offline rollout.
    Paced at 2x (about 18 s): this node and the board must discover each other while the board
    runs (at 8x, in a 4.6 s mission, a slow discovery left both the boards heard and the warning
    empty), and the latched keyframe reaches this node whenever it matches before the board exits."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    seed = 3
    node = graph.node("stray_clock")
    clock = node.create_publisher(Clock, topics.CLOCK, topics.CLOCK_QOS)
    sent = [0]

    def tick() -> None:
        if clock.get_subscription_count() > 0:
            clock.publish(C.clock_to_msg(100000.0 + sent[0]))
            sent[0] += 1

    node.create_timer(0.2, tick)
    boards: list[C.Board] = []
    for name, qos in ((topics.BOARD, topics.BOARD_QOS), (topics.KEYFRAME, topics.KEYFRAME_QOS)):
        node.create_subscription(String, name, lambda m: boards.append(C.board_from_msg(m, state=False)), qos)
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots_of(inst), seed=seed,
                          agents_per_process=6, time_scale=2.0, board_params={"progress_period": 0.0})
    wait_board_exit(graph, procs, 150)
    assert sent[0] > 5  # the stray clock ran through the mission
    assert boards and all(b.clock < 1000.0 for b in boards)  # the board's clock never followed it
    result = json.loads((tmp_path / "result.json").read_text())
    assert_same_as_offline(result, inst, seed)
    assert result["lost_robots"] == [] and result["makespan"] < 1000.0
    assert "past the board's horizon" in procs.board.log.read_text()


def test_a_stray_clock_heard_before_the_missions_own_is_held_to_the_horizons(tmp_path, graph):
    """A latched stray clock (t = 100000) is the first clock the board hears: it waits for its own
    mission's clock rather than stop (as it does where none comes: test_board_crash.py), takes
    sim_robot's when it comes, and the mission equals the offline rollout. The board starts alone,
    so the order is sure."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from hmrta_coordinator.mission import ros_params

    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    path, out, seed = save_instance(inst, tmp_path / "inst.yaml"), tmp_path / "result.json", 3
    node = graph.node("stray_clock")
    clock = node.create_publisher(Clock, topics.CLOCK, topics.CLOCK_QOS)
    node.create_timer(0.2, lambda: clock.publish(C.clock_to_msg(100000.0)))
    env = {**os.environ, "ROS_DOMAIN_ID": str(graph.domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOG_DIR": str(tmp_path / "ros")}
    bin_ = Path(sys.executable).parent
    logs, procs = {}, {}

    def spawn(name: str, cmd: list[str]) -> None:
        logs[name] = open(tmp_path / f"{name}.log", "w")
        procs[name] = subprocess.Popen(cmd, stdout=logs[name], stderr=subprocess.STDOUT, env=env)

    def text(name: str) -> str:
        return (tmp_path / f"{name}.log").read_text()

    try:
        spawn("board", [str(bin_ / "task_board"), "--ros-args",
                        *ros_params({"instance": str(path), "seed": seed, "output": str(out), "progress_period": 0.0})])
        graph.spin_until(lambda: "another publisher's; waiting for this mission's own" in text("board") or procs["board"].poll() is not None,
                         60, "the board to hear the stray clock first")
        spawn("sim", [str(bin_ / "sim_robot"), "--ros-args", *ros_params({"time_scale": 8.0})])
        spawn("agents", [str(bin_ / "agent_node"), "--robots", ",".join(robots_of(inst)), "--ros-args",
                         *ros_params({"seed": seed})])
        graph.spin_until(lambda: procs["board"].poll() is not None, 150, "the board to finish the mission")
        assert procs["board"].returncode == 0, text("board")[-3000:]
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
            p.wait()
        for f in logs.values():
            f.close()
    log = text("board")
    assert "heard: this mission's own" in log and "past the board's horizon" in log, log[-3000:]
    result = json.loads(out.read_text())  # (every node on its default method: the board's portfolio choice)
    assert_same_as_offline(result, inst, seed, "portfolio")
    assert result["lost_robots"] == [] and result["makespan"] < 1000.0
