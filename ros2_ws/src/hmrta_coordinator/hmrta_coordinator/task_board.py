"""task_board: the mission's shared state, owned by the SPEC §3 state machine (hmrta.core).

The board never decides for anyone. It publishes the mission (``/hmrta/mission``) and the board
(``/hmrta/board``: header, legs, full state snapshot; reliable + transient local) naming the robot
whose turn it is; that robot's agent answers on ``/hmrta/choice`` with the board version it saw.
The board validates every message (schema, known and live robot, version, turn, mask) and
applies valid choices with ``MissionState.step``; anything else is rejected with a logged reason
(also published on ``/hmrta/rejections``) and never changes the board.

Time: the board follows ``/clock`` (driven by ``sim_robot``). It releases a decision only when
the clock has reached the decision's instant, and gives the clock a *horizon* it may not pass:
the next decision instant, and the start of any task whose members have not yet reported
(``/<robot>/pose``) being at the task. Simulated robots report at once, so a sim-time mission is
deterministic and equals the offline rollout; a real (or slower) robot holds the clock until it
arrives.

Robot loss: a robot whose agent heartbeat (``/hmrta/agent_status``) or pose stops for
``heartbeat_timeout`` seconds (wall time) is dropped (``MissionState.drop_agent``): its
commitments are released, the others re-plan, tasks nobody left can satisfy are cancelled. The
result JSON (``hmrta-solution/1``, ``output`` parameter and ``/hmrta/result``) lists
``lost_robots`` and ``undone_tasks``.

Authentication (``keystore`` parameter: a mission keystore folder, ``hmrta keys create``; empty:
off): every choice and heartbeat must carry a valid MAC of the robot it speaks for with a fresh
counter (``hmrta.keys``, docs/security.md). Choices that fail are rejected (``unsigned``,
``forged``, ``replayed``, ``unknown_robot``) before any other check on their robot; heartbeats
that fail keep nobody alive.

Rejections are counted one by one; the log line and the ``/hmrta/rejections`` message of each
are rate-limited (``rejection_rate`` per second), so a flood of junk costs the board little more
than decoding it.
"""
from __future__ import annotations

import dataclasses
import math
import statistics
import sys
import time
import uuid
from collections import Counter
from functools import partial
from typing import Any

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.task import Future
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from hmrta.core import DONE, LOST, STATUS_NAMES, MissionState, Rules
from hmrta.formats import load_instance
from hmrta.instance import InstanceError
from hmrta.keys import Verifier, load_keystore, rejection_code
from hmrta.methods import MethodError
from hmrta.methods import rules as method_rules
from hmrta.solution import solution_from_state
from hmrta_msgs_py import topics
from hmrta_msgs_py.codec import (HOLD, Board, DecodeError, MarkerView, Mission, Rejection, board_to_msg,
                                 choice_from_msg, clock_from_msg, markers_to_msg, mission_to_msg, pose_from_msg,
                                 rejection_to_msg, result_to_msg, state_to_json, status_from_msg)
from hmrta_msgs_py.runtime import declare_method_parameters, spin_nodes

EPS = 1e-6  # sim-time comparisons (stamps are rounded to the nanosecond)


LEG_WINDOW = 4  # legs per robot repeated on every board (a reader that skipped versions catches up)


class BoardState(MissionState):
    """The mission state machine, logging every leg a commitment starts.

    One ``step`` may run several events ahead of the mission clock (a robot commits to a task,
    the task completes, the robot is sent home), so the current leg alone would lose moves; the
    log keeps them all, in order, for the robots' goals."""

    def __init__(self, inst, seed: int = 0, rules: Rules = Rules()):
        self.leg_log: list[list[tuple[int, float, float, float]]] = [[] for _ in range(inst.n_agents)]
        super().__init__(inst, seed=seed, rules=rules)

    def commit(self, a: int, node: int) -> None:
        before = (float(self.depart[a]), float(self.arrive[a]))
        super().commit(a, node)
        if (float(self.depart[a]), float(self.arrive[a])) != before or node > 0:
            self.log_leg(a, node)

    def log_leg(self, a: int, node: int) -> None:
        self.leg_log[a].append((node, float(self.to_pos[a, 0]), float(self.to_pos[a, 1]), float(self.depart[a])))


