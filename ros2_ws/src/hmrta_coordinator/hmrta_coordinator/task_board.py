"""task_board: the mission's shared state, owned by the SPEC §3 state machine (hmrta.core).

Topic names here are those of a mission in the root namespace; with ``-p mission_namespace:=/ns``
(the same on every node of the mission) each is under ``/ns`` (``/ns/hmrta/board``,
``/ns/<robot>/pose``), so that missions share a ROS domain (docs/ros.md).

The board never decides for anyone. It publishes the mission (``/hmrta/mission``) and the board:
every version on the board stream (``/hmrta/board``: a header naming the robot whose turn it is,
with the events applied since the previous version and the state's digest), and now and then a
keyframe (``/hmrta/board_keyframe``: the header, every robot's latest legs and the full state
snapshot; latched). Agents keep a replica of the state by applying the events
(:mod:`hmrta.replica`); one that misses a version asks for a keyframe on
``/hmrta/keyframe_requests``. The robot whose turn it is answers on ``/hmrta/choice`` with the
board version it saw.
The board validates every message (schema, known and live robot, version, turn, mask) and
applies valid choices with ``MissionState.step``; anything else is rejected with a logged reason
(also published on ``/hmrta/rejections``) and never changes the board.

Method: the mission's method (``method``) fixes the state machine's rules. With ``portfolio`` (the
default) the board simulates the candidates on its mission at the start and runs the one of the
shortest makespan (:func:`hmrta.methods.choose_live`), named in the mission (e.g.
``rl@coalition-team``) for the agents; restarted on its journal, it keeps the journal's method.

Time: the board follows the mission clock (``clock_topic``, default ``/hmrta/clock``, driven by
``sim_robot``: as fast as possible, or paced by the system clock for real robots; another node's
``/clock`` moves nothing). It releases a decision only when
the clock has reached the decision's instant, and gives the clock a *horizon* it may not pass:
the next decision instant, and the start of any task whose members have not yet reported
(``/<robot>/pose``) being at the task. Simulated robots report at once, so a sim-time mission is
deterministic and equals the offline rollout; a real (or slower) robot holds the clock until it
arrives.

Poses: each robot's pose topic carries ``geometry_msgs/PoseStamped`` (default),
``geometry_msgs/PoseWithCovarianceStamped`` (``amcl_pose``: subscribed reliable and transient
local, as Nav2's amcl publishes it) or ``nav_msgs/Odometry``: ``pose_type`` for every robot,
``pose_types`` (``ROBOT:TYPE``) per robot. A pose whose ``header.frame_id`` is not ``frame_id`` is
rejected (reason ``wrong_frame``, logged and published rate-limited). Poses confirm arrivals
only; a pose topic that stays silent (a robot standing still) drops nobody.

Robot loss: a robot whose agent heartbeat (``/hmrta/agent_status``) stops for
``heartbeat_timeout`` seconds (wall time) is dropped (``MissionState.drop_agent``): its
commitments are released, the others re-plan, tasks nobody left can satisfy are cancelled. The
result JSON (``hmrta-solution/1``, ``output`` parameter and ``/hmrta/result``) lists
``lost_robots`` and ``undone_tasks``.

Robots joining: an agent whose robot is not in the mission announces it (name, species, its pose
when its driver reports one) in its heartbeat; the board adds it at the mission clock
(:meth:`hmrta.board.MissionBoard.join`), journals it, republishes the mission (same session, the
grown robot list and instance) and follows the new robot's pose; it takes part in the next
decisions. Robots a scenario's ``add_robot`` events add are published the same way.

Authentication (``keystore`` parameter: a mission keystore folder, ``hmrta keys create``; empty:
off): every choice and heartbeat must carry a valid MAC of the robot it speaks for with a fresh
counter (``hmrta.keys``, docs/security.md). Choices that fail are rejected (``unsigned``,
``forged``, ``replayed``, ``unknown_robot``) before any other check on their robot; heartbeats
that fail keep nobody alive.

Journal (``journal`` parameter: a path; empty: off): every board version is appended to a
JSON-lines journal before it is published (the events it applies fsynced first); a board started
on an existing journal replays it, keeps the mission session and version numbers, and goes on
with a keyframe: agents and robots resynchronise from it and re-send what was lost in flight.

The protocol itself (validation, clock and arrival gate, robot loss, journal, result) lives in
:mod:`hmrta.board` (``MissionBoard``, no ROS); this node maps parameters, topics and timers onto it.

Rejections are counted one by one; the log line and the ``/hmrta/rejections`` message of each
are rate-limited (``rejection_rate`` per second), so a flood of junk costs the board little more
than decoding it.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from functools import partial
from typing import Any

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.task import Future
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from hmrta.board import BoardState, JournalError, MissionBoard, TokenBucket, View, journal_header  # noqa: F401  (BoardState: re-exported)
from hmrta.core import STATUS_NAMES
from hmrta.deps import MissingDependency, require
from hmrta.formats import load_instance
from hmrta.instance import InstanceError
from hmrta.keys import Verifier, load_keystore
from hmrta.methods import MethodError, adopt, checkpoint_of, choose_live, chooses, live_label
from hmrta.methods import rules as method_rules
from hmrta.reading import short
from hmrta_msgs_py import topics
from hmrta_msgs_py.codec import (POSE_TYPES, Board, DecodeError, MarkerView, Mission, Rejection, TaskEvent,
                                 board_to_msg, mission_from_msg, pose_type,
                                 choice_from_msg, clock_from_msg, keyframe_request_from_msg, markers_to_msg,
                                 mission_to_msg, pose_from_msg, rejection_to_msg, request_id_of, result_to_msg,
                                 status_from_msg, task_event_to_msg, task_request_from_msg)
from hmrta_msgs_py.console import signals_deferred
from hmrta_msgs_py.runtime import (check_period, closest, declare_method_parameters, parameters_read_at_start,
                                   spin_nodes, starting, writable_file)


@parameters_read_at_start
class TaskBoard(Node):
    """ROS wrapper of :class:`hmrta.board.MissionBoard`: parameters, topics and timers."""

    def __init__(self, **node_kw: Any):
        super().__init__("task_board", **node_kw)
        topics.check_root_namespace(self, "the task board")
        P = self.declare_parameter
        self.topics = T = topics.mission_topics(P("mission_namespace", "/").value)
        path = P("instance", "").value
        self.seed = P("seed", 0).value
        self.method, method_opts = declare_method_parameters(self)
        self.output = P("output", "").value
        names = list(P("robot_names", Parameter.Type.STRING_ARRAY).value or [])
        frame_id = P("frame_id", "map").value
        try:
            self.pose_type = pose_type(P("pose_type", "PoseStamped").value)
        except ValueError as e:  # a user error
            raise ValueError(f"pose_type: {e}") from None
        self.pose_types = _pose_types(list(P("pose_types", Parameter.Type.STRING_ARRAY).value or []))
        clock_topic = P("clock_topic", "").value
        scale = P("scale", 1.0).value
        wait_for_robots = P("wait_for_robots", True).value
        startup_timeout = P("startup_timeout", 120.0).value
        heartbeat_timeout = P("heartbeat_timeout", 5.0).value
        decision_timeout = P("decision_timeout", 30.0).value
        tolerance = P("arrival_tolerance", 0.25).value  # metres (Nav2's usual goal tolerance)
        leg_timeout_factor = P("leg_timeout_factor", 3.0).value
        leg_timeout_floor = P("leg_timeout_floor", 10.0).value
        self.exit_on_done = P("exit_on_done", True).value
        marker_period = P("marker_period", 0.5).value
        self.progress_period = P("progress_period", 5.0).value
        # real robots cannot leave in the past: no back-dated departures for postponed robots
        real_time = P("real_time_departures", False).value
        keystore = P("keystore", "").value  # mission keystore folder (or its keys.json); empty: no authentication
        journal = P("journal", "").value  # JSON-lines journal (replayed when it exists); empty: none
        self.rejection_rate = float(P("rejection_rate", 200.0).value)  # logged + published rejections per second
        # the board's receive queues of choices and heartbeats (messages): deep enough to ride out the
        # moments the board process is not scheduled while junk floods the topics, bounded in memory
        queue_depth = int(P("queue_depth", 2000).value)
        keyframe_period = int(P("keyframe_period", 0).value)  # versions between keyframes (0: by size)

        if not path:
            raise ValueError("set the mission file: -p instance:=PATH")
        if not (scale > 0 and math.isfinite(scale)):
            raise ValueError(f"scale: expected a positive number of metres per mission unit, got {scale!r}")
        # where the result and the journal go, checked before the mission (a write that fails at its end
        # loses the result; a journal that is a FIFO would block the start)
        for name, value in (("output", self.output), ("journal", journal)):
            if value:
                writable_file(name, value)
        for k, v in (("arrival_tolerance", tolerance), ("leg_timeout_factor", leg_timeout_factor),
                     ("leg_timeout_floor", leg_timeout_floor), ("startup_timeout", startup_timeout),
                     ("heartbeat_timeout", heartbeat_timeout), ("decision_timeout", decision_timeout),
                     ("rejection_rate", self.rejection_rate), ("marker_period", marker_period),
                     ("progress_period", self.progress_period)):
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"{k}: expected a finite number >= 0, got {v!r}")
        check_period("marker_period", marker_period, off=True)
        if queue_depth < 1:
            raise ValueError(f"queue_depth: expected a number of messages >= 1, got {queue_depth}")
        if tolerance == 0:  # a pose is never exactly on its goal (localisation noise, the controller's own tolerance)
            self.get_logger().warning("arrival_tolerance 0: a robot counts as arrived only on its goal exactly, which a "
                                      "real robot never is; take a little more than your controller's goal tolerance")
        if real_time and tolerance > 0.1 * scale:  # real robots; the mission area is scale x scale metres
            self.get_logger().warning(
                f"arrival_tolerance {tolerance:g} m is {100 * tolerance / scale:.0f}% of the mission area's side "
                f"(scale {scale:g} m per mission unit): a robot that far from a task counts as there; set scale to "
                f"your map's size in metres (or a smaller arrival_tolerance)")
        if not frame_id:
            raise ValueError("frame_id: expected the frame of the mission's coordinates (e.g. map), got ''")
        try:
            self.inst = inst = load_instance(path)
        except InstanceError as e:  # (the file and the field named by the reader)
            raise InstanceError(f"instance: {e}") from None
        A = inst.n_agents
        names = names or [f"robot_{a}" for a in range(A)]
        if len(names) != A:
            raise ValueError(f"robot_names: expected {A} names (one per robot of the mission), got {len(names)}")
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"robot_names: expected {A} distinct names, got {', '.join(map(repr, twice))} more than once")
        strangers = sorted(set(self.pose_types) - set(names))
        if strangers:  # an entry for a robot that may join later is allowed; a typo is far likelier
            close = {r: closest(r, names) for r in strangers}
            self.get_logger().warning(
                "pose_types: " + "; ".join(f"{r!r} is not a robot of the mission"
                                           + (f" (did you mean {close[r]!r}?)" if close[r] else "")
                                           for r in strangers)
                + f"; its robots are {_names(names)}. The entry applies only if a robot of that name joins")
        clock_topic = T.clock_topic(clock_topic)
        # KeystoreError (a ValueError, one line naming the file and field) is a user error
        if keystore:  # a key for every robot of the mission; those of robots a scenario adds are taken too
            load_keystore(keystore, names)
            verifier = Verifier(load_keystore(keystore))
        else:
            verifier = None
        self.choice: dict[str, Any] | None = None  # what a portfolio chose, and its candidates' makespans
        if chooses(self.method):  # portfolio: the live method the mission runs, chosen here (once every
            # parameter is checked)
            self.method, method_opts = self._choose(inst, method_opts, journal)
        # the mission names its method with its checkpoint (rl@coalition-team): an agent with another
        # method or network refuses it, an agent started with portfolio runs it
        spec = live_label(self.method, method_opts)
        self._checkpoint = checkpoint_of(self.method, method_opts)
        rules = method_rules(self.method, **method_opts)  # from the checkpoint's config: no torch here
        if real_time:
            rules = dataclasses.replace(rules, backdate=False)
        self.board = MissionBoard(inst, names, seed=self.seed, rules=rules, method=spec, verifier=verifier,
                                  tolerance=tolerance / scale, scale=scale, leg_timeout_factor=leg_timeout_factor,
                                  leg_timeout_floor=leg_timeout_floor, heartbeat_timeout=heartbeat_timeout,
                                  decision_timeout=decision_timeout, startup_timeout=startup_timeout,
                                  wait_for_robots=wait_for_robots, journal=journal or None,
                                  keyframe_period=keyframe_period, log=self._log)
        self.names = self.board.names  # the board's list: robots that join are appended to it
        self.mission = Mission(self.board.session, inst, tuple(names), self.seed, spec, frame_id, scale,
                               rules=rules, created=self.board.created)

        self.t_created = time.monotonic()
        self.failure: str | None = None  # why the finished mission failed
        self._rejections = TokenBucket(self.rejection_rate, self.rejection_rate, time.monotonic())  # logged/published
        self._rej_quiet = 0  # rejections counted but neither logged nor published since the last summary
        self._said: dict[Any, float] = {}  # (reason, robot) or warning text -> when it was last logged
        self._rej_summary_at = 0.0
        self.done = Future()
        self._marker_key = None
        self._last_progress = 0.0
        self._published_at = self._clock_at = self._clock_heard = time.monotonic()
        self._clock_seen = False  # a mission clock heard yet (the first is checked: foreign_clock)
        self._foreign_clock: tuple[str, float, float] | None = None  # another mission's clock heard first:
        # why, when, its value
        self.clock_topic = clock_topic
        self._streamed = 0  # the latest version published

        self.pub_mission = self.create_publisher(String, T.mission, topics.MISSION_QOS)
        self.pub_board = self.create_publisher(String, T.board, topics.BOARD_QOS)
        self.pub_keyframe = self.create_publisher(String, T.keyframe, topics.KEYFRAME_QOS)
        self.pub_result = self.create_publisher(String, T.result, topics.RESULT_QOS)
        self.pub_rej = self.create_publisher(String, T.rejections, topics.REJECTION_QOS)
        self.pub_markers = self.create_publisher(MarkerArray, T.markers, topics.MARKER_QOS)
        self.pub_task_events = self.create_publisher(String, T.task_events, topics.TASK_EVENT_QOS)
        self.create_subscription(String, T.task_requests, self.on_task_request, topics.TASK_REQUEST_QOS)
        self.create_subscription(String, T.keyframe_requests, self.on_keyframe_request,
                                 topics.KEYFRAME_REQUEST_QOS)
        self.create_subscription(String, T.choice, self.on_choice, _deeper(topics.CHOICE_QOS, queue_depth))
        self.create_subscription(String, T.status, self.on_status, _deeper(topics.STATUS_QOS, queue_depth))
        self.create_subscription(Clock, clock_topic, self.on_clock, topics.CLOCK_QOS)
        # another board's mission in this namespace (its latched message): two missions would mix
        self.create_subscription(String, T.mission, self.on_other_mission, topics.MISSION_SUB_QOS)
        self.refusal: str | None = None  # why this board stopped at start (another mission in its namespace)
        self.refused = Future()  # done when it stopped so (whatever exit_on_done says)
        self._other_warned = -math.inf
        self._pose_subs = 0
        self._subscribe_poses()
        self.create_timer(0.1, self.on_watchdog)
        if marker_period > 0:
            self.create_timer(marker_period, self.on_markers)

        self.pub_mission.publish(mission_to_msg(self.mission))
        b = self.board
        self.get_logger().info(
            f"mission {inst.name}: {A} robots, {inst.n_tasks} tasks, method {b.method}, seed {self.seed}; "
            + ("resumed from its journal" if b.restarts else
               "waiting for every robot's agent and pose" if wait_for_robots else "starting"))
        self._flush()

    # ------------------------------------------------------------------------------------------
    # publishing
    # ------------------------------------------------------------------------------------------
    def _log(self, level: str, text: str) -> None:
        if level == "warning":  # one call site per severity (rclpy's logger requires it)
            self.get_logger().warning(text)
        else:
            self.get_logger().info(text)

    @property
    def finished(self) -> bool:
        return self.board.finished

    def _subscribe_poses(self) -> None:
        """Subscribe the pose of every robot not yet subscribed (robots that joined included),
        with its pose type's message class and QoS."""
        for a in range(self._pose_subs, len(self.names)):
            kind = self.pose_types.get(self.names[a], self.pose_type)
            self.create_subscription(POSE_TYPES[kind], self.topics.robot(self.names[a], topics.POSE),
                                     partial(self.on_pose, a), topics.POSE_SUB_QOS_BY_TYPE[kind])
        self._pose_subs = len(self.names)

    def _republish_mission(self) -> None:
        """Robots were added (a robot joined, a scenario's add_robot): publish the mission again,
        same session, with the grown robot list and instance (the robots added, not the tasks:
        those travel in the board's state), and follow the new robots' poses."""
        b = self.board
        b.robots_changed = False
        inst = dataclasses.replace(b.state.inst, tasks=self.inst.tasks, _cache={})
        self.mission = dataclasses.replace(self.mission, instance=inst, robots=tuple(self.names))
        self.pub_mission.publish(mission_to_msg(self.mission))
        self._subscribe_poses()
        self.get_logger().info(f"mission republished with {len(self.names)} robots "
                               f"(added: {', '.join(self.names[self.inst.n_agents:])})")

    def _flush(self) -> None:
        """Publish the board's new version, if any (it is journaled before it returns): its
        header on the stream, and the keyframe when it is one; the mission first when robots
        were added."""
        if self.board.robots_changed:
            self._republish_mission()
        v = self.board.poll()
        self._task_events()
        if v is None:
            return
        new = v.version > self._streamed  # not a header or keyframe published again
        self._streamed = max(self._streamed, v.version)
        if v.phase == "done" and new:
            self._finish()
        b = Board(v.session, v.version, v.rev, v.phase, v.decider, v.clock, v.horizon, v.n_done, v.n_cancelled,
                  v.n_tasks, v.lost, prev=v.prev, events=v.events, digest=v.digest)
        if v.stream:
            self.pub_board.publish(board_to_msg(b))
        if v.keyframe:
            kf = dataclasses.replace(b, legs=v.legs, until=v.until, keyframe=True)
            self.pub_keyframe.publish(board_to_msg(kf, v.state_json))
        if new:
            self._published_at = time.monotonic()
        if v.phase == "done" and new and self.exit_on_done:
            # linger briefly so that the final board and result reach everyone
            self._exit_timer = self.create_timer(1.0, self._exit)

    def _task_events(self) -> None:
        events, self.board.task_events = self.board.task_events, []
        for e in events:
            self.pub_task_events.publish(task_event_to_msg(TaskEvent(e["id"], e["event"], e["t"], e.get("task"),
                                                                     e.get("reason") or "", e.get("op", ""),
                                                                     e.get("request_id", ""))))

    def on_keyframe_request(self, msg: String) -> None:
        """A replica asks for a keyframe (it missed versions, diverged, or joined late)."""
        try:
            r = keyframe_request_from_msg(msg)
        except DecodeError as e:
            self.board.malformed()
            return self._reject("malformed", f"malformed keyframe request: {e}")
        if r.session != self.board.session:
            return
        if r.version != self.board.version:
            self.get_logger().info(f"keyframe asked for by {r.who or 'a replica'} at version {r.version} (board "
                                   f"{self.board.version}): {r.reason}", throttle_duration_sec=2.0)
        self.board.request(r.version, r.reason)
        self._flush()

    def on_task_request(self, msg: String) -> None:
        try:
            r = task_request_from_msg(msg)
        except DecodeError as e:
            self.board.malformed()
            self.get_logger().warning(f"rejected task request: {e}", throttle_duration_sec=1.0)
            self.pub_task_events.publish(task_event_to_msg(TaskEvent("", "rejected", self.board.clock,
                                                                     reason=f"malformed request: {e}",
                                                                     request_id=request_id_of(msg.data))))
            return
        ans = self.board.task_request(r.op, r.id, r.task, r.request_id)
        self.get_logger().info(f"task request {r.op} {r.id!r}: {ans['event']}"
                               + (f" ({ans['reason']})" if ans.get("reason") else ""))
        self._flush()

    def _reject(self, reason: str, detail: str, robot: str = "", version: int = -1, every: float = 0.0) -> None:
        """Log and publish a rejection (within ``rejection_rate``); ``every``: at most once every that
        many seconds per reason and robot (a driver streaming poses in the wrong frame), the rest
        counted in the periodic summary."""
        if every > 0 and self._recent((reason, robot), every):
            self._rej_quiet += 1
            return
        if self._rate_ok():
            if every > 0:
                self._note((reason, robot))
            self.get_logger().warning(f"rejected: {detail}")
            self.pub_rej.publish(rejection_to_msg(Rejection(reason, detail, robot, version)))

    def _recent(self, key: Any, every: float) -> bool:
        """Whether what ``key`` names was logged in the last ``every`` seconds."""
        return time.monotonic() - self._said.get(key, -math.inf) < every

    def _note(self, key: Any) -> None:
        """What ``key`` names is logged now."""
        if len(self._said) > 4096:  # bounded: a flood of distinct texts forgets the oldest first
            for k in list(self._said)[:2048]:
                del self._said[k]
        self._said[key] = time.monotonic()

    def _rate_ok(self) -> bool:
        """Token bucket (``rejection_rate`` per second, as many in a burst): whether this
        rejection is logged and published; the others are only counted, and summarised in one
        log line every few seconds."""
        if self._rejections.take(time.monotonic()):
            return True
        self._rej_quiet += 1
        return False

    # ------------------------------------------------------------------------------------------
    # callbacks
    # ------------------------------------------------------------------------------------------
    def on_choice(self, msg: String) -> None:
        try:
            c = choice_from_msg(msg)
        except DecodeError as e:
            self.board.malformed()
            return self._reject("malformed", f"malformed choice: {e}")
        r = self.board.choice(c)
        if r is not None:
            return self._reject(r.reason, r.detail, r.robot, r.version)
        self._flush()

    def on_status(self, msg: String) -> None:
        try:
            s = status_from_msg(msg)
        except DecodeError as e:
            self.board.malformed()
            return self._reject("malformed", f"malformed status: {e}")
        warn = self.board.heartbeat(s.session, s.robots, s.payload, s.joining, s.host, s.refused)
        if warn is not None and not self._recent(warn, 5.0) and self._rate_ok():  # each text at most every 5 s:
            self._note(warn)  # a warning the board gives once (two agent processes, a join refused) is kept
            self.get_logger().warning(warn)
        for j in s.joining:  # tell a robot the board refuses to add, so that its agent stops asking
            why = self.board.join_refused.get(j.robot)
            if why is not None and self._rate_ok():
                self.pub_rej.publish(rejection_to_msg(Rejection("join_refused", why, j.robot)))
        self._flush()

    def on_pose(self, a: int, msg: Any) -> None:
        frame = msg.header.frame_id
        if frame != self.mission.frame_id:
            self.board.rejected["wrong_frame"] += 1
            why = f"pose of {self.names[a]} in frame {short(frame)}, expected {self.mission.frame_id!r} (frame_id)"
            self.board.pose_rejected(a, why)
            return self._reject("wrong_frame", why, self.names[a], every=5.0)
        try:
            x, y, _ = pose_from_msg(msg, self.mission.scale)
        except DecodeError as e:
            self.board.malformed()
            self.board.pose_rejected(a, f"malformed pose: {e}")
            return self._reject("malformed", f"malformed pose of {self.names[a]}: {e}", self.names[a], every=5.0)
        if self.board.pose(a, x, y):  # a pose repeated (heartbeat) changes nothing to publish
            self._flush()

    def _choose(self, inst, options: dict[str, Any], journal: str) -> tuple[str, dict[str, Any]]:
        """(the live method, its options) of a board started with a method that chooses per mission
        (portfolio): the candidate of the shortest makespan (``self.choice`` records it). A board
        restarted on its journal takes the method its mission ran (never a new choice mid-mission)."""
        asked = self.method
        header = journal_header(journal) if journal else None
        if header is not None and isinstance(header.get("method"), str):
            spec = header["method"]
            self.get_logger().info(f"method {asked}: {spec}, as chosen when the mission started (journal {journal})")
        else:
            with signals_deferred():  # torch's import, if installed: a signal inside it would abort in C++
                try:  # the learned candidates' rollouts on one thread (torch's own choice collapses on a busy CPU)
                    require("torch", "the portfolio's learned candidates").set_num_threads(1)
                except MissingDependency:  # the portfolio leaves them out, and says why
                    pass
            self.get_logger().info(f"method {asked}: simulating the candidates on mission {inst.name} ...")
            t0 = time.monotonic()
            spec, _, scores = choose_live(inst, asked, self.seed, **options)
            self.get_logger().info(
                f"method {asked}: chose {spec} in {time.monotonic() - t0:.1f} s (makespans: "
                + ", ".join(f"{c} {v:.2f}" for c, v in scores.items()) + ")")
            self.choice = {"chosen": spec, "candidates": scores}
        return adopt(spec, options)

    # seconds a board that first heard another mission's clock waits (following no clock), once
    # its mission has started, before it stops: its own sim_robot's clock may still come (the
    # other was then a stray publisher beside it, which set_clock holds to the horizons; sim_robot
    # publishes its clock with the poses the start waits for), or the other mission's own message,
    # if it is in this namespace, which names it better
    FOREIGN_CLOCK_WAIT = 10.0

    def on_clock(self, msg: Clock) -> None:
        if self.refusal is not None:
            return
        t = clock_from_msg(msg)
        self._clock_heard = time.monotonic()
        if self._foreign_clock is not None:
            if t >= self._foreign_clock[2] - 1e-9:
                return  # only the other clock so far
            self._foreign_clock = None  # a clock from further back: this mission's own; the first was stray
            self.get_logger().info(f"mission clock {t:.3f} s heard: this mission's own; the other publisher's "
                                   f"is followed only up to the board's horizons")
        elif not self._clock_seen:
            self._clock_seen = True
            why = self.board.foreign_clock(t)
            if why is not None:
                self._foreign_clock = (f"{self.clock_topic}: {why}", time.monotonic(), t)
                self.get_logger().warning(f"mission clock {t:.3f} s on {self.clock_topic} before this board released "
                                          f"any time: another publisher's; waiting for this mission's own "
                                          f"(sim_robot's, from 0: up to {self.FOREIGN_CLOCK_WAIT:g} s after the start)")
                return
        if self.board.set_clock(t):
            self._clock_at = time.monotonic()
            self._flush()

    def on_watchdog(self) -> None:
        b = self.board
        if b.finished:
            return
        now = time.monotonic()
        if self._foreign_clock is not None and self.refusal is None and b.t_start is not None and \
                now - max(self._foreign_clock[1], b.t_start) >= self.FOREIGN_CLOCK_WAIT:  # (b.now: monotonic)
            self._refuse(self._foreign_clock[0])
            return
        if not b.started and now - self.t_created > 5.0:
            agents = [n for a, n in enumerate(self.names) if b.seen_status[a] is None]
            poses = [n for a, n in enumerate(self.names) if b.seen_pose[a] is None]
            bad = [a for a in range(len(self.names)) if b.seen_pose[a] is None and a in b.pose_rejections]
            self.get_logger().info(_waiting_text(self.names, agents, poses, now - self.t_created, b.startup_timeout)
                                   + f" (heartbeats on {self.topics.status}, poses on "
                                   f"{self.topics.robot('<robot>', topics.POSE)})"
                                   + (f"; {len(bad)} of those robots' poses are heard but rejected, e.g. "
                                      f"{b.pose_rejections[bad[0]]}" if bad else ""),
                                   throttle_duration_sec=5.0)
        b.tick()
        self._flush()
        if self._rej_quiet and now - self._rej_summary_at >= 5.0:
            self._rej_summary_at = now
            self.get_logger().warning(f"{self._rej_quiet} more message(s) rejected (not logged one by one: more than "
                                      f"{self.rejection_rate:g}/s, or a robot's pose rejected again within 5 s); "
                                      f"by reason so far: {dict(b.rejected)}")
            self._rej_quiet = 0
        if b.phase in ("wait", "closing") and now - max(self._published_at, self._clock_at, b.resumed_at) > 5.0:
            silent = now - max(self._clock_heard, b.resumed_at)  # (the board's own stall: not the clock's silence)
            if silent > 5.0:  # nobody drives the clock: not a robot's fault
                self.get_logger().warning(f"mission clock held: nothing heard on {self.clock_topic} for {silent:.0f} s "
                                          f"(is sim_robot, or whatever publishes the mission clock, running?); "
                                          f"{b.waiting_for()}", throttle_duration_sec=10.0)
            else:
                self.get_logger().warning(f"mission clock held: {b.waiting_for()}", throttle_duration_sec=10.0)
        if self.progress_period > 0 and now - self._last_progress >= self.progress_period and b.started:
            self._last_progress = now
            st = b.state
            self.get_logger().info(f"t={b.clock:.2f}: {st.n_done}/{st.M} tasks done, phase {b.phase}, "
                                   f"{len(b.lost)} lost, {sum(b.rejected.values())} rejected")

    def on_markers(self) -> None:
        if self.pub_markers.get_subscription_count() == 0:
            return
        b = self.board
        key = (b.rev, tuple(b.last_pose))
        if key == self._marker_key:
            return
        self._marker_key = key
        st, inst = b.state, self.inst
        pos = st.positions()
        tasks = tuple((float(x), float(y), STATUS_NAMES[s]) for (x, y), s in zip(inst.task_locations, st.status))
        robots = tuple((n, *(b.last_pose[a] or (float(pos[a, 0]), float(pos[a, 1]))), a in b.lost)
                       for a, n in enumerate(self.names))
        legs = tuple((float(st.from_pos[a, 0]), float(st.from_pos[a, 1]), float(st.to_pos[a, 0]),
                      float(st.to_pos[a, 1])) for a in range(st.A) if st.arrive[a] > b.clock)
        m = self.mission
        self.pub_markers.publish(markers_to_msg(MarkerView(tasks, robots, legs), b.clock, m.frame_id, m.scale))

    # ------------------------------------------------------------------------------------------
    def result(self):
        """The board's result, with what a portfolio chose (as offline) and the checkpoint the
        mission's method runs (path and sha256, as offline), for a method that takes one."""
        sol = self.board.result()
        if self.choice is not None:
            sol.extra["portfolio"] = dict(self.choice)
        if self._checkpoint is not None:
            sol.extra["checkpoint"] = dict(self._checkpoint)
        return sol

    def _finish(self) -> None:
        sol = self.result()
        self.failure = None if sol.success else str(sol.extra.get("failure") or "the mission did not succeed")
        self.pub_result.publish(result_to_msg(sol.to_dict()))  # first: a file that cannot be written loses nothing
        if self.output:
            try:
                sol.save(self.output)
            except OSError as e:
                self.get_logger().error(f"output: cannot write {self.output} ({e.strerror or type(e).__name__}); "
                                        f"the result went out on {self.pub_result.topic_name} only")
                self.output = ""
        lost = self.board.lost
        self.get_logger().info(sol.summary() + (f"; lost {sol.extra['lost_robots']}, undone tasks "
                                                f"{sol.extra['undone_tasks']}" if lost else "")
                               + (f"; wrote {self.output}" if self.output else ""))
        if self.failure is not None:
            self.get_logger().error(f"mission failed: {self.failure} (exit status 3)")

    def exit_status(self) -> int:
        """0; 3 when the mission finished and failed (as ``hmrta solve`` and ``hmrta-mission``); 2
        when it stopped at start, another mission being in its mission namespace or on its clock."""
        return 2 if self.refusal is not None else 3 if self.failure is not None else 0

    # a board that hears an older mission in its namespace within this many seconds of its start stops
    NEWCOMER = 10.0

    # seconds a board that refused its mission stays for the others to get its mission message
    LEAVE_WITHIN = 3.0

    def _refuse(self, why: str) -> None:
        """Stop at start, with exit status 2 and ``why`` logged: this board cannot run its mission
        here. It leaves once the other nodes on its mission topic have its mission message (so the
        earlier mission's board can warn of it), within LEAVE_WITHIN s."""
        self.refusal = why
        self.get_logger().error(f"{why}; stopping (exit status 2)")
        self.board.close()
        self._refused_at = time.monotonic()
        self.create_timer(0.1, self._leave)
        self._leave()

    def _leave(self) -> None:
        if self.refused.done():
            return
        others = self.pub_mission.get_subscription_count() > 1  # (its own subscription is one)
        if (others and self.pub_mission.wait_for_all_acked(Duration(seconds=0))) or \
                time.monotonic() - self._refused_at >= self.LEAVE_WITHIN:
            for f in (self.done, self.refused):
                if not f.done():
                    f.set_result(True)

    def on_other_mission(self, msg: String) -> None:
        """A mission message of another session on this board's mission topic: a second mission in
        the same mission namespace on this ROS domain, whose agents and robots would answer both
        boards. The later-created mission gives way (its agents keep to the earlier one, see
        agent_node): its board, if it hears the other within ``NEWCOMER`` s of its start, stops
        with exit status 2 and says why; otherwise, and on the earlier mission's board, a warning
        (every 10 s)."""
        if self.refusal is not None:
            return
        try:
            other = mission_from_msg(msg)
        except DecodeError:
            return
        if other.session == self.board.session:
            return
        ns = self.topics.namespace
        text = (f"another task board publishes mission {short(other.instance.name)} (session {short(other.session)}) "
                f"in mission namespace {ns} on this ROS domain: two missions in one mission namespace mix (agents and "
                f"robots answer both boards); give each mission its own mission_namespace or ROS_DOMAIN_ID")
        now = time.monotonic()
        if self.mission.newer_than(other) and now - self.t_created <= self.NEWCOMER:
            self._refuse(text + "; that mission was created earlier: this board gives way")
        elif now - self._other_warned >= 10.0:
            self._other_warned = now
            self.get_logger().warning(text)

    def stopped(self, sig: str) -> str:
        """The log line of a board stopped by a signal."""
        b = self.board
        if b.finished:
            return f"stopped by {sig} (the mission had finished)"
        return (f"stopped by {sig} before the mission finished: t={b.clock:.3f}, {b.state.n_done}/{b.state.M} tasks "
                f"done, phase {b.phase}" + (f"; the journal {b.journal.path} resumes it" if b.journal else ""))

    def _exit(self) -> None:
        self._exit_timer.cancel()
        self.board.close()
        if not self.done.done():
            self.done.set_result(True)


