"""External robots never hang a mission: fake drivers (small rclpy nodes of the test) consume a
robot's goals and publish its pose as it moves, like a Nav2 robot would. One stops 0.2 m short
of every goal (within the 0.25 m arrival tolerance: the mission completes), one never arrives (its
goal is re-sent once, then it is dropped as stuck and the others finish), one is slower than
planned (the mission completes, late)."""
from __future__ import annotations

import dataclasses
import json
import math

import pytest

from conftest import save_instance
from test_mission import wait_board_exit
from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.generators import ScenarioGenerator
from hmrta.sim import simulate

rclpy = pytest.importorskip("rclpy")
from geometry_msgs.msg import PoseStamped, PoseWithCovariance, PoseWithCovarianceStamped  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402

from hmrta_msgs_py import topics  # noqa: E402
from hmrta_msgs_py import codec as C  # noqa: E402

SCALE = 10.0  # metres per mission unit: the mission area is 10 m x 10 m
INST = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
ROBOTS = [f"robot_{a}" for a in range(INST.n_agents)]
EXT, SEED = "robot_1", 5


class FakeDriver:
    """Drives robot ``name`` in wall time at ``speed`` mission units per second towards each goal,
    stopping ``short`` mission units before it (``ignore``: never moves), publishing its pose at
    20 Hz; records every goal and, at each stop, the mission clock and the planned arrival."""

    def __init__(self, graph, name: str, speed: float, short: float = 0.0, ignore: bool = False,
                 pose_type: str = "PoseStamped", frame: str = "map"):
        self.node = graph.node(f"driver_{name}")
        self.frame = frame  # of the poses it publishes
        a = ROBOTS.index(name)
        self.pos = (float(INST.depots[a, 0]), float(INST.depots[a, 1]))
        self.speed, self.short, self.ignore = speed, short, ignore
        self.target: tuple[float, float] | None = None
        self.planned = 0.0  # planned arrival of the current goal (mission time)
        self.clock = 0.0
        self.goals: list[tuple[float, float, float]] = []
        self.yaws: list[float | None] = []  # each goal's heading
        self.stops: list[tuple[float, float]] = []  # (mission clock, planned arrival) at each stop
        self.amcl = pose_type == "PoseWithCovarianceStamped"  # as Nav2's amcl: amcl_pose, latched
        self.pub = self.node.create_publisher(PoseWithCovarianceStamped, topics.robot_topic(name, "amcl_pose"),
                                              topics.AMCL_POSE_SUB_QOS) if self.amcl else \
            self.node.create_publisher(PoseStamped, topics.robot_topic(name, topics.POSE), qos_profile_sensor_data)
        self.node.create_subscription(PoseStamped, topics.robot_topic(name, topics.GOAL), self.on_goal, 10)
        self.node.create_subscription(Clock, topics.CLOCK, self.on_clock, topics.CLOCK_QOS)
        self.node.create_timer(0.05, self.step)

    def on_clock(self, msg: Clock) -> None:
        self.clock = max(self.clock, C.clock_from_msg(msg))

    def on_goal(self, msg: PoseStamped) -> None:
        x, y, t = C.pose_from_msg(msg, SCALE)
        self.goals.append((x, y, t))
        self.yaws.append(C.yaw_from_msg(msg))
        if self.ignore:
            return
        d = math.hypot(x - self.pos[0], y - self.pos[1])
        f = max(0.0, d - self.short) / d if d > 0 else 0.0
        self.target = (self.pos[0] + (x - self.pos[0]) * f, self.pos[1] + (y - self.pos[1]) * f)
        self.planned = t + d / INST.velocity

    def step(self) -> None:
        if self.target is not None:
            dx, dy = self.target[0] - self.pos[0], self.target[1] - self.pos[1]
            d, s = math.hypot(dx, dy), self.speed * 0.05
            if d <= s:
                self.pos, self.target = self.target, None
                self.stops.append((self.clock, self.planned))
            else:
                self.pos = (self.pos[0] + dx / d * s, self.pos[1] + dy / d * s)
        msg = C.pose_to_msg(self.pos, self.clock, self.frame, SCALE)
        if self.amcl:
            msg = PoseWithCovarianceStamped(header=msg.header, pose=PoseWithCovariance(pose=msg.pose))
        self.pub.publish(msg)


def run(tmp_path, graph, mission_procs, board: dict, time_scale: float = 0.0, **driver) -> tuple[dict, FakeDriver]:
    amcl = {}
    if driver.get("pose_type") == "PoseWithCovarianceStamped":  # the board and the robot's agent read amcl_pose
        amcl = {"board_ros_args": ["-r", f"/{EXT}/pose:=/{EXT}/amcl_pose"],
                "agent_ros_args": {EXT: ["-r", "pose:=amcl_pose", "-p", "pose_type:=PoseWithCovarianceStamped"]}}
        board = {**board, "pose_types": [f"{EXT}:PoseWithCovarianceStamped"]}
    procs = mission_procs(save_instance(INST, tmp_path / "inst.yaml"), ROBOTS, seed=SEED, external=[EXT],
                          agents_per_process=6, time_scale=time_scale,
                          board_params={"scale": SCALE, "progress_period": 0.0, "real_time_departures": True,
                                        **board}, **amcl)
    fake = FakeDriver(graph, EXT, **driver)
    wait_board_exit(graph, procs, 90)
    return json.loads((tmp_path / "result.json").read_text()), fake