def percentile(xs: list[float], q: float) -> float:
    if not xs:
        return math.nan
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, math.ceil(q / 100 * len(s)) - 1))]


class TaskBoard(Node):
    def __init__(self, **node_kw: Any):
        super().__init__("task_board", **node_kw)
        P = self.declare_parameter
        path = P("instance", "").value
        self.seed = P("seed", 0).value
        self.method, method_opts = declare_method_parameters(self)
        self.output = P("output", "").value
        names = list(P("robot_names", Parameter.Type.STRING_ARRAY).value or [])
        frame_id = P("frame_id", "map").value
        scale = P("scale", 1.0).value
        self.wait_for_robots = P("wait_for_robots", True).value
        self.startup_timeout = P("startup_timeout", 120.0).value
        self.heartbeat_timeout = P("heartbeat_timeout", 5.0).value
        self.decision_timeout = P("decision_timeout", 30.0).value
        self.tolerance = P("arrival_tolerance", 1e-3).value
        self.exit_on_done = P("exit_on_done", True).value
        marker_period = P("marker_period", 0.5).value
        self.progress_period = P("progress_period", 5.0).value
        # real robots cannot leave in the past: no back-dated departures for postponed robots
        real_time = P("real_time_departures", False).value
        keystore = P("keystore", "").value  # mission keystore folder (or its keys.json); empty: no authentication
        self.rejection_rate = float(P("rejection_rate", 200.0).value)  # logged + published rejections per second
        # the board's receive queues of choices and heartbeats (messages): deep enough to ride out the
        # moments the board process is not scheduled while junk floods the topics, bounded in memory
        queue_depth = int(P("queue_depth", 2000).value)

        if not path:
            raise ValueError("task_board: set the mission file: -p instance:=PATH")
        self.inst = inst = load_instance(path)
        rules = method_rules(self.method, **method_opts)  # from the checkpoint's config: no torch here
        if real_time:
            rules = dataclasses.replace(rules, backdate=False)
        A = inst.n_agents
        names = names or [f"robot_{a}" for a in range(A)]
        if len(names) != A or len(set(names)) != A:
            raise ValueError(f"robot_names: expected {A} distinct names, got {len(names)}")
        self.names = names
        self.index = {n: a for a, n in enumerate(names)}
        # KeystoreError (a ValueError, one line naming the file and field) is a user error
        self.verifier = Verifier(load_keystore(keystore, names)) if keystore else None
        self.state = BoardState(inst, seed=self.seed, rules=rules)
        self.mission = Mission(uuid.uuid4().hex[:12], inst, tuple(names), self.seed, self.method, frame_id, scale,
                               rules=rules)

        # bookkeeping (wall times from time.monotonic)
        self.version = 0  # published board version
        self.rev = 0  # state revision
        self.phase = "starting"
        self.clock = 0.0  # latest /clock
        self.t_created = time.monotonic()
        self.t_start: float | None = None
        self.seen_status: list[float | None] = [None] * A
        self.seen_pose: list[float | None] = [None] * A
        self.last_pose: list[tuple[float, float] | None] = [None] * A
        self.ptr = [0] * A  # route prefix whose arrivals are confirmed
        self.lost: dict[int, str] = {}
        self.accepted: set[tuple[int, int]] = set()
        self.released_at = 0.0  # perf_counter when the current decision was released
        self.latency_ms: list[float] = []
        self.agent_ms: list[float] = []
        self.rejected: Counter[str] = Counter()
        self.auth_rejected: dict[str, Counter[str]] = {"choice": Counter(), "status": Counter()}
        self._rej_tokens = self.rejection_rate  # token bucket of logged/published rejections
        self._rej_time = time.monotonic()
        self._rej_quiet = 0  # rejections counted but neither logged nor published since the last summary
        self._rej_summary_at = 0.0
        self.finished = False
        self.done = Future()
        self._key = None
        self._cache_rev = -1
        self._legs: tuple | None = None
        self._state_json = ""
        self._marker_key = None
        self._last_progress = 0.0
        self._published_at = self._clock_at = time.monotonic()

        self.pub_mission = self.create_publisher(String, topics.MISSION, topics.MISSION_QOS)
        self.pub_board = self.create_publisher(String, topics.BOARD, topics.BOARD_QOS)
        self.pub_result = self.create_publisher(String, topics.RESULT, topics.RESULT_QOS)
        self.pub_rej = self.create_publisher(String, topics.REJECTIONS, topics.REJECTION_QOS)
        self.pub_markers = self.create_publisher(MarkerArray, topics.MARKERS, topics.MARKER_QOS)
        self.create_subscription(String, topics.CHOICE, self.on_choice, _deeper(topics.CHOICE_QOS, queue_depth))
        self.create_subscription(String, topics.STATUS, self.on_status, _deeper(topics.STATUS_QOS, queue_depth))
        self.create_subscription(Clock, topics.CLOCK, self.on_clock, topics.CLOCK_QOS)
        for a, n in enumerate(names):
            self.create_subscription(PoseStamped, topics.robot_topic(n, topics.POSE), partial(self.on_pose, a),
                                     topics.POSE_SUB_QOS)
        self.create_timer(0.1, self.on_watchdog)
        if marker_period > 0:
            self.create_timer(marker_period, self.on_markers)

        self.pub_mission.publish(mission_to_msg(self.mission))
        self.get_logger().info(
            f"mission {inst.name}: {A} robots, {inst.n_tasks} tasks, method {self.method}, seed {self.seed}; "
            + ("waiting for every robot's agent and pose" if self.wait_for_robots else "starting"))
        if not self.wait_for_robots:
            self._start()
        else:
            self._publish("starting", None, 0.0)

    # ------------------------------------------------------------------------------------------
    # publishing
    # ------------------------------------------------------------------------------------------
    def _legs_now(self) -> tuple:
        st = self.state
        return tuple(None if st.mode[a] == LOST else (len(log), tuple(log[-LEG_WINDOW:]))
                     for a, log in enumerate(st.leg_log))

    def _publish(self, phase: str, decider_: int | None, horizon: float) -> None:
        key = (self.rev, phase, decider_, horizon)
        if key == self._key:
            return
        self._key = key
        self.phase = phase
        if self._cache_rev != self.rev:
            self._cache_rev = self.rev
            self._legs = self._legs_now()
            self._state_json = state_to_json(self.state.snapshot())
        self.version += 1
        st = self.state
        b = Board(self.mission.session, self.version, self.rev, phase, decider_, float(st.clock), float(horizon),
                  int(st.n_done), int(st.n_cancelled), st.M, tuple(sorted(self.lost)), self._legs)
        msg = board_to_msg(b, self._state_json)
        if phase == "decide":
            self.released_at = time.perf_counter()  # latency: board update -> choice received
        self.pub_board.publish(msg)
        self._published_at = time.monotonic()

    def _reject(self, reason: str, detail: str, robot: str = "", version: int = -1) -> None:
        self.rejected[reason] += 1
        if self._rate_ok():
            self.get_logger().warning(f"rejected: {detail}")
            self.pub_rej.publish(rejection_to_msg(Rejection(reason, detail, robot, version)))

    def _rate_ok(self) -> bool:
        """Token bucket (``rejection_rate`` per second, as many in a burst): whether this
        rejection is logged and published; the others are only counted, and summarised in one
        log line every few seconds."""
        if self.rejection_rate <= 0:
            return True
        now = time.monotonic()
        self._rej_tokens = min(self.rejection_rate, self._rej_tokens + (now - self._rej_time) * self.rejection_rate)
        self._rej_time = now
        if self._rej_tokens >= 1.0:
            self._rej_tokens -= 1.0
            return True
        self._rej_quiet += 1
        return False

    # ------------------------------------------------------------------------------------------
    # the mission clock and arrival confirmations
    # ------------------------------------------------------------------------------------------
    def _near(self, a: int, xy) -> bool:
        p = self.last_pose[a]
        return p is not None and math.hypot(p[0] - xy[0], p[1] - xy[1]) <= self.tolerance

    def _gate(self) -> float:
        """Earliest start of a task with a member not yet confirmed there (inf: none)."""
        st, locs = self.state, self.inst.task_locations
        gate = math.inf
        for a in range(st.A):
            if st.mode[a] == LOST:
                continue
            route = st.routes[a]
            p = min(self.ptr[a], len(route))
            while p < len(route):
                m = route[p]
                if self._near(a, locs[m]):
                    p += 1
                    continue
                s = st.start[m]
                if s == s:  # not NaN: the task has its coalition and a start time
                    gate = min(gate, float(s))
                break
            self.ptr[a] = p
        return gate

    def _waiting_for(self) -> str:
        """What the clock is waiting for (diagnostics)."""
        st, locs = self.state, self.inst.task_locations
        if st.done:
            away = [self.names[a] for a in range(st.A) if a not in self.lost and not self._near(a, self.inst.depots[a])]
            return f"clock {self.clock:.3f}, robots not yet home: {away[:10]}"
        late = []
        for a in range(st.A):
            route = st.routes[a]
            if a not in self.lost and self.ptr[a] < len(route):
                m = route[self.ptr[a]]
                if st.start[m] == st.start[m]:
                    late.append(f"{self.names[a]} at task {m} (starts {st.start[m]:.3f}, last pose {self.last_pose[a]}, "
                                f"task at {tuple(locs[m])})")
        return f"clock {self.clock:.3f}, next decision at {st.clock:.3f}; arrivals not confirmed: {late[:10]}"

    def _refresh(self) -> None:
        """Recompute phase and horizon from the state, the clock and the confirmations."""
        if self.finished or self.t_start is None:
            return
        st = self.state
        if st.done:
            alive = [a for a in range(st.A) if a not in self.lost]
            if st.failure and not st.n_cancelled:  # deadlock / time limit: nobody is going home
                return self._finish()
            final = max([float(st.arrive[a]) for a in alive] + [float(st.clock)])
            if self.clock >= final - EPS and all(self._near(a, self.inst.depots[a]) for a in alive):
                return self._finish()
            return self._publish("closing", None, final)
        gate = self._gate()
        t = float(st.clock)
        if self.clock >= t - EPS and gate > t + EPS:
            self._publish("decide", st.agent, t)
        else:
            self._publish("wait", None, min(t, gate))

    def _start(self) -> None:
        self.t_start = time.monotonic()
        self.get_logger().info("all robots present: mission starts" if not self.lost else
                               f"mission starts without {len(self.lost)} robot(s)")
        self._refresh()

    # ------------------------------------------------------------------------------------------
    # callbacks
    # ------------------------------------------------------------------------------------------
    def on_choice(self, msg: String) -> None:
        t_recv = time.perf_counter()
        try:
            c = choice_from_msg(msg)
        except DecodeError as e:
            return self._reject("malformed", f"malformed choice: {e}")
        a = self.index.get(c.robot)
        who = f"choice of {c.robot!r} for board {c.version}"
        if c.session != self.mission.session:
            return self._reject("foreign_session", f"{who}: for mission run {c.session!r}, not this one", c.robot,
                                c.version)
        if self.verifier is not None:
            why = self.verifier.verify(c.payload)
            if why is not None:
                code = rejection_code(why)
                self.auth_rejected["choice"][code] += 1
                return self._reject(code, f"{who}: {why}", c.robot, c.version)
        if a is None:
            return self._reject("unknown_robot", f"{who}: unknown robot", c.robot, c.version)
        if a in self.lost:
            return self._reject("lost", f"{who}: robot was declared lost ({self.lost[a]})", c.robot, c.version)
        if (a, c.version) in self.accepted:
            return self._reject("duplicate", f"{who}: duplicate (already applied)", c.robot, c.version)
        if c.version != self.version:
            return self._reject("stale", f"{who}: board is at version {self.version}", c.robot, c.version)
        if self.finished or self.phase != "decide":
            return self._reject("not_released", f"{who}: no decision is open ({self.phase})", c.robot, c.version)
        st = self.state
        if a != st.agent:
            return self._reject("not_your_turn", f"{who}: it is {self.names[st.agent]}'s turn", c.robot, c.version)
        mask = st.mask()
        if not 0 <= c.node < len(mask) or not mask[c.node]:
            what = "its depot" if c.node == 0 else f"task {c.node - 1}"
            return self._reject("masked", f"{who}: node {c.node} ({what}) is not admissible now", c.robot,
                                c.version)
        self.accepted.add((a, c.version))
        self.latency_ms.append((t_recv - self.released_at) * 1e3)
        self.agent_ms.append(c.compute_ms)
        st.step(c.node)
        self.rev += 1
        self._refresh()

    def on_status(self, msg: String) -> None:
        try:
            s = status_from_msg(msg)
        except DecodeError as e:
            return self._reject("malformed", f"malformed status: {e}")
        if s.session != self.mission.session:
            return  # agents of another mission run (e.g. before a board restart)
        if self.verifier is not None:
            why = self.verifier.verify(s.payload)
            if why is not None:  # keeps nobody alive
                self.auth_rejected["status"][rejection_code(why)] += 1
                self.get_logger().warning(f"ignoring heartbeat of {', '.join(s.robots[:4])[:200]}: {why}",
                                          throttle_duration_sec=5.0)
                return
        now = time.monotonic()
        for r in s.robots:
            a = self.index.get(r)
            if a is None:
                self.get_logger().warning(f"heartbeat names unknown robot {r!r}", throttle_duration_sec=10.0)
            else:
                self.seen_status[a] = now
        if self.t_start is None:
            self._maybe_start()

    def on_pose(self, a: int, msg: PoseStamped) -> None:
        try:
            x, y, _ = pose_from_msg(msg, self.mission.scale)
        except DecodeError as e:
            return self._reject("malformed", f"malformed pose of {self.names[a]}: {e}", self.names[a])
        self.seen_pose[a] = time.monotonic()
        self.last_pose[a] = (x, y)
        if self.t_start is None:
            self._maybe_start()
        else:
            self._refresh()

    def on_clock(self, msg: Clock) -> None:
        t = clock_from_msg(msg)
        if t > self.clock:
            self.clock = t
            self._clock_at = time.monotonic()
            self._refresh()

    def _maybe_start(self) -> None:
        if all(s is not None for s in self.seen_status) and all(s is not None for s in self.seen_pose):
            self._start()

    def on_watchdog(self) -> None:
        if self.finished:
            return
        now = time.monotonic()
        if self.t_start is None:
            if now - self.t_created > 5.0:
                agents = [n for a, n in enumerate(self.names) if self.seen_status[a] is None]
                poses = [n for a, n in enumerate(self.names) if self.seen_pose[a] is None]
                self.get_logger().info(f"waiting for the agents of {agents[:8]}{'...' if len(agents) > 8 else ''} and "
                                       f"the poses of {poses[:8]}{'...' if len(poses) > 8 else ''}",
                                       throttle_duration_sec=5.0)
            if self.startup_timeout > 0 and now - self.t_created > self.startup_timeout:
                for a in range(self.state.A):
                    if self.seen_status[a] is None or self.seen_pose[a] is None:
                        self._lose(a, "never reported", refresh=False)
                self._start()
            return
        T = self.heartbeat_timeout
        if T > 0:
            for a in range(self.state.A):
                if a in self.lost:
                    continue
                for seen, what in ((self.seen_status[a], "agent heartbeat"), (self.seen_pose[a], "robot pose")):
                    if now - max(seen or 0.0, self.t_start) > T:
                        self._lose(a, f"no {what} for {T:g} s")
                        break
        if (self.decision_timeout > 0 and self.phase == "decide"
                and time.perf_counter() - self.released_at > self.decision_timeout):
            self._lose(self.state.agent, f"no decision within {self.decision_timeout:g} s")
        if self._rej_quiet and now - self._rej_summary_at >= 5.0:
            self._rej_summary_at = now
            self.get_logger().warning(f"{self._rej_quiet} more message(s) rejected (not logged one by one: more than "
                                      f"{self.rejection_rate:g}/s); by reason so far: {dict(self.rejected)}")
            self._rej_quiet = 0
        if self.phase in ("wait", "closing") and now - max(self._published_at, self._clock_at) > 5.0:
            self.get_logger().warning(f"mission clock held: {self._waiting_for()}", throttle_duration_sec=10.0)
        if self.progress_period > 0 and now - self._last_progress >= self.progress_period:
            self._last_progress = now
            st = self.state
            self.get_logger().info(f"t={self.clock:.2f}: {st.n_done}/{st.M} tasks done, phase {self.phase}, "
                                   f"{len(self.lost)} lost, {sum(self.rejected.values())} rejected")

    def _lose(self, a: int, reason: str, refresh: bool = True) -> None:
        if a in self.lost or self.finished:
            return
        self.lost[a] = reason
        st = self.state
        before = [(len(log), float(st.depart[b]), float(st.arrive[b])) for b, log in enumerate(st.leg_log)]
        cancelled = st.drop_agent(a)
        for b, (n, d, r) in enumerate(before):  # robots stopped where they were (no commitment): a hold leg
            if b != a and len(st.leg_log[b]) == n and (float(st.depart[b]), float(st.arrive[b])) != (d, r):
                st.log_leg(b, HOLD)
        self.rev += 1
        extra = f"; cancelled task(s) {cancelled} (no longer satisfiable)" if cancelled else ""
        self.get_logger().warning(f"robot {self.names[a]} lost ({reason}): its commitments are released{extra}")
        if refresh:
            self._refresh()

    def on_markers(self) -> None:
        if self.pub_markers.get_subscription_count() == 0:
            return
        key = (self.rev, tuple(self.last_pose))
        if key == self._marker_key:
            return
        self._marker_key = key
        st, inst = self.state, self.inst
        pos = st.positions()
        tasks = tuple((float(x), float(y), STATUS_NAMES[s]) for (x, y), s in zip(inst.task_locations, st.status))
        robots = tuple((n, *(self.last_pose[a] or (float(pos[a, 0]), float(pos[a, 1]))), a in self.lost)
                       for a, n in enumerate(self.names))
        legs = tuple((float(st.from_pos[a, 0]), float(st.from_pos[a, 1]), float(st.to_pos[a, 0]),
                      float(st.to_pos[a, 1])) for a in range(st.A) if st.arrive[a] > self.clock)
        m = self.mission
        self.pub_markers.publish(markers_to_msg(MarkerView(tasks, robots, legs), self.clock, m.frame_id, m.scale))

    # ------------------------------------------------------------------------------------------
    def result(self) -> dict[str, Any]:
        st = self.state
        wall = time.monotonic() - (self.t_start or self.t_created)
        sol = solution_from_state(st, self.method, self.seed, wall)
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
        })
        if self.lost and alive:
            sol.extra["home_time"] = max(float(st.arrive[a]) for a in alive)
        return sol

    def _finish(self) -> None:
        self.finished = True
        sol = self.result()
        if self.output:
            sol.save(self.output)
        self.pub_result.publish(result_to_msg(sol.to_dict()))
        self._key = None
        self._publish("done", None, float(self.clock))
        self.get_logger().info(sol.summary() + (f"; lost {sol.extra['lost_robots']}, undone tasks "
                                                f"{sol.extra['undone_tasks']}" if self.lost else "")
                               + (f"; wrote {self.output}" if self.output else ""))
        if self.exit_on_done:  # linger briefly so that the final board and result reach everyone
            self._exit_timer = self.create_timer(1.0, self._exit)

    def _exit(self) -> None:
        self._exit_timer.cancel()
        if not self.done.done():
            self.done.set_result(True)


def _deeper(qos: QoSProfile, depth: int) -> QoSProfile:
    """``qos`` with a receive history of ``depth`` messages (at least its own)."""
    return QoSProfile(history=qos.history, depth=max(qos.depth, depth), reliability=qos.reliability,
                      durability=qos.durability)


def _r(v: float | None) -> float | None:
    return None if v is None or v != v else round(float(v), 3)



def main(args: list[str] | None = None) -> None:
    argv = sys.argv if args is None else args
    rclpy.init(args=argv)
    try:
        board = TaskBoard()
    except (InstanceError, MethodError, ValueError) as e:  # bad mission file / policy: a user error
        print(f"task_board: {e}", file=sys.stderr)
        rclpy.try_shutdown()
        raise SystemExit(2) from None
    spin_nodes([board], until=board.done if board.exit_on_done else None)


if __name__ == "__main__":
    main()
