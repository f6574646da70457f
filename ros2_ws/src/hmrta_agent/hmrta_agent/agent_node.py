"""agent_node: one robot's decision maker.

Builds its view only from received topics: the mission (``<ns>/hmrta/mission``; ``<ns>`` is the
``mission_namespace`` parameter, default ``/``), the board stream (``<ns>/hmrta/board``: every
version's events) and keyframes (``<ns>/hmrta/board_keyframe``), and the mission clock
(``clock_topic``, default ``<ns>/hmrta/clock``; never ``/clock``; followed only up to the horizon
of the board's stream, as the board follows it); the agents hosted in one
process share one subscription to each, one choice publisher, one replica of the board's state
machine (:class:`hmrta.replica.Replica`: it starts from a keyframe and applies every version's
events; a version it misses, or a state whose digest differs from the board's, makes it ask for a
keyframe on ``<ns>/hmrta/keyframe_requests``, again every second until one comes, with the reason
in the log) and one copy of the policy. When the board names this robot as the current decider,
its agent runs its own copy of the policy on the replica's state and publishes its choice
(``<ns>/hmrta/choice``, tagged with the board session and version it answers). The board's state
lists every leg the robot must drive (its own choices and automatic ones such as going home);
when the mission clock reaches a leg's departure time the agent publishes it as a
``geometry_msgs/PoseStamped`` goal on ``goal_pose`` (relative: in the node's namespace, stamp =
departure time), which a Nav2 navigator or ``sim_robot`` consumes unchanged. A heartbeat on
``<ns>/hmrta/agent_status`` tells the board it is alive (sent only once the board and the robot's
driver listen, so that nothing the agent sends is lost).

A robot joins a running mission by starting its agent under a name the mission does not have,
with its species (``-p species:=S``, an index of the mission's species): the heartbeat asks the
board to add it (at its driver's reported pose, else its species' depot); the board republishes
the mission with it and it takes part in the next decisions. An agent not in the mission and
without a species waits until the board adds its robot (a scenario's ``add_robot`` event).

The agent reads its robot's pose (``pose`` in its namespace, of type ``pose_type``: remap it to
the driver's, e.g. ``-r pose:=amcl_pose -p pose_type:=PoseWithCovarianceStamped``) to report
where a joining robot is and, when the board drops the robot, to stop it where it is: a goal at
its latest pose replaces the goal it may still be driving to.

Method: by default (``method:=portfolio``) the agent runs the mission's method, whatever its board
runs (a board started with ``portfolio`` chooses one at the start and names it in the mission);
``-p method:=greedy`` (or any live method) runs that one, which must run under the mission's rules.

One robot per process::

    agent_node --ros-args -r __ns:=/robot_3 -p method:=greedy -p seed:=1

or many robots in one process (lean nodes on one executor, one shared copy of the policy; node
``<ns>/<robot>/agent`` each)::

    agent_node --robots robot_0,robot_1,robot_2 --ros-args -p method:=rl

A mission in a namespace (``-p mission_namespace:=/fleet1`` on every node of the mission): one
robot per process runs in ``-r __ns:=/fleet1/robot_3`` (goals on ``/fleet1/robot_3/goal_pose``,
where ``sim_robot`` of that mission listens), ``--robots`` puts its nodes there itself.

Authenticated missions (``hmrta.keys``, docs/security.md): ``-p keystore:=DIR`` (the process
loads the keys of the robots it hosts from the mission keystore) or ``-p key_file:=FILE`` (one
robot's ``robots/<robot>.key.json``); the process then signs every choice and heartbeat.
"""
from __future__ import annotations

import argparse
import math
import os
import socket
import sys
import time
from typing import Any

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.task import Future
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from hmrta.keys import KeystoreError, Signer, load_key_file, load_keystore
from hmrta.methods import MethodError, adopt, checkpoint_of, chooses, decider, live_label
from hmrta.replica import Replica
from hmrta_msgs_py import topics
from hmrta_msgs_py.console import signals_deferred
from hmrta_msgs_py.codec import (POSE_TYPES, Choice, DecodeError, Join, KeyframeRequest, Mission, Refusal, Status,
                                 board_from_msg, choice_to_msg, clock_from_msg, keyframe_request_to_msg,
                                 mission_from_msg, pose_from_msg, pose_to_msg, pose_type, rejection_from_msg,
                                 status_to_msg, yaw_from_msg)
from hmrta_msgs_py.runtime import (BoardSilence, LEAN_NODE, declare_method_parameters, mission_namespaces,
                                   parameters_read_at_start, spin_nodes, starting)
from hmrta_msgs_py.codec import RESEND  # leg node: the board re-sends a goal


EPS = 1e-6  # sim-time comparisons (stamps are rounded to the nanosecond)
# a choice the board has not acted on after this many seconds is sent again (freshly signed): a
# flood of junk on /hmrta/choice can push it out of the board's queue; a copy that arrives after
# the first was applied is rejected as a duplicate and changes nothing
RESEND_AFTER = 1.0