def offline() -> dict:
    ref = simulate(INST, Greedy(), SEED, dataclasses.replace(GREEDY_RULES, backdate=False))
    return json.loads(json.dumps(ref.to_dict()))


def test_a_robot_that_stops_0_2_m_short_has_arrived(tmp_path, graph, mission_procs):
    result, fake = run(tmp_path, graph, mission_procs, {"leg_timeout_factor": 1.0, "leg_timeout_floor": 5.0},
                       speed=2.0, short=0.2 / SCALE)
    assert result["lost_robots"] == [] and result["undone_tasks"] == []
    ref = offline()
    for k in ("success", "routes", "makespan"):
        assert result[k] == ref[k], k
    assert len(fake.stops) >= 2  # it drove its route (and home), always 0.2 m short
    # every goal is headed along its leg (from the previous goal; the first from the depot), not
    # at a fixed heading that a navigation stack would turn the robot to at every goal
    start = tuple(INST.depots[ROBOTS.index(EXT)])
    for (x, y, _), yaw in zip(fake.goals, fake.yaws):
        if math.dist((x, y), start) > 1e-9:
            assert yaw is not None and abs(math.remainder(yaw - math.atan2(y - start[1], x - start[0]), math.tau)) < 1e-6
        start = (x, y)


@pytest.mark.parametrize("pose_type", ["PoseStamped", "PoseWithCovarianceStamped"])
def test_a_robot_that_never_arrives_is_dropped_as_stuck_and_the_rest_finish(tmp_path, graph, mission_procs,
                                                                            pose_type):
    """... and its agent stops it where it is, reading its pose as the board does (a Nav2 robot's
    amcl_pose too: once, its agent followed only a PoseStamped on pose and sent no stop)."""
    result, fake = run(tmp_path, graph, mission_procs, {"leg_timeout_factor": 1.0, "leg_timeout_floor": 2.0},
                       speed=2.0, ignore=True, pose_type=pose_type)
    assert result["lost_robots"] == [EXT]
    reason = result["lost_reasons"][EXT]
    assert reason.startswith("stuck: no arrival at task ") and "np.float64" not in reason
    first = fake.goals[0]
    assert fake.goals.count(first) == 2  # the goal was re-sent once before the robot was dropped
    # ... and then it was told to stop: a goal where it is (it never moved from its depot)
    assert len(fake.goals) == 3 and math.dist(fake.goals[-1][:2], fake.pos) < 1e-6, fake.goals
    lost = ROBOTS.index(EXT)
    team = INST.traits[[a for a in range(INST.n_agents) if a != lost]].sum(0)
    for m in result["undone_tasks"]:
        assert not (INST.requirements[m] <= team).all(), f"task {m} was satisfiable without {EXT}"
    assert all(r["return_time"] is not None for a, r in enumerate(result["agents"]) if a != lost)


def test_a_robot_whose_poses_are_in_another_frame_is_dropped_saying_so_and_never_sent_a_goal_there(
        tmp_path, graph, mission_procs):
    """Nav2's odometry is in frame odom: the board rejects every pose of that robot, drops it at
    the start-up timeout saying why (not as a robot that never reported), and its agent, which
    stops a dropped robot where it is, sends no stop goal made of odom coordinates (a place on the
    map the robot would drive to)."""
    procs = mission_procs(save_instance(INST, tmp_path / "inst.yaml"), ROBOTS, seed=SEED, external=[EXT],
                          agents_per_process=6,
                          board_params={"scale": SCALE, "progress_period": 0.0, "real_time_departures": True,
                                        "startup_timeout": 6.0})
    fake = FakeDriver(graph, EXT, speed=2.0, frame="odom")
    graph.spin_until(lambda: procs.board.proc.poll() is not None, 90, "the task board to finish the mission")
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["lost_robots"] == [EXT], result["lost_reasons"]
    assert result["lost_reasons"][EXT] == (f"no pose accepted: pose of {EXT} in frame 'odom', expected 'map' "
                                           f"(frame_id)")
    graph.spin_until(lambda: all(p.proc.poll() is not None for p in procs.agents), 30, "the agents to exit")
    assert fake.goals == [], fake.goals  # no stop goal in the wrong frame (and no leg: it was dropped at the start)
    log = "".join(p.log.read_text() for p in procs.agents)
    assert f"{EXT}: its poses are in frame 'odom', not the mission's 'map': not used" in log, log[-3000:]


def test_a_robot_slower_than_planned_completes_late(tmp_path, graph, mission_procs):
    time_scale = 4.0  # the plan: velocity x 4 mission units per wall second; the robot drives at half that
    result, fake = run(tmp_path, graph, mission_procs, {"leg_timeout_factor": 3.0, "leg_timeout_floor": 2.0},
                       time_scale=time_scale, speed=INST.velocity * time_scale / 2)
    assert result["lost_robots"] == [] and result["undone_tasks"] == [] and result["success"]
    assert any(clock >= planned - 1e-6 for clock, planned in fake.stops[:-1]), fake.stops  # it was late
    ref = offline()
    assert result["routes"] == ref["routes"]
