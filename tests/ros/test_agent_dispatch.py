"""The agents' host hands each board version only to the agents it concerns (the decider, the
robots given legs, the agents not yet settled). Checked against walking every agent on every
version, over the board's own missions (tests/policy/test_board.py's drivers): every agent gets
every leg of its robot on the version that gives it, and every decider is asked, exactly as with
the full walk; the process publishes every choice through one writer."""
from __future__ import annotations

import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "policy"))
import test_board as tb  # noqa: E402  (the board's test drivers)
from hmrta_agent.agent_node import Host  # noqa: E402


class FakeAgent:
    """What Host.dispatch reads of an agent, and an act() that takes its robot's new legs."""

    def __init__(self, host: Host, index: int | None, ready: bool = True):
        self.host, self.index, self.ready, self.finished = host, index, ready, False
        self.leg_seq: int | None = None
        self.seen: list[tuple] = []
        host.agents.append(self)

    def act(self, head, t_recv: float) -> None:
        if self.index is None or not self.ready:
            return
        st = self.host.replica.state
        if self.index in head.lost or self.index >= st.A:
            return
        seq = st.leg_seq(self.index)
        if seq != self.leg_seq:
            self.seen.append((head.version, "legs", seq))
            self.leg_seq = seq
        if head.phase == "decide" and head.decider == self.index:
            self.seen.append((head.version, "decide"))
        if head.phase == "done":
            self.finished = True


def play(stuck: bool, drive_kw: dict, walk_all: bool, monkeypatch) -> tuple[list[list[tuple]], int]:
    """What each agent saw (legs, turns to decide), and how many times an agent was looked at."""
    looked = [0]
    settled = Host._settled

    def counted(*args):
        looked[0] += 1
        return settled(*args)

    monkeypatch.setattr(Host, "_settled", staticmethod(counted))
    b = tb.stuck_board()[0] if stuck else tb.started_board()
    host = Host()
    host.replica = tb.replica_of(b)
    host.mission = SimpleNamespace(session=b.session)
    agents = [FakeAgent(host, a) for a in range(b.inst.n_agents)] + [FakeAgent(host, None)]
    pump = tb.pump

    def pump_and_dispatch(board):
        v = pump(board)
        if walk_all:
            host._walked = ()  # the former behaviour: every agent on every version
        if host.replica.current:
            host.dispatch()
        return v

    tb.pump = pump_and_dispatch
    try:
        tb.drive(b, **drive_kw)
    finally:
        tb.pump = pump
    assert b.finished
    monkeypatch.setattr(Host, "_settled", staticmethod(settled))
    return [a.seen for a in agents], looked[0]


@pytest.mark.parametrize("case", ["plain", "stuck robot: goal re-sent, then lost"])
def test_dispatch_reaches_the_same_agents_as_walking_all_of_them(case, monkeypatch):
    stuck = case != "plain"
    kw = {"tick": 0.1, "where": lambda a, xy: tuple(tb.INST.depots[a]) if a == 0 else xy} if stuck else {}
    (fast, looked), (full, looked_all) = (play(stuck, kw, False, monkeypatch), play(stuck, kw, True, monkeypatch))
    assert fast == full
    # fewer agents looked at: 34% and 21% of the full walk's here (6 robots; hundreds in a fleet). A
    # walk of every agent whenever the phase changes (not only at the end) looked at 69% and 27%.
    assert looked < 0.5 * looked_all
    assert sum(e[1] == "decide" for seen in fast for e in seen) > 10 and all(fast[:-1])


def test_the_agents_of_one_process_share_one_choice_writer(graph):
    """Real rclpy nodes: three agents hosted in one process publish their choices through one
    publisher (each choice names and signs its robot), which a subscriber sees as one writer."""
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from hmrta_agent.agent_node import AgentNode
    from hmrta_msgs_py import topics

    host = Host()
    agents = [AgentNode(host, context=graph.context, namespace=f"/robot_{a}", start_parameter_services=False,
                        parameter_overrides=[Parameter("robot", value=f"robot_{a}")]) for a in range(3)]
    graph.nodes.extend(agents)
    assert agents[0].choice_pub is agents[1].choice_pub is agents[2].choice_pub
    listener = graph.node("choice_listener")
    sub = listener.create_subscription(String, topics.CHOICE, lambda m: None, topics.CHOICE_QOS)
    graph.spin_until(lambda: sub.get_publisher_count() >= 1, 10, "the agents' choice writer")
    assert listener.count_publishers(topics.CHOICE) == 1