class Host:
    """What the agents of one process share: the policy (one read-only copy of the weights), one
    subscription each to the mission, the board stream, the keyframes and the clock (decoded
    once), one replica of the board's state, and the heartbeat."""

    def __init__(self) -> None:
        self._node: Node | None = None  # the node the process's subscriptions live on (attach)
        self.replica = Replica()
        self._deciders: dict[tuple, Any] = {}
        self.torch_threads = 1  # torch's threads once a decider loaded it (--torch-threads)
        self._mission_text: str | None = None
        self.mission: Mission | None = None
        self.agents: list["AgentNode"] = []
        self.all_done = Future()
        self._seq = 0
        self._status_pub = None
        self._request_pub = None
        # agents that refuse the mission, told to the board before they stop (report_refusal)
        self._refusals: list[dict[str, Any]] = []
        self._refusal_timer = None
        self.clock = 0.0  # the mission clock as followed: never past the board's horizon (_on_clock)
        self.horizon = 0.0  # the latest horizon of the board's session (the clock may run up to it)
        self._horizon_session: str | None = None
        self._beyond = 0.0  # a clock heard past the horizon, followed as later horizons allow
        self._session_heard = -math.inf  # when the board of the mission followed was last heard
        self._held: tuple[String, Mission] | None = None  # a later mission heard while that board is (_on_mission)
        self.waiting: dict[int, "AgentNode"] = {}  # agents with legs not yet due, by id (the clock flushes them)
        self.keys: dict[str, bytes] = {}  # the hosted robots' keys (authenticated missions)
        self.signer: Signer | None = None  # one per process: its counter orders every message it signs
        self._keystores: dict[str, dict[str, bytes]] = {}
        self._dispatched = -1  # the replica version the agents last acted on
        self._walked: tuple = ()  # (state, mission, robots, lost, done) at the last walk of every agent
        self._by_index: dict[int, "AgentNode"] = {}  # hosted agents by robot index (as of that walk)
        self._unsettled: list["AgentNode"] = []  # agents not yet following the board (acted on every version)
        self._choice_pub = None  # one choice publisher for every agent of the process
        self.topics: topics.MissionTopics | None = None  # the mission's (its agents' mission_namespace)
        self._kf_sessions: set[str] = set()  # sessions a keyframe was received for (the first may be old)
        self._early: list[tuple[String, bool]] = []  # keyframes that came before the mission
        self.ignore: set[int] = set()  # testing (--ignore-board-version): versions dropped once, as if lost
        self._ignored: set[tuple[int, bool]] = set()
        self.silence: BoardSilence | None = None  # when to warn that no board is heard

    def exit_status(self) -> int:
        """2 when an agent of the process refused to take part (its configuration or the mission's), else 0."""
        return 2 if any(a.refusal is not None for a in self.agents) else 0

    def add_key(self, robot: str, keystore: str, key_file: str) -> None:
        """Load ``robot``'s key from a keystore folder or from its own key file (KeystoreError:
        missing, unreadable, or the file is another robot's)."""
        if keystore:
            if keystore not in self._keystores:
                self._keystores[keystore] = load_keystore(keystore)
            keys = self._keystores[keystore]
            if robot not in keys:
                raise KeystoreError(f"{keystore}: robots: no key for {robot}")
            self.keys[robot] = keys[robot]
        elif key_file:
            owner, key = load_key_file(key_file)
            if owner != robot:
                raise KeystoreError(f"{key_file}: robot: the key of {owner!r}, not of {robot!r}")
            self.keys[robot] = key
        if self.keys:
            self.signer = Signer(self.keys)

    def decider(self, method: str, seed: int, options: dict[str, Any]):
        key = (method, seed, tuple(sorted(options.items())))
        if key not in self._deciders:
            self._deciders[key] = decider(method, seed, **options)
            _set_torch_threads(self.torch_threads)  # (a portfolio agent builds its decider once the mission comes)
        return self._deciders[key]

    def attach(self, node: Node, period: float) -> None:
        """Subscribe the mission, the board stream, the keyframes and the clock, and start the
        heartbeat (one status message per period lists every robot this process hosts), on one
        node of the process."""
        self._node = node
        T = self.topics
        node.create_subscription(String, T.mission, self._on_mission, topics.MISSION_SUB_QOS)
        node.create_subscription(String, T.board, self._on_board, topics.BOARD_QOS)
        node.create_subscription(String, T.keyframe, self._on_keyframe, topics.KEYFRAME_QOS)
        node.create_subscription(Clock, getattr(node, "clock_topic", T.clock), self._on_clock, topics.CLOCK_QOS)
        node.create_subscription(String, T.rejections, self._on_rejection, topics.REJECTION_QOS)
        self._status_pub = node.create_publisher(String, T.status, topics.STATUS_QOS)
        self._request_pub = node.create_publisher(String, T.keyframe_requests, topics.KEYFRAME_REQUEST_QOS)
        self._host = f"{socket.gethostname()}:{os.getpid()}"
        self.silence = BoardSilence(getattr(node, "board_silence_warning", 10.0), mission=T)
        node.create_timer(period, self._beat)
        node.create_timer(1.0, self._check_silence)
        self._beat()

    def _heard(self) -> None:
        if self.silence is not None:
            again = self.silence.heard()
            if again is not None:
                self._node.get_logger().info(again)

    def _mission_over(self) -> bool:
        h = self.replica.head
        return self.mission is not None and h is not None and h.session == self.mission.session and h.phase == "done"

    def _check_silence(self) -> None:
        held = self._held
        if held is not None and not self.all_done.done() and (
                time.monotonic() - self._session_heard >= self.KEEP or self._mission_over()):
            self._held = None  # the mission followed is gone or over: the later one is taken
            self._on_mission(held[0])
        for a in self.agents:
            a.check_waiting()
        head = self.replica.head
        if self.silence is None or self.all_done.done() or (head is not None and head.phase == "done"):
            return
        text = self.silence.check(self.replica.version if head is not None else None,
                                  lambda: mission_namespaces(self._node))
        if text is not None:
            self._node.get_logger().warning(text)

    def _on_rejection(self, msg: String) -> None:
        """The board refused to add a robot of this process that asked to join: it stops asking."""
        try:
            r = rejection_from_msg(msg)
        except DecodeError:
            return
        if r.reason == "join_refused":
            for a in self.agents:
                if a.robot == r.robot and a.mission is None:
                    a.refused(r.detail)

    # seconds: a mission whose board was heard this recently is kept over a later-created one
    KEEP = 5.0

    def _on_mission(self, msg: String) -> None:
        """The mission (again when robots join). A mission of another session replaces the one
        followed, except a later-created one while the board of the one followed is heard (two
        missions in one mission namespace: the later one's board gives way, task_board): it is
        held, and taken once that board has been silent for ``KEEP`` s or its mission is over."""
        self._heard()
        if msg.data == self._mission_text:
            return
        try:
            m = mission_from_msg(msg)
        except DecodeError as e:
            self._node.get_logger().error(f"ignoring malformed mission: {e}")
            return
        cur, now = self.mission, time.monotonic()
        if (cur is not None and m.session != cur.session and m.newer_than(cur) and now - self._session_heard < self.KEEP
                and not self._mission_over()):
            if self._held is None or self._held[1].session != m.session:
                self._node.get_logger().warning(
                    f"a later mission {m.instance.name} (session {m.session}) is published on {self.topics.mission} "
                    f"while the board of mission {cur.instance.name} (session {cur.session}) is heard: keeping "
                    f"that one (two missions in one mission namespace)")
            self._held = (msg, m)
            return
        self._held = None
        self.mission, self._session_heard = m, now
        self._mission_text = msg.data
        for a in self.agents:
            a.join(self.mission)
        early, self._early = self._early, []
        for kf, latched in early:  # the two latched topics arrive in either order
            self._on_keyframe(kf, latched)

    # ------------------------------------------------------------------------------------------
    # the board: stream and keyframes -> the replica -> the agents
    # ------------------------------------------------------------------------------------------
    def _on_board(self, msg: String) -> None:
        t_recv = time.perf_counter()
        self._heard()
        try:
            b = board_from_msg(msg, legs=False, state=False)
        except DecodeError as e:
            self._node.get_logger().error(f"ignoring malformed board: {e}", throttle_duration_sec=10.0)
            return
        if not self._lost(b.version, False):
            self._take(b, None, False, t_recv)

    def _on_keyframe(self, msg: String, latched: bool | None = None) -> None:
        t_recv = time.perf_counter()
        self._heard()
        try:
            b = board_from_msg(msg, legs=False, state=False)
        except DecodeError as e:
            self._node.get_logger().error(f"ignoring malformed keyframe: {e}", throttle_duration_sec=10.0)
            return
        if latched is None:  # the first keyframe of a session may be the old one a latched topic kept
            latched = b.session not in self._kf_sessions
            self._kf_sessions.add(b.session)
        if self.mission is None:
            self._early = [(msg, latched)]
            return
        if not self._lost(b.version, True):
            self._take(b, lambda: self._keyframe_parts(msg), latched, t_recv)

    @staticmethod
    def _keyframe_parts(msg: String) -> tuple[Any, dict[str, Any]]:
        full = board_from_msg(msg)
        return full.legs, full.state

    def _lost(self, version: int, keyframe: bool) -> bool:
        """Testing (``--ignore-board-version``): the messages of that version are dropped once."""
        if version in self.ignore and (version, keyframe) not in self._ignored:
            self._ignored.add((version, keyframe))
            self._node.get_logger().warning(f"ignoring the board {'keyframe' if keyframe else 'header'} of version "
                                            f"{version} (--ignore-board-version: as if it were lost)")
            return True
        return False

    def _take(self, b, keyframe, latched: bool, t_recv: float) -> None:
        m = self.mission
        if m is not None and b.session != m.session:
            return
        if m is not None:
            self._session_heard = time.monotonic()
            self._new_horizon(b.session, b.horizon)
        r = self.replica
        before = r.why
        out = r.receive(b, keyframe, m.instance if m is not None else None, latched)
        if out in ("diverged", "bad") or (out == "ahead" and r.synced and r.why != before):
            self._node.get_logger().warning(f"board replica: {r.why}: asking for a keyframe")
        self._ask()
        if r.current and r.version != self._dispatched:
            self.dispatch(t_recv)

    def _ask(self) -> None:
        """Send the replica's keyframe request, if it has one now (it repeats it every second
        until it is current again; the log says why and for how long)."""
        if self._request_pub is None:
            return
        ask = self.replica.request()
        if ask is None:
            return
        version, why = ask
        r = self.replica
        waited = (r.asked_at or 0.0) - (r.asking_since or 0.0)
        if waited > 0:
            self._node.get_logger().warning(f"board replica: no keyframe {waited:.1f} s after asking ({why}); "
                                            "asking again", throttle_duration_sec=5.0)
        else:
            self._node.get_logger().info(f"board replica: asking for a keyframe ({why})")
        self._request_pub.publish(keyframe_request_to_msg(KeyframeRequest(self.replica.session or "", version, why,
                                                                          self._host)))

    def choice_publisher(self, node: Node):
        """The process's publisher of choices (created on the first agent's node): one writer
        however many robots the process hosts (each choice names and signs its robot)."""
        if self._choice_pub is None:
            self._choice_pub = node.create_publisher(String, self.topics.choice, topics.CHOICE_QOS)
        return self._choice_pub

    def dispatch(self, t_recv: float | None = None) -> None:
        """Hand the replica's version to the agents of the process it concerns (once it is
        current): the decider first (latency), every robot given legs since the last dispatch,
        and the agents not yet settled (not ready, not in the mission, lost, new legs pending).
        Hundreds of robots in one process: most versions concern a few, so the others are not
        walked; a new state (keyframe), mission, team or loss, and the mission's end, walk them all."""
        t_recv = time.perf_counter() if t_recv is None else t_recv
        r = self.replica
        if not r.current or self.mission is None or r.head.session != self.mission.session:
            return
        head, st = r.head, r.state
        self._dispatched = r.version
        touched, st.touched = st.touched, set()
        walk = (st, self.mission, st.A, head.lost, head.phase == "done")  # (objects, not ids: an id can be reused)
        w = self._walked
        if not w or w[0] is not st or w[1] is not self.mission or w[2:] != walk[2:]:
            self._walked = walk
            self._by_index = {a.index: a for a in self.agents if a.index is not None}
            todo = list(self.agents)
        else:
            todo = [self._by_index[i] for i in sorted(touched) if i in self._by_index] + self._unsettled
        d = self._by_index.get(head.decider) if head.decider is not None else None
        order = list({id(a): a for a in ([d] if d is not None else []) + todo}.values())  # the decider first
        lost = set(head.lost)
        for a in order:
            if a is d or not self._settled(a, head, st, lost):
                a.act(head, t_recv)
        self._unsettled = [a for a in order if not self._settled(a, head, st, lost)]

    @staticmethod
    def _settled(a: "AgentNode", head, st, lost: set[int]) -> bool:
        """Whether agent ``a`` follows the board with nothing new for it in this version (its
        robot's legs unchanged, the mission not over)."""
        i = a.index
        return (head.phase != "done" and i is not None and i < st.A and i not in lost and a.ready
                and not a.finished and a.leg_seq == st.leg_seq(i))

    def _on_clock(self, msg: Clock) -> None:
        """The mission clock, followed only up to the horizon the board has published, as the
        board itself does (``MissionBoard.set_clock``): the simulated robots never take it
        further, so a clock past it comes from another publisher (a recording played back, a
        stray node), and following it would send goals early. Held there, it is released as
        later horizons allow (the simulated robots' clock often comes before the board's header
        that allows it: the two have different publishers); a clock within the horizon forgets
        the one beyond. Silent: the board warns of a stray clock, and here a held clock is
        mostly that ordinary race."""
        t = clock_from_msg(msg)
        if t <= self.horizon + EPS:
            self._beyond = 0.0
        else:
            self._beyond = max(self._beyond, t)
            t = self.horizon
        self._advance(t)

    def _new_horizon(self, session: str, horizon: float) -> None:
        """A board header's horizon (``_take``, before the agents see its version): the clock held
        at the previous horizon moves on up to it."""
        if session != self._horizon_session:
            if self._horizon_session is not None:  # a new mission: its clock starts again
                self.clock, self._beyond = 0.0, 0.0
            self._horizon_session, self.horizon = session, 0.0
        if horizon > self.horizon:
            self.horizon = horizon
            if self._beyond > self.clock:
                self._advance(min(self._beyond, horizon))

    def _advance(self, t: float) -> None:
        if t > self.clock:
            self.clock = t
            for k, a in list(self.waiting.items()):  # only the robots with goals waiting, not the whole team
                a.flush_goals()
                if not a.pending:
                    del self.waiting[k]

    def _beat(self) -> None:
        if not rclpy.ok():
            return
        if any(not a.ready and a.is_ready() for a in self.agents):
            self._dispatched, self._walked = -1, ()
            self.dispatch()  # what they saw while not ready (they held back: their messages would be lost)
        self._ask()  # a replica still waiting for a keyframe asks again
        sessions: dict[str, list[str]] = {}
        joining: list[Join] = []
        for a in self.agents:
            if a.ready and not a.finished:
                sessions.setdefault(a.mission.session, []).append(a.robot)
            elif a.wants_to_join():
                joining.append(Join(a.robot, a.species_param, None, a.position()))
        if joining:
            sessions.setdefault(self.mission.session, [])
        r = self.replica
        if r.current and self.mission is not None and r.head.session == self.mission.session:
            for a in self.agents:
                a.resend(r.head)
        for session, robots in sessions.items():
            self._seq += 1
            join = tuple(joining) if self.mission is not None and session == self.mission.session else ()
            self._status_pub.publish(status_to_msg(Status(tuple(robots), session, self._seq, self._host, joining=join),
                                                   self.signer))

    def agent_finished(self) -> None:
        if all(a.finished for a in self.agents) and not self._refusals and not self.all_done.done():
            self.all_done.set_result(True)

    # an agent that refuses the mission: how long it waits for the board to hear it (a reader of
    # its status matched, the message acknowledged) before it stops all the same, and how long it
    # keeps sending it to readers that match later (the recorder's may match before the board's)
    REFUSAL_WAIT = 3.0
    REFUSAL_SETTLE = 1.0

    def report_refusal(self, agent: "AgentNode", session: str, why: str) -> None:
        """Tell the board that ``agent``'s robot, one of the mission ``session``, does not take
        part (``why``: the agent's reason): a status message with ``refused``, sent to every
        reader of the status topic as it matches, for REFUSAL_SETTLE seconds after the first and
        then until acknowledged (REFUSAL_WAIT seconds in all at most); the agent then counts as
        finished. Without it the board would wait out its start-up timeout with no reason to give."""
        now = time.monotonic()
        self._refusals.append({"agent": agent, "session": session, "why": why, "give_up": now + self.REFUSAL_WAIT,
                               "first": None, "readers": 0})
        if self._refusal_timer is None and self._node is not None:
            self._refusal_timer = self._node.create_timer(0.05, self._send_refusals)
        self._send_refusals()

    def _send_refusals(self) -> None:
        from rclpy.duration import Duration

        pub, now, left = self._status_pub, time.monotonic(), []
        readers = pub.get_subscription_count() if pub is not None and rclpy.ok() else 0
        for r in self._refusals:
            if readers > r["readers"]:  # a reader more (the board's, the recorder's): it gets the refusal too
                self._seq += 1
                refusal = (Refusal(r["agent"].robot, r["why"]),)
                pub.publish(status_to_msg(Status((), r["session"], self._seq, self._host, refused=refusal), self.signer))
                r["first"] = now if r["first"] is None else r["first"]
                r["readers"] = readers
            heard = (r["first"] is not None and now - r["first"] >= self.REFUSAL_SETTLE
                     and (not rclpy.ok() or pub.wait_for_all_acked(Duration(seconds=0))))
            if heard:
                continue
            if now < r["give_up"] and rclpy.ok():
                left.append(r)
            elif r["first"] is None:
                r["agent"].get_logger().warning(f"{r['agent'].robot}: no task board heard this refusal (nothing reads "
                                                f"{self.topics.status} here); its board waits until its start-up timeout")
        self._refusals = left
        if not left:
            if self._refusal_timer is not None:
                self._refusal_timer.cancel()
                self._refusal_timer = None
            self.agent_finished()


