"""sim_robot: simulated kinematics for any number of robots, and the mission clock.

Topic names here are those of a mission in the root namespace; with ``-p mission_namespace:=/ns``
(the same on every node of the mission) each is under ``/ns`` (``/ns/hmrta/board``,
``/ns/<robot>/pose``), so that missions share a ROS domain (docs/ros.md).

Each simulated robot consumes goals on ``/<robot>/goal_pose`` (``geometry_msgs/PoseStamped``,
stamp = departure time) and drives there in a straight line at the instance velocity; it
publishes its pose on ``/<robot>/pose`` when it arrives, as a heartbeat, and (paced mode) while
moving. The node publishes the mission clock (``rosgraph_msgs/Clock`` on ``clock_topic``, default
``/hmrta/clock``; never ``/clock``, which a simulator such as Gazebo may own): it advances mission
time up to the horizon the board allows, at once (``time_scale`` 0: as fast as possible) or at
``time_scale`` mission seconds per second of the system clock (1 for real robots). Robots named in ``external`` (real robots, drivers elsewhere) are
not simulated; with every robot external this node is just the mission clock.

Robots added during the mission (a robot that joined, a scenario's ``add_robot``) appear in the
mission the board publishes again (same session); the node simulates the new ones from where the
board's state has them (their first leg's start).

Restart: the node starts from the latched mission and the board, not from zero: it keeps a replica
of the board's state (:class:`hmrta.replica.Replica`: the latched keyframe, the stream's events,
a keyframe request when it misses versions or the keyframe may be old) until it holds the current
version. The clock resumes at the board's horizon (the latest instant the board allowed; in
as-fast-as-possible mode exactly where the previous process stopped) and each robot's position and
in-flight legs are rebuilt from the legs the board lists, so a ``sim_robot`` that died (and was
restarted by ``hmrta-mission``) continues the mission. A goal it already has (same pose, same
departure) or one older than the leg a robot is driving is a repeat from a resynchronising agent
and is ignored.
"""
from __future__ import annotations

import heapq
import itertools
import math
import os
import socket
import sys
import time
from dataclasses import dataclass, field
from typing import Any

from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.task import Future
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from hmrta.replica import Replica
from hmrta_msgs_py import topics
from hmrta_msgs_py.codec import (DecodeError, KeyframeRequest, Mission, board_from_msg, clock_to_msg,
                                 keyframe_request_to_msg, mission_from_msg, pose_from_msg, pose_to_msg)
from hmrta_msgs_py.runtime import (MAX_PERIOD, MIN_PERIOD, BoardSilence, check_period, mission_namespaces,
                                   parameters_read_at_start, spin_nodes, starting)
from hmrta_msgs_py.codec import RESEND  # leg node: the board re-sends a goal

EPS = 1e-6


@dataclass
class Leg:
    start: tuple[float, float]
    goal: tuple[float, float]
    depart: float
    arrive: float
    announced: bool = False


@dataclass
class SimulatedRobot:
    name: str
    base: tuple[float, float]  # where it is before its first remembered leg (its depot at first)
    pub: Any
    legs: list[Leg] = field(default_factory=list)  # in departure order; later goals replace later legs
    index: int = -1  # its agent index in the mission
    placed: bool = True  # a robot added during the mission: False until a board says where it is
    lost: bool = False  # the board dropped it: it stays where it stopped and takes no more goals
    early: list = field(default_factory=list)  # goals received before it was placed

    def position(self, t: float) -> tuple[float, float]:
        pos = self.base
        for g in self.legs:
            if g.depart > t:
                break
            if t >= g.arrive or g.arrive <= g.depart:
                pos = g.goal
            else:
                f = (t - g.depart) / (g.arrive - g.depart)
                pos = (g.start[0] + (g.goal[0] - g.start[0]) * f, g.start[1] + (g.goal[1] - g.start[1]) * f)
        return pos

    def moving(self, t: float) -> bool:
        return any(g.depart <= t < g.arrive for g in self.legs)