def _pose_types(items: list[str]) -> dict[str, str]:
    """``pose_types`` entries ``ROBOT:TYPE`` -> {robot: pose type}; ValueError naming the entry."""
    out: dict[str, str] = {}
    for item in items:
        robot, sep, kind = item.rpartition(":")
        robot = robot.strip().strip("/")
        if not sep or not robot:
            raise ValueError(f"pose_types: expected ROBOT:TYPE (robot_1:Odometry), got {item!r}")
        try:
            out[robot] = pose_type(kind)
        except ValueError as e:
            raise ValueError(f"pose_types: {item!r}: {e}") from None
    return out


def _deeper(qos: QoSProfile, depth: int) -> QoSProfile:
    """``qos`` with a receive history of ``depth`` messages (at least its own)."""
    return QoSProfile(history=qos.history, depth=max(qos.depth, depth), reliability=qos.reliability,
                      durability=qos.durability)


def _names(names: list[str]) -> str:
    return ", ".join(names) if len(names) <= 8 else f"{', '.join(names[:6])}, ..., {names[-1]}"


def _waiting_text(names: list[str], agents: list[str], poses: list[str], waited: float, timeout: float) -> str:
    """The start-up wait in one line: how many of the robots' agents and poses are missing (which
    ones, the first few), for how long, and what happens at ``timeout`` (the board's
    ``startup_timeout``; 0 waits without limit)."""
    parts = [f"{len(missing)} of {len(names)} {what} ({_names(missing)})"
             for what, missing in (("agents", agents), ("poses", poses)) if missing]
    heard = [f"every {what} heard" for what, missing in (("agent", agents), ("pose", poses)) if not missing]
    end = (f"at {timeout:g} s (startup_timeout) the mission starts without the robots still missing"
           if timeout > 0 else "no limit (startup_timeout 0)")
    heard_text = f" ({', '.join(heard)})" if heard else ""
    return f"waiting for {' and '.join(parts) or 'the start'} for {waited:.0f} s{heard_text}; {end}"


def main(args: list[str] | None = None) -> int:
    """Exit status: 0, 2 a user error, 3 the mission finished and failed, 130 Ctrl-C at start-up."""
    argv = sys.argv if args is None else args
    from hmrta_msgs_py.params import node_parameters
    from hmrta_msgs_py.runtime import help_requested, no_own_arguments

    help_requested(argv, "task_board", __doc__.split("\n\n")[0], node_parameters("task_board"))
    no_own_arguments("task_board", argv)
    # a bad mission file, policy or parameter is a user error
    with starting("task_board", (InstanceError, MethodError, JournalError, ValueError), args=argv):
        board = TaskBoard()
    spin_nodes([board], until=board.done if board.exit_on_done else board.refused, stopped=board.stopped,
               exit_status=board.exit_status)
    return board.exit_status()


if __name__ == "__main__":
    sys.exit(main())