@parameters_read_at_start
class AgentNode(Node):
    def __init__(self, host: Host, **node_kw: Any):
        super().__init__("agent", **node_kw)
        self.host = host
        host.agents.append(self)
        robot = self.declare_parameter("robot", "").value
        self.robot = robot or self.get_namespace().strip("/").split("/")[-1]
        if not self.robot:
            raise ValueError("set the robot name (-p robot:=NAME or a namespace, -r __ns:=/NAME)")
        topics.check_robot_name(self.robot)  # its topics are <ns>/<robot>/...: refused here, by its parameter
        self.index_param = self.declare_parameter("index", -1).value
        self.species_param = self.declare_parameter("species", -1).value
        for k, v in (("index", self.index_param), ("species", self.species_param)):
            if v < -1:
                raise ValueError(f"{k}: expected an integer >= 0, or -1 (not set), got {v}")
        self.method, self.options = declare_method_parameters(self)
        self.seed = self.declare_parameter("seed", 0).value
        self.exit_on_done = self.declare_parameter("exit_on_done", True).value
        # a method that chooses per mission (portfolio) runs the one its board chose and names as the
        # mission's method: the decider is made when the mission is heard (_adopt)
        self.chooser = self.method if chooses(self.method) else None
        with signals_deferred():  # loading torch (learned methods): a signal inside it would abort in C++
            self.decide, self.rules = (None, None) if self.chooser else host.decider(self.method, self.seed,
                                                                                      self.options)
        keystore = self.declare_parameter("keystore", "").value
        key_file = self.declare_parameter("key_file", "").value
        self.topics = topics.mission_topics(self.declare_parameter("mission_namespace", "/").value)
        if host.topics is None:
            host.topics = self.topics
        elif host.topics.namespace != self.topics.namespace:
            raise ValueError(f"mission_namespace: the robots of one agent_node process take part in one mission, "
                             f"but {self.robot} has {self.topics.namespace} and another {host.topics.namespace}")
        self.clock_topic = self.topics.clock_topic(self.declare_parameter("clock_topic", "").value)
        self.board_silence_warning = self.declare_parameter("board_silence_warning", 10.0).value
        if not (self.board_silence_warning >= 0 and math.isfinite(self.board_silence_warning)):
            raise ValueError(f"board_silence_warning: expected a number of seconds >= 0 (0: never), "
                             f"got {self.board_silence_warning!r}")
        try:
            self.pose_type = pose_type(self.declare_parameter("pose_type", "PoseStamped").value)
        except ValueError as e:
            raise ValueError(f"pose_type: {e}") from None
        if keystore or key_file:
            host.add_key(self.robot, keystore, key_file)

        self.mission: Mission | None = None
        self.index: int | None = None
        self.finished = False
        self.answered = -1  # board version last answered
        self.leg_seq: int | None = None  # number of this robot's legs already taken from the board
        self.pending: list = []  # legs whose departure time has not come yet
        self._goal_at: tuple[float, float] | None = None  # the last goal sent (mission coordinates)
        self._goal_yaw: float | None = None  # its heading
        self.ready = False
        self._unready_since: float | None = None  # monotonic time it has had a mission without being ready
        self._unready_said = -math.inf  # when it last said why
        self.seq = 0
        self._sent: tuple[int, int, float, float] | None = None  # (board version, node, compute ms, monotonic time)
        self._warned: set[str] = set()
        self._fit: dict[str, bool] = {}  # mission session -> whether its rules are this method's (joining)
        self.refusal: str | None = None  # why this robot does not take part (it then stops)
        self._stopping: float | None = None  # lost: since when it is being stopped (_stop_robot)
        self._stop_sent = False  # lost: its stop goal went out
        self.choice_pub = host.choice_publisher(self)
        self.goal_pub = self.create_publisher(PoseStamped, topics.GOAL, topics.GOAL_QOS)
        self._pose = None  # its driver's latest pose, of pose_type (a robot asking to join reports it)
        if self.species_param >= 0:
            self._follow_pose()

    def _follow_pose(self) -> None:
        """Subscribe the robot's pose (``pose`` in its namespace) as the board does: its message
        type and that type's QoS (amcl_pose is latched)."""
        self.create_subscription(POSE_TYPES[self.pose_type], topics.POSE, self._on_pose,
                                 topics.POSE_SUB_QOS_BY_TYPE[self.pose_type])

    def _on_pose(self, msg) -> None:
        self._pose = msg

    def _pose_xy(self, m: Mission) -> tuple[float, float] | None:
        """The robot's last reported position in mission coordinates, or None: no pose yet, a
        malformed one, or one in another frame than the mission's (its coordinates would mean
        another place: warned once)."""
        if self._pose is None:
            return None
        frame = self._pose.header.frame_id
        if frame != m.frame_id:
            self._warn_once(f"pose frame {frame}", f"{self.robot}: its poses are in frame {frame[:64]!r}, not the "
                                                   f"mission's {m.frame_id!r}: not used (the board rejects them too)")
            return None
        try:
            x, y, _ = pose_from_msg(self._pose, m.scale)
        except DecodeError:
            return None
        return x, y

    def position(self) -> tuple[float, float] | None:
        """Where its driver last reported the robot (mission coordinates, clipped to the unit
        square), or None (no pose yet, or not in the mission's frame: the board places it at its
        species' depot)."""
        m = self.host.mission
        xy = None if m is None else self._pose_xy(m)
        if xy is None:
            return None
        return (min(1.0, max(0.0, xy[0])), min(1.0, max(0.0, xy[1])))

    def wants_to_join(self) -> bool:
        """Not in the mission heard, with a species: it asks the board to add it (heartbeat)."""
        m = self.host.mission
        return (self.mission is None and not self.finished and self.species_param >= 0 and m is not None
                and m.index(self.robot) is None and self._fits(m))

    def refused(self, why: str) -> None:
        """The board refused to add this robot (hmrta-rejection/1 ``join_refused``): stop asking."""
        self.refuse(f"{self.robot}: the board refuses to add this robot: {why}; not asking again")

    def refuse(self, text: str, session: str | None = None) -> None:
        """This robot does not take part (``text``: why): log it and stop; the process exits with
        status 2 once its other agents are done. ``session``: the mission this robot is one of,
        whose board is told why before the agent stops (:meth:`Host.report_refusal`)."""
        if self.refusal is None:
            self.refusal = text
            self.get_logger().error(f"{text}; stopping (exit status 2)")
            self.finished = True
            if session is None:
                self.host.agent_finished()
            else:
                self.host.report_refusal(self, session, text)

    def _fits(self, mission: Mission) -> bool:
        """A robot asks to join only a mission whose rules its method runs under: the board would
        add it, and then drop it when its agent refuses to take part (_mismatch)."""
        if mission.session not in self._fit:
            self._fit[mission.session] = self._mismatch(mission) is None
        return self._fit[mission.session]

    # ------------------------------------------------------------------------------------------
    def is_ready(self) -> bool:
        """Ready (and only then reported in the heartbeat, deciding and sending goals) once it has
        the mission and the board and both the board (choices) and the robot's driver (goals) are
        listening, so that nothing it sends is lost."""
        if not self.ready:
            self.ready = self.mission is not None and self.why_not_ready() is None
        return self.ready

    # seconds an agent with a mission may wait for its listeners before it says why, then between repeats
    UNREADY_WARNING = 5.0
    UNREADY_REPEAT = 30.0

    def why_not_ready(self) -> str | None:
        """What this agent, which has a mission, still waits for before it takes part; None when
        nothing (it only reads: ``ready`` is set by :meth:`is_ready`, whose caller then hands the agent
        the board it held back)."""
        if self.ready or self.mission is None:
            return None
        if not self.host.replica.synced:
            return f"the board's state (no keyframe of {self.topics.keyframe} yet)"
        if self.choice_pub.get_subscription_count() == 0:
            return (f"the board's subscription to {self.topics.choice} (is the task board running on this ROS domain, "
                    f"with this mission_namespace?)")
        if self.goal_pub.get_subscription_count() == 0:
            return (f"a subscriber to its goal topic {self.goal_pub.topic_name} (is the robot's driver running, and "
                    f"is the agent's goal_pose remapped to the driver's goal topic?)")
        return None

    def check_waiting(self) -> None:
        """Say (warning) why an agent with a mission is not taking part after UNREADY_WARNING s, and
        again every UNREADY_REPEAT s while that lasts."""
        why = None if self.finished else self.why_not_ready()
        now = time.monotonic()
        if why is None:
            self._unready_since = None
            return
        if self._unready_since is None:
            self._unready_since = now
        elif now - self._unready_since >= self.UNREADY_WARNING and now - self._unready_said >= self.UNREADY_REPEAT:
            self._unready_said = now
            self.get_logger().warning(f"{self.robot}: not taking part yet after {now - self._unready_since:.0f} s: "
                                      f"waiting for {why}")

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def join(self, mission: Mission) -> None:
        """Take part in a (new) mission: find this robot in it. A mission of the same session
        published again (robots were added) only replaces the mission this agent knows. A robot
        not in the mission waits: with a species it asks the board to add it (heartbeat), without
        one it waits until the board adds it (a scenario's add_robot event)."""
        idx = mission.index(self.robot) if self.index_param < 0 else self.index_param
        if (self.mission is not None and mission.session == self.mission.session and idx == self.index
                and idx is not None and idx < len(mission.robots) and mission.robots[idx] == self.robot):
            self.mission = mission  # the same mission, grown: nothing to redo
            return
        if idx is None and self.index_param < 0:
            if self.species_param >= 0 and not self._fits(mission):
                return self.refuse(self._mismatch(mission))
            self._warn_once(f"join {mission.session}",
                            f"robot {self.robot!r} is not in mission {mission.instance.name}: "
                            + (f"asking the board to add it (species {self.species_param})" if self.species_param >= 0
                               else "waiting until the board adds it (start the agent with -p species:=S to join)"))
            return
        if idx is None or not 0 <= idx < mission.instance.n_agents or mission.robots[idx] != self.robot:
            return self.refuse(f"robot {self.robot!r} (index {self.index_param}) is not in mission "
                               f"{mission.instance.name} (robots {', '.join(mission.robots[:5])}...): not taking part")
        mismatch = self._mismatch(mission)
        if mismatch is not None:
            return self.refuse(mismatch, mission.session)
        species = int(mission.instance.agent_species[idx])
        if self.species_param >= 0 and self.species_param != species:
            return self.refuse(f"robot {self.robot!r} is species {self.species_param} but the mission lists it as "
                               f"species {species}: not taking part", mission.session)
        self.mission, self.index = mission, idx
        self.answered, self.leg_seq, self.pending = -1, None, []
        self._goal_at = self._goal_yaw = None
        self.get_logger().info(f"{self.robot}: agent {idx} (species {species}) of mission "
                               f"{mission.instance.name}, method {self.method}")

    def _same_method(self, mission: Mission) -> bool:
        """Whether this agent's own method is the mission's: the same method, and for a method
        that takes a checkpoint the same checkpoint file (by content: a shipped name, a path here
        and the board's path to a copy of it are one network)."""
        try:
            name, theirs = adopt(mission.method, {})
            if name != self.method:
                return False
            if theirs.get("checkpoint") == self.options.get("checkpoint"):  # (named alike: no file read)
                return True
            a, b = checkpoint_of(name, theirs), checkpoint_of(name, self.options)
        except (MethodError, OSError):  # (the board's checkpoint is not a file here)
            return False
        return a is None or a["sha256"] == b["sha256"]

    def _adopt(self, mission: Mission) -> str | None:
        """An agent started with a method that chooses per mission (portfolio): run the mission's
        method (the board's choice, e.g. ``rl@coalition-team``) with this agent's options that it
        takes (its checkpoint); why it cannot, or None."""
        try:
            name, options = adopt(mission.method, self.options)
            self.decide, self.rules = self.host.decider(name, self.seed, options)
        except MethodError as e:
            return (f"{self.robot}: method {self.chooser}: mission {mission.instance.name} runs {mission.method} "
                    f"(the board's choice), which this agent cannot run: {e}; not taking part")
        if self.method != mission.method:
            self.method = mission.method
            self.get_logger().info(f"{self.robot}: method {self.chooser}: running {mission.method}, the board's choice")
        return None

    def _mismatch(self, mission: Mission) -> str | None:
        """Why this robot's method cannot run under the mission's rules, or None (checked once, on
        joining). The board decides ``backdate`` (real-time departures); everything else must match."""
        if self.chooser is not None:
            why = self._adopt(mission)
            if why is not None:
                return why
        elif not self._same_method(mission):
            return (f"{self.robot}: method {live_label(self.method, self.options)} but mission "
                    f"{mission.instance.name} runs {mission.method}: not taking part; start this agent with "
                    f"-p method:=portfolio (the default: it runs the mission's method) or -p method:={mission.method}")
        theirs, mine = mission.rules.to_dict(), self.rules.to_dict()  # the codec requires and checks them
        theirs.pop("backdate", None), mine.pop("backdate", None)
        if theirs == mine:
            return None
        return (f"{self.robot}: method {self.method} runs under rules {mine} but mission {mission.instance.name} "
                f"runs under {theirs} (method {mission.method}): not taking part; start this agent with "
                f"-p method:=portfolio (the default: it runs the mission's method) or the mission's method and "
                f"checkpoint")

    def act(self, board, t_recv: float) -> None:
        """Follow the board (the header of the replica's version): queue this robot's new legs,
        decide when it is its turn."""
        if self.mission is None and board.phase == "done":  # never added: the mission is over
            return self._finish()
        if self.mission is None or self.finished or board.session != self.mission.session:
            return
        a = self.index
        if a in board.lost:  # also while it waits for its listeners: the board has given up on it
            return self._stop_robot()
        if not self.is_ready():
            if board.phase == "done":  # the mission ended while it waited: it ends too
                self.get_logger().warning(f"{self.robot}: the mission ended before this agent took part "
                                          f"(it waited for {self.why_not_ready()})")
                return self._finish()
            return
        entry = self.host.replica.legs(a, self.leg_seq)
        if entry is not None:
            self._take_legs(*entry)
        if board.phase == "done":
            return self._finish()
        if board.phase == "decide" and board.decider == a and board.version != self.answered:
            self.answered = board.version
            self._decide(board.version, t_recv)

    def _take_legs(self, seq: int, legs: tuple) -> None:
        """Queue this robot's legs that are new since the last board (all of them in order)."""
        if self.leg_seq is None:  # first board seen (start or restart): from the leg driven now on
            # (its driver gets the current goal again, and the legs that came due while this process
            # was down; without them an arrival the board waits for would never happen)
            due = [i for i, g in enumerate(legs) if g[0] != RESEND and g[3] <= self.host.clock + EPS]
            self.leg_seq = seq - len(legs) + (due[-1] if due else 0)
        first = seq - len(legs) + 1
        new = [g for i, g in enumerate(legs) if first + i > self.leg_seq]
        if new:
            self.leg_seq = seq
            self.pending += [g for g in new if g[0] != RESEND]
            self.flush_goals()
            if self.pending:
                self.host.waiting[id(self)] = self
            m = self.mission
            for node, x, y, depart in new:  # a goal the robot has not reached in time: published again now
                if node == RESEND and not self.finished:
                    self._send_goal(x, y, depart)
                    self.get_logger().warning(f"{self.robot}: the board re-sends the goal ({x * m.scale:.2f}, "
                                              f"{y * m.scale:.2f}) m "
                                              f"(departed t={depart:.3f}): the robot has not arrived in time")

    def flush_goals(self) -> None:
        """Publish the queued legs whose departure time the mission clock has reached."""
        m = self.mission
        while self.pending and self.pending[0][3] <= self.host.clock + EPS:
            if self.finished:
                return
            node, x, y, depart = self.pending.pop(0)
            self._send_goal(x, y, depart)
            self.get_logger().debug(f"goal node {node} at ({x * m.scale:.2f}, {y * m.scale:.2f}) m, departing "
                                    f"t={depart:.3f}")

    def _send_goal(self, x: float, y: float, depart: float) -> None:
        """Publish the goal (x, y) (mission coordinates), headed along the leg that reaches it:
        from the previous goal (the robot's pose, or its depot, before the first), so that a
        navigation stack does not turn the robot to a fixed heading at every goal. A goal at the
        same place as the previous one (sent again) keeps its heading."""
        m = self.mission
        start = self._goal_at or self._pose_xy(m)
        if start is None and self.index is not None:
            start = tuple(float(v) for v in m.instance.depots[self.index])
        if start is not None and math.hypot(x - start[0], y - start[1]) > 1e-9:
            self._goal_yaw = math.atan2(y - start[1], x - start[0])
        self._goal_at = (x, y)
        self.goal_pub.publish(pose_to_msg((x, y), depart, m.frame_id, m.scale, self._goal_yaw))

    def _decide(self, version: int, t_recv: float) -> None:
        state = self.host.replica.state  # shared by the agents of the process: deciders only read it
        if state.agent != self.index:
            self.get_logger().error(f"board {version} names agent {self.index} but its state's decider is "
                                    f"{state.agent}: not answering")
            return
        node = int(self.decide(state))
        ms = (time.perf_counter() - t_recv) * 1e3
        self._send(version, node, round(ms, 3))
        self.get_logger().debug(f"board {version}: chose node {node} ({ms:.1f} ms)")

    def _send(self, version: int, node: int, ms: float) -> None:
        self.seq += 1
        self.choice_pub.publish(choice_to_msg(Choice(self.robot, self.mission.session, version, node, self.seq, ms),
                                              self.host.signer))
        self._sent = (version, node, ms, time.monotonic())

    def resend(self, board) -> None:
        """Send the last choice again when the board still waits for it after RESEND_AFTER s."""
        sent = self._sent
        if (sent is None or self.finished or board.phase != "decide" or board.decider != self.index
                or board.version != sent[0] or time.monotonic() - sent[3] < RESEND_AFTER):
            return
        self.get_logger().warning(f"{self.robot}: board {sent[0]} still waits for this robot's choice after "
                                  f"{RESEND_AFTER:g} s: sending it again", throttle_duration_sec=10.0)
        self._send(sent[0], sent[1], sent[2])

    # seconds to wait for the robot's pose before giving up on stopping it, and for the stop goal to go out
    STOP_POSE_WAIT, STOP_SEND_WAIT = 3.0, 0.5

    def _stop_robot(self) -> None:
        """The board declared this robot lost: it stops where it is, so its driver gets a goal at
        its own latest pose (departing now) in place of the goal it may still be driving to; then
        the agent ends. With no pose heard within STOP_POSE_WAIT s it ends without one (logged)."""
        if self.finished or self._stopping is not None:
            return
        self._stopping = time.monotonic()
        self.pending = []  # no queued leg goes out after the stop
        if self._pose is None and self.species_param < 0:  # not yet following its pose: from now on
            self._follow_pose()
        self._stop_timer = self.create_timer(0.1, self._try_stop)
        self._try_stop()

    def _try_stop(self) -> None:
        m, waited = self.mission, time.monotonic() - self._stopping
        if self._pose is not None and not self._stop_sent:
            xy = self._pose_xy(m)  # (never a pose of another frame: another place)
            if xy is not None:  # where it is, heading as it is (not turned to a fixed heading)
                x, y = xy
                self.goal_pub.publish(pose_to_msg((x, y), self.host.clock, m.frame_id, m.scale,
                                                  yaw_from_msg(self._pose)))
                self._stop_sent, self._stopping = True, time.monotonic()  # then a moment for it to go out
                self.get_logger().warning(f"{self.robot}: the board declared this robot lost: goal set to where it "
                                          f"is ({x * m.scale:.2f}, {y * m.scale:.2f}) m to stop it; stopping")
                return
        if self._stop_sent:
            if waited < self.STOP_SEND_WAIT:
                return
        elif waited < self.STOP_POSE_WAIT:
            return
        else:
            self.get_logger().warning(f"{self.robot}: the board declared this robot lost; no pose in frame "
                                      f"{m.frame_id!r} heard from it within {self.STOP_POSE_WAIT:g} s, so it was not "
                                      f"sent a stop (it may still drive to its last goal); stopping")
        self._stop_timer.cancel()
        self._finish()

    def _finish(self) -> None:
        if not self.finished and self.exit_on_done:
            self.finished = True
            self.host.agent_finished()


