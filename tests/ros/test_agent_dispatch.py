"""The agents' host hands each board version only to the agents it concerns (the decider, the
robots given legs, the agents not yet settled). Checked against walking every agent on every
version, over the board's own missions (tests/policy/test_board.py's drivers): every agent gets
every leg of its robot on the version that gives it, and every decider is asked, exactly as with
the full walk; the process publishes every choice through one writer."""
from __future__ import annotations

import sys
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