@parameters_read_at_start
class SimRobot(Node):
    def __init__(self, **node_kw: Any):
        super().__init__("sim_robot", **node_kw)
        topics.check_root_namespace(self, "sim_robot")
        P = self.declare_parameter
        self.topics = T = topics.mission_topics(P("mission_namespace", "/").value)
        self.only = list(P("robots", Parameter.Type.STRING_ARRAY).value or [])
        self.external = set(P("external", Parameter.Type.STRING_ARRAY).value or [])
        both = [r for r in self.only if r in self.external]
        if both:
            raise ValueError(f"robots and external both name {', '.join(both[:5])}: a robot is either simulated here "
                             f"(robots) or driven elsewhere (external)")
        self.time_scale = P("time_scale", 0.0).value
        rate = P("rate", 20.0).value
        heartbeat = P("heartbeat_period", 1.0).value
        self.exit_on_done = P("exit_on_done", True).value
        clock_topic = P("clock_topic", "").value
        silence = P("board_silence_warning", 10.0).value
        for k, v, ok, want in (("time_scale", self.time_scale, self.time_scale >= 0, "a number >= 0 (0: as fast "
                                                                                    "as possible)"),
                               ("rate", rate, 1 / MAX_PERIOD <= rate <= 1 / MIN_PERIOD,
                                f"a number of ticks per second in [{1 / MAX_PERIOD:.3g}, {1 / MIN_PERIOD:g}]"),
                               ("board_silence_warning", silence, silence >= 0, "a number of seconds >= 0 (0: never)")):
            if not ok or not math.isfinite(v):
                raise ValueError(f"{k}: expected {want}, got {v!r}")
        check_period("heartbeat_period", heartbeat)
        if self.external and self.time_scale <= 0:  # real robots on a clock that jumps: tasks take no time
            self.get_logger().warning(
                f"external robots ({', '.join(sorted(self.external)[:5])}) on a mission clock run as fast as "
                f"possible (time_scale 0): the clock jumps to each next event, so their tasks take no wall time once "
                f"they arrive; set -p time_scale:=1.0 for real robots")
        clock_topic = T.clock_topic(clock_topic)
        self.mission: Mission | None = None
        self.robots: dict[str, SimulatedRobot] = {}
        self.now = 0.0
        self.horizon = 0.0
        self._early: list[tuple[String, bool]] = []  # board messages that came before the mission
        self._last_keyframe = None  # the latest keyframe (robots added later are placed from it)
        self._kf_sessions: set[str] = set()  # sessions a keyframe was received for (the first may be old)
        self.replica: Replica | None = Replica()  # until synced: the board's state, to start from
        self.synced = False  # clock and robots rebuilt from the board's current version (start or restart)
        self._early_goals: list[tuple[SimulatedRobot, PoseStamped]] = []  # goals before that
        # (arrival, n, robot) of every leg added: as fast as possible, a clock step announces only
        # the robots with an arrival due instead of walking the team (stale entries are harmless)
        self._due: list[tuple[float, int, SimulatedRobot]] = []
        self._seq = itertools.count()
        self.done = Future()
        self.silence = BoardSilence(silence, mission=T)
        self._version: int | None = None  # the latest board version heard
        self.pub_clock = self.create_publisher(Clock, clock_topic, topics.CLOCK_QOS)
        self.create_subscription(String, T.mission, self.on_mission, topics.MISSION_SUB_QOS)
        self.create_subscription(String, T.board, self.on_board, topics.BOARD_SIM_QOS)
        self.create_subscription(String, T.keyframe, self.on_keyframe, topics.KEYFRAME_QOS)
        self.pub_request = self.create_publisher(String, T.keyframe_requests, topics.KEYFRAME_REQUEST_QOS)
        self._who = f"{socket.gethostname()}:{os.getpid()} sim_robot"
        self.create_timer(heartbeat, self.on_heartbeat)
        self.create_timer(1.0, self.on_silence)
        if self.time_scale > 0:
            self._wall = time.monotonic()
            self.create_timer(1.0 / rate, self.on_tick)

    # ------------------------------------------------------------------------------------------
    def _heard(self) -> None:
        again = self.silence.heard()
        if again is not None:
            self.get_logger().info(again)

    def on_silence(self) -> None:
        if not self.done.done():
            text = self.silence.check(self._version, lambda: mission_namespaces(self))
            if text is not None:
                self.get_logger().warning(text)

    def on_mission(self, msg: String) -> None:
        self._heard()
        try:
            m = mission_from_msg(msg)
        except DecodeError as e:
            self.get_logger().error(f"ignoring malformed mission: {e}")
            return
        if self.mission is not None:
            if m.session != self.mission.session:
                self.get_logger().warning("a new mission session appeared; this node keeps its first mission")
            elif len(m.robots) > len(self.mission.robots):
                self._grown(m)
            return
        self.mission = m
        inst = m.instance
        names = self.only or [n for n in m.robots if n not in self.external]
        for n in names:
            a = m.index(n)
            if a is None:
                if not self.only:
                    self.get_logger().error(f"robot {n!r} is not in the mission; not simulating it")
                continue
            self._simulate(n, a, placed=True)
        self.get_logger().info(f"simulating {len(self.robots)} robot(s) at velocity {inst.velocity:g}; "
                               + ("as fast as possible" if self.time_scale <= 0 else f"x{self.time_scale:g} real time"))
        early, self._early = self._early, []
        for msg, keyframe in early:  # the latched topics may arrive in either order
            (self.on_keyframe if keyframe else self.on_board)(msg)

    def _simulate(self, n: str, a: int, placed: bool) -> SimulatedRobot:
        inst = self.mission.instance
        home = (float(inst.depots[a, 0]), float(inst.depots[a, 1]))
        pub = self.create_publisher(PoseStamped, self.topics.robot(n, topics.POSE), topics.POSE_PUB_QOS)
        r = self.robots[n] = SimulatedRobot(n, home, pub, index=a, placed=placed)
        self.create_subscription(PoseStamped, self.topics.robot(n, topics.GOAL),
                                 lambda g, r=r: self.on_goal(r, g), topics.GOAL_QOS)
        return r

    def _grown(self, m: Mission) -> None:
        """The mission was published again with robots added (a robot joined, a scenario's
        add_robot): simulate the new ones (those this node simulates), each from where the board
        says it was added (its first leg's start in the board's state). A robot whose pose another
        node already publishes is a real robot joining (its driver's): it is left to it."""
        old = set(self.mission.robots)
        self.mission = m
        new = [n for n in m.robots if n not in old and n not in self.external and (not self.only or n in self.only)]
        driven = [n for n in new if self.count_publishers(self.topics.robot(n, topics.POSE)) > 0]
        if driven:  # a real robot joined: its driver already publishes its pose
            self.get_logger().info(f"not simulating {', '.join(driven)}: joined with a pose published by another "
                                   f"node (a driver)")
            self.external.update(driven)
            new = [n for n in new if n not in driven]
        for n in new:
            self._simulate(n, m.index(n), placed=False)
        if new:
            self.get_logger().info(f"simulating {len(new)} robot(s) added to the mission: {', '.join(new)}")
            if self.synced and self._last_keyframe is not None:
                self._place(self._last_keyframe.state["agents"]["from"])

    def _place(self, frm) -> None:
        """Put robots added during the mission where the board's state has them (``frm``: the
        start of each robot's current leg: where it was added, as long as it has not driven on),
        then give them the goals that came first."""
        for r in self.robots.values():
            if r.placed or r.index >= len(frm):
                continue
            r.base, r.placed = (float(frm[r.index][0]), float(frm[r.index][1])), True
            early, r.early = r.early, []
            for g in early:
                self.on_goal(r, g)
            self._announce(r)
            m = self.mission
            r.pub.publish(pose_to_msg(r.position(self.now), self.now, m.frame_id, m.scale))

    def on_board(self, msg: String) -> None:
        """A version of the board stream: its horizon moves the clock; before the node is in sync
        its events go to the replica."""
        self._heard()
        if self.mission is None:
            self._early.append((msg, False))
            del self._early[:-1000]
            return
        try:
            b = board_from_msg(msg, legs=False, state=False)
        except DecodeError as e:
            self.get_logger().error(f"ignoring malformed board: {e}")
            return
        if b.session != self.mission.session:
            return
        if not self.synced:
            return self._sync(b, None, False)
        self._follow(b)

    def on_keyframe(self, msg: String) -> None:
        self._heard()
        if self.mission is None:
            self._early = [e for e in self._early if not e[1]] + [(msg, True)]
            return
        try:
            b = board_from_msg(msg)
        except DecodeError as e:
            self.get_logger().error(f"ignoring malformed keyframe: {e}")
            return
        if b.session != self.mission.session:
            return
        latched = b.session not in self._kf_sessions  # the first one may be the old one a latched topic kept
        self._kf_sessions.add(b.session)
        self._last_keyframe = b
        if not self.synced:
            return self._sync(b, lambda: (b.legs, b.state), latched)
        if any(not r.placed for r in self.robots.values()):
            self._place(b.state["agents"]["from"])
        self._follow(b)

    def _sync(self, b, keyframe, latched: bool) -> None:
        """Feed the replica until it holds the board's current version, then start from it."""
        r = self.replica
        r.receive(b, keyframe, self.mission.instance, latched)
        self._ask()
        if r.current:
            self.replica = None
            self.resync(r)
            self._follow(r.head)

    def _ask(self) -> None:
        ask = self.replica.request() if self.replica is not None else None
        if ask is None:
            return
        version, why = ask
        self.get_logger().info(f"asking the board for a keyframe ({why})", throttle_duration_sec=5.0)
        self.pub_request.publish(keyframe_request_to_msg(KeyframeRequest(self.replica.session or "", version, why,
                                                                          self._who)))

    def _follow(self, b) -> None:
        self._version = b.version
        self.horizon = max(self.horizon, b.horizon)
        for r in self.robots.values():
            if r.index in b.lost and not r.lost:  # a lost robot stops where it is (docs/semantics.md)
                r.lost, r.base, r.legs = True, r.position(self.now), []
                self.get_logger().info(f"{r.name}: lost on the board at t={self.now:.3f}: stopped at "
                                       f"({r.base[0]:.3f}, {r.base[1]:.3f})")
        if b.phase == "done":
            self.advance(max(self.now, b.clock))
            if self.exit_on_done and not self.done.done():
                self.done.set_result(True)
            return
        if self.time_scale <= 0:
            self.advance(self.horizon)

    def resync(self, rep: Replica) -> None:
        """Start from the board's current version (held by the replica ``rep``): the clock at its
        horizon, every robot on the legs the board lists for it (all of them from its depot when
        the board still has its whole history, else from its latest legs), then the goals that
        came before."""
        m, b, st = self.mission, rep.head, rep.state
        self.synced = True
        self.now = self.horizon = float(b.horizon)
        self._place(st.from_pos)  # robots added during the mission
        resumed = 0
        for r in self.robots.values():
            a = m.index(r.name)
            entry = rep.legs(a) if a is not None else None
            if not entry or not entry[1]:
                continue
            seq, legs = entry
            resumed += 1
            if seq > len(legs):  # older legs are gone: where did the first remaining one start?
                _, x, y, depart = legs[0]
                r.base = (x, y)  # unknown: arriving at once never holds the board's clock
                # the state's current leg, when it is this one, knows its start
                to, dep, frm = st.to_pos[a], float(st.depart[a]), st.from_pos[a]
                if abs(to[0] - x) <= EPS and abs(to[1] - y) <= EPS and abs(dep - depart) <= EPS:
                    r.base = (float(frm[0]), float(frm[1]))
            for node, x, y, depart in legs:
                if node == RESEND:
                    continue  # a goal re-sent to a late robot: the leg it repeats is listed already
                self._add_leg(r, x, y, depart)
        if resumed or self.now > 0:
            self.get_logger().info(f"resuming the mission at t={self.now:.3f} (board version {b.version}, "
                                   f"{b.n_done}/{b.n_tasks} tasks done) with the legs of {resumed} robot(s)")
        early, self._early_goals = self._early_goals, []
        for r, g in early:
            self.on_goal(r, g)
        for r in self.robots.values():
            self._announce(r)
        self.on_heartbeat()

    def on_goal(self, r: SimulatedRobot, msg: PoseStamped) -> None:
        if not self.synced:
            self._early_goals.append((r, msg))
            return
        if not r.placed:
            r.early.append(msg)
            return
        if r.lost:
            return
        try:
            x, y, t = pose_from_msg(msg, self.mission.scale)
        except DecodeError as e:
            self.get_logger().error(f"ignoring malformed goal for {r.name}: {e}")
            return
        if any(abs(g.depart - t) <= EPS and abs(g.goal[0] - x) <= EPS and abs(g.goal[1] - y) <= EPS
               for g in r.legs):
            return  # a goal it already drives (an agent that resynchronised sends its legs again)
        if r.legs and t < r.legs[0].depart - EPS and r.legs[0].depart <= self.now:
            self.get_logger().debug(f"{r.name}: ignoring goal departing t={t:.6f}, before its current leg")
            return
        self._add_leg(r, x, y, t)
        self._announce(r)

    def _add_leg(self, r: SimulatedRobot, x: float, y: float, t: float) -> None:
        start = r.position(t)
        r.legs = [g for g in r.legs if g.depart < t]  # a goal replaces whatever was planned after it
        dist = math.hypot(x - start[0], y - start[1])
        r.legs.append(Leg(start, (x, y), t, t + dist / self.mission.instance.velocity))
        if self.time_scale <= 0:
            heapq.heappush(self._due, (r.legs[-1].arrive, next(self._seq), r))
        self.get_logger().debug(f"{r.name}: goal ({x:.3f}, {y:.3f}) from ({start[0]:.3f}, {start[1]:.3f}) departing "
                                f"t={t:.6f}, arriving t={r.legs[-1].arrive:.6f} (now {self.now:.6f})")

    # ------------------------------------------------------------------------------------------
    def _announce(self, r: SimulatedRobot) -> None:
        """Publish the arrivals of r up to now (in order)."""
        m = self.mission
        for g in r.legs:
            if not g.announced and g.arrive <= self.now + EPS:
                g.announced = True
                r.pub.publish(pose_to_msg(g.goal, max(g.arrive, 0.0), m.frame_id, m.scale))
        done = 0  # forget finished legs (all but the last), keeping where they ended
        while done < len(r.legs) - 1 and r.legs[done].announced and r.legs[done + 1].depart <= self.now:
            done += 1
        if done:
            r.base, r.legs = r.legs[done - 1].goal, r.legs[done:]

    def advance(self, t: float) -> None:
        if t <= self.now:
            return
        self.now = t
        m = self.mission
        if self.time_scale > 0:  # paced: every moving robot reports its pose
            for r in self.robots.values():
                if not r.placed:
                    continue
                self._announce(r)
                if r.moving(t):
                    r.pub.publish(pose_to_msg(r.position(t), t, m.frame_id, m.scale))
        else:  # only the robots with an arrival due by now
            due = self._due
            while due and due[0][0] <= t + EPS:
                self._announce(heapq.heappop(due)[2])
        self.pub_clock.publish(clock_to_msg(t))

    def on_tick(self) -> None:
        wall = time.monotonic()
        dt, self._wall = wall - self._wall, wall
        if self.mission is not None and self.horizon > self.now:
            self.advance(min(self.horizon, self.now + dt * self.time_scale))

    def on_heartbeat(self) -> None:
        if self.mission is None or not self.synced:
            self._ask()  # still waiting for the board's current version: ask again
            return
        m = self.mission
        for r in self.robots.values():
            if r.placed:
                r.pub.publish(pose_to_msg(r.position(self.now), self.now, m.frame_id, m.scale))
        self.pub_clock.publish(clock_to_msg(self.now))


def main(args: list[str] | None = None) -> None:
    argv = sys.argv if args is None else args
    from hmrta_msgs_py.params import node_parameters
    from hmrta_msgs_py.runtime import help_requested, no_own_arguments

    help_requested(argv, "sim_robot", __doc__.split("\n\n")[0], node_parameters("sim_robot"))
    no_own_arguments("sim_robot", argv)
    with starting("sim_robot", args=argv):  # a bad parameter: a user error
        node = SimRobot()
    spin_nodes([node], until=node.done if node.exit_on_done else None)


if __name__ == "__main__":
    sys.exit(main())