def robots_arg(text: str) -> list[str]:
    names = [r.strip().strip("/") for r in text.split(",")]
    if not all(names) or len(set(names)) != len(names):  # (an empty name between commas too)
        raise argparse.ArgumentTypeError(f"expected distinct comma-separated robot names, got {text!r}")
    return names


def _set_torch_threads(n: int) -> None:
    """Set torch's threads if a method loaded torch (a greedy agent never imports it: a restarted
    agent process must be back before its heartbeat times out)."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)


def _mission_namespace(argv: list[str]) -> str:
    """The ``mission_namespace`` given on the command line (``--ros-args -p mission_namespace:=NS``),
    before the robots' nodes are made: their namespaces are under it. Read from the arguments, not
    from a node, so that no extra node comes and goes; each node then checks the value it gets
    (a parameter file may say otherwise)."""
    ros = argv[argv.index("--ros-args") + 1:] if "--ros-args" in argv else []
    ns = "/"
    for flag, value in zip(ros, ros[1:]):
        if flag in ("-p", "--param") and value.startswith("mission_namespace:="):
            ns = value.split(":=", 1)[1]
    try:  # a YAML value, as ROS reads it ("/f1" quoted or not)
        import yaml

        parsed = yaml.safe_load(ns)
        ns = parsed if isinstance(parsed, str) else ns
    except yaml.YAMLError:
        pass
    return topics.check_mission_namespace(ns)


def main(args: list[str] | None = None) -> int:
    """Exit status: 0, 2 a user error or an agent that refused to take part, 130 Ctrl-C at start-up."""
    argv = sys.argv if args is None else args
    from hmrta_msgs_py.params import node_parameters
    from hmrta_msgs_py.runtime import check_period, parameters_help, without_ros_args

    from hmrta.cli import Parser  # a bad command line: one line naming the flag (exit 2), like every user error
    from hmrta.cli.common import UserError
    from hmrta.cli.threads import check_threads

    p = Parser(prog="agent_node", description=__doc__.split("\n\n")[0],
               usage="agent_node [-h] [--robots ROBOTS] [--heartbeat-period S] [--torch-threads N] "
                     "[--ignore-board-version V] [--ros-args -p NAME:=VALUE ... -r FROM:=TO ...]",
               formatter_class=argparse.RawDescriptionHelpFormatter,
               epilog="ROS parameters (--ros-args -p NAME:=VALUE):\n" + parameters_help(node_parameters("agent_node")))
    p.add_argument("--robots", type=robots_arg, default=None,
                   help="host several robots in this process (node <mission_namespace>/<robot>/agent each); default: one "
                        "robot named by -p robot:=NAME or by the namespace")
    p.add_argument("--heartbeat-period", type=float, default=0.5, metavar="S",
                   help="seconds between status messages (default 0.5)")
    p.add_argument("--torch-threads", type=int, default=1, metavar="N",
                   help="intra-op threads of the learned policy (decisions are small batches: one thread is "
                        "fastest, and several agent processes on one machine must not oversubscribe its cores; default 1)")
    p.add_argument("--ignore-board-version", type=int, action="append", default=[], metavar="V",
                   help="testing: drop the board messages of version V once, as if they were lost (the process's "
                        "replica recovers from a keyframe); repeatable")
    cli = p.parse_args(without_ros_args("agent_node", argv)[1:])
    try:
        check_threads("--torch-threads", cli.torch_threads)
        check_period("--heartbeat-period", cli.heartbeat_period)
    except (UserError, ValueError) as e:
        p.error(str(e))
    host = Host()
    host.torch_threads = cli.torch_threads
    host.ignore.update(cli.ignore_board_version)
    with starting("agent_node", (MethodError, ValueError), args=argv):  # bad policy / checkpoint: a user error
        if cli.robots:
            lean = LEAN_NODE if len(cli.robots) > 1 else {}
            nodes = []
            ns = _mission_namespace(argv)
            for r in cli.robots:
                own = topics.robot_namespace(r, ns)
                nodes.append(AgentNode(host, namespace=own, parameter_overrides=[Parameter("robot", value=r)],
                                       **lean))
                if nodes[-1].topics.namespace != ns:
                    raise ValueError(f"--robots: mission_namespace {nodes[-1].topics.namespace} does not match the "
                                     f"command line's ({ns}): give it as --ros-args -p mission_namespace:=NS")
                if nodes[-1].get_namespace() != own:  # a global -r __ns:= puts every robot's node there
                    raise ValueError(f"--robots: each robot's agent runs in its own namespace ({own}/agent), but "
                                     f"-r __ns:= moved it to {nodes[-1].get_namespace()}; leave __ns out with --robots "
                                     f"(one agent per process takes -r __ns:={own})")
        else:
            nodes = [AgentNode(host)]
        _set_torch_threads(cli.torch_threads)  # the deciders are built: torch is loaded if they use it
        host.attach(nodes[0], cli.heartbeat_period)
    spin_nodes(nodes, until=host.all_done, exit_status=host.exit_status)
    return host.exit_status()


if __name__ == "__main__":
    sys.exit(main())