def test_a_goal_waits_for_its_departure_and_the_clock_sends_only_the_goals_due(graph):
    """Real rclpy nodes: a robot's leg departing later is published when the mission clock
    reaches its departure, not before; the clock looks only at the agents holding such legs."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.parameter import Parameter

    from hmrta_agent.agent_node import AgentNode
    from hmrta_msgs_py import topics
    from hmrta_msgs_py.codec import clock_to_msg, pose_from_msg

    host = Host()
    agents = [AgentNode(host, context=graph.context, namespace=f"/robot_{a}", start_parameter_services=False,
                        parameter_overrides=[Parameter("robot", value=f"robot_{a}")]) for a in range(3)]
    graph.nodes.extend(agents)
    listener = graph.node("goal_listener")
    got: dict[str, list[tuple[float, float, float]]] = {a.robot: [] for a in agents}
    for a in agents:
        listener.create_subscription(PoseStamped, f"/{a.robot}/{topics.GOAL}",
                                     lambda m, r=a.robot: got[r].append(pose_from_msg(m)), topics.GOAL_QOS)
        a.mission = SimpleNamespace(frame_id="map", scale=1.0)
        a.leg_seq = 0
    graph.spin_until(lambda: all(a.goal_pub.get_subscription_count() >= 1 for a in agents), 10, "the goal listener")

    agents[0]._take_legs(2, ((1, 0.1, 0.2, 0.0), (2, 0.3, 0.4, 5.0)))  # one leg now, one departing at t=5
    agents[1]._take_legs(1, ((1, 0.5, 0.6, 0.0),))
    assert list(host.waiting.values()) == [agents[0]] and len(agents[0].pending) == 1
    host._new_horizon("s1", 10.0)  # a board header: the clock may run up to t=10
    host._on_clock(clock_to_msg(4.0))
    graph.spin_until(lambda: len(got["robot_0"]) >= 1 and len(got["robot_1"]) >= 1, 10, "the goals due at t=0")
    assert got["robot_0"] == [pytest.approx((0.1, 0.2, 0.0))] and agents[0].pending
    host._on_clock(clock_to_msg(5.0))
    graph.spin_until(lambda: len(got["robot_0"]) >= 2, 10, "the goal departing at t=5")
    assert got["robot_0"][1] == pytest.approx((0.3, 0.4, 5.0)) and not agents[0].pending and not host.waiting
    quiet = time.monotonic() + 0.5  # anything else published would have arrived by now
    while time.monotonic() < quiet:
        graph.executor.spin_once(timeout_sec=0.05)
    assert got["robot_1"] == [pytest.approx((0.5, 0.6, 0.0))] and got["robot_2"] == []


def test_the_clock_is_followed_only_up_to_the_boards_horizon(graph):
    """A clock past the board's horizon (a stray publisher on the clock topic) is followed only up
    to the horizon, and further as later horizons allow, as the board does; a clock heard before
    the header that allows it (the two come from different publishers) is caught up with; a clock
    within the horizon is followed as it comes and forgets the stray value."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.parameter import Parameter

    from hmrta_agent.agent_node import AgentNode
    from hmrta_msgs_py import topics
    from hmrta_msgs_py.codec import clock_to_msg, pose_from_msg

    host = Host()
    agent = AgentNode(host, context=graph.context, namespace="/robot_0", start_parameter_services=False,
                      parameter_overrides=[Parameter("robot", value="robot_0")])
    graph.nodes.append(agent)
    listener = graph.node("goal_listener")
    got: list[tuple[float, float, float]] = []
    listener.create_subscription(PoseStamped, f"/robot_0/{topics.GOAL}", lambda m: got.append(pose_from_msg(m)),
                                 topics.GOAL_QOS)
    agent.mission = SimpleNamespace(frame_id="map", scale=1.0)
    agent.leg_seq = 0
    graph.spin_until(lambda: agent.goal_pub.get_subscription_count() >= 1, 10, "the goal listener")

    def settle() -> None:
        quiet = time.monotonic() + 0.3
        while time.monotonic() < quiet:
            graph.executor.spin_once(timeout_sec=0.05)

    host._new_horizon("s1", 3.0)
    agent._take_legs(3, ((1, 0.1, 0.1, 5.0), (2, 0.2, 0.2, 9.0), (3, 0.3, 0.3, 11.5)))
    host._on_clock(clock_to_msg(100000.0))  # stray: held at the horizon
    assert host.clock == 3.0 and len(agent.pending) == 3
    host._new_horizon("s1", 6.0)  # the next horizon: up to it, not beyond
    assert host.clock == 6.0 and len(agent.pending) == 2
    host._on_clock(clock_to_msg(6.0))  # the simulated robots' clock: the stray value is forgotten
    host._new_horizon("s1", 10.0)
    assert host.clock == 6.0 and len(agent.pending) == 2
    host._on_clock(clock_to_msg(12.0))  # the robots' clock heard before the header that allows it
    assert host.clock == 10.0 and len(agent.pending) == 1
    host._new_horizon("s1", 13.0)
    assert host.clock == 12.0 and not agent.pending
    host._new_horizon("s2", 1.0)  # a new session starts its horizons and its clock again
    assert host.horizon == 1.0 and host.clock == 0.0
    graph.spin_until(lambda: len(got) >= 3, 10, "the three goals")
    settle()
    assert [g[2] for g in got] == [5.0, 9.0, 11.5]


def test_the_waiting_check_names_what_is_missing_and_never_marks_an_agent_ready(graph):
    """check_waiting (a 1 Hz timer) only reads: were it to set ``ready``, the heartbeat would not see
    the agent become ready and would not hand it the board it held back (a decider would miss its
    turn)."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from hmrta_agent.agent_node import AgentNode
    from hmrta_msgs_py import topics

    host = Host()
    a = AgentNode(host, context=graph.context, namespace="/robot_0", start_parameter_services=False,
                  parameter_overrides=[Parameter("robot", value="robot_0")])
    graph.nodes.append(a)
    a.mission = SimpleNamespace(frame_id="map", scale=1.0, session="s")
    host.replica = SimpleNamespace(synced=True)
    listener = graph.node("listener")
    listener.create_subscription(String, topics.CHOICE, lambda m: None, topics.CHOICE_QOS)
    graph.spin_until(lambda: a.choice_pub.get_subscription_count() >= 1, 10, "the choice listener")
    assert "a subscriber to its goal topic /robot_0/goal_pose" in a.why_not_ready()
    listener.create_subscription(PoseStamped, "/robot_0/goal_pose", lambda m: None, topics.GOAL_QOS)
    graph.spin_until(lambda: a.goal_pub.get_subscription_count() >= 1, 10, "the goal listener")
    a.check_waiting()
    assert a.why_not_ready() is None and not a.ready  # left to is_ready(), the heartbeat's
    assert a.is_ready() and a.ready
