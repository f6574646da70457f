"""Rules travel with the mission: an agent checks once, on joining, that its method runs under the
mission's rules, and refuses loudly otherwise (real rclpy node, its own domain)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from rclpy.parameter import Parameter

from hmrta.baselines import GREEDY_RULES, RANDOM_RULES
from hmrta.formats import load_instance
from hmrta_agent.agent_node import AgentNode, Host
from hmrta_msgs_py.codec import Mission, mission_from_msg, mission_to_msg

EXAMPLE = Path(__file__).resolve().parents[2] / "policy" / "hmrta" / "data" / "example.yaml"


def _agent(graph, method: str) -> AgentNode:
    node = AgentNode(Host(), context=graph.context, namespace="/robot_0", start_parameter_services=False,
                     parameter_overrides=[Parameter("robot", value="robot_0"), Parameter("method", value=method)])
    graph.nodes.append(node)
    return node


def _mission(rules) -> Mission:
    inst = load_instance(EXAMPLE)
    m = Mission("s1", inst, tuple(f"robot_{a}" for a in range(inst.n_agents)), 0, "greedy", rules=rules)
    return mission_from_msg(mission_to_msg(m))  # as received over the wire


def test_agent_joins_a_mission_under_its_rules_and_refuses_other_rules(graph):
    greedy = _agent(graph, "greedy")
    greedy.join(_mission(GREEDY_RULES))
    assert greedy.mission is not None and greedy.index == 0
    # the board's real-time departures (backdate off) are its own call, not a mismatch
    greedy.join(_mission(dataclasses.replace(GREEDY_RULES, backdate=False)))
    assert greedy.mission is not None

    rand = _agent(graph, "random")  # runs under the unrestricted rules
    assert rand.rules == RANDOM_RULES != GREEDY_RULES
    rand.join(_mission(GREEDY_RULES))
    assert rand.mission is None and rand.index is None  # refused: not taking part


def test_an_agent_started_with_portfolio_runs_the_method_its_board_chose(graph):
    """method:=portfolio on an agent: it has no decider of its own until the mission names the
    board's choice, then runs that (its own checkpoint option applies; a candidate's own, as in
    rl@broad, wins) under that method's rules; a mission whose method it cannot run is refused."""
    from hmrta.methods import rules as method_rules

    def mission(method: str, rules) -> Mission:
        return mission_from_msg(mission_to_msg(dataclasses.replace(_mission(rules), method=method)))

    agent = _agent(graph, "portfolio")
    assert agent.decide is None and agent.chooser == "portfolio"
    agent.join(mission("greedy-coalition", method_rules("greedy-coalition")))
    assert agent.mission is not None and agent.method == "greedy-coalition" and agent.refusal is None
    assert agent.rules == method_rules("greedy-coalition") and agent.decide is not None

    ck = _agent(graph, "portfolio")
    ck.join(mission("rl@broad", method_rules("rl", checkpoint="broad")))
    assert ck.mission is not None and ck.method == "rl@broad" and ck.rules == method_rules("rl", checkpoint="broad")

    other = _agent(graph, "portfolio")
    other.join(mission("cpsat", GREEDY_RULES))  # offline only: no per-decision form
    assert other.mission is None and "cpsat" in other.refusal and "per-decision" in other.refusal


def test_an_agent_with_its_own_method_refuses_a_mission_of_another_method_under_the_same_rules(graph):
    """greedy-coalition runs under the rules of rl with the coalition-team checkpoint: the rules
    check let such an agent run greedy-coalition in an rl@coalition-team mission, unnoticed (the
    result named rl@coalition-team). The agent compares the method and its checkpoint file too."""
    from hmrta.methods import rules as method_rules

    team = method_rules("rl", checkpoint="coalition-team")
    assert method_rules("greedy-coalition") == team  # (what let it through)

    def mission(method: str) -> Mission:
        return mission_from_msg(mission_to_msg(dataclasses.replace(_mission(team), method=method)))

    gc = _agent(graph, "greedy-coalition")
    gc.join(mission("rl@coalition-team"))
    assert gc.mission is None and "runs rl@coalition-team" in gc.refusal and "method:=portfolio" in gc.refusal
    same = _agent(graph, "greedy-coalition")
    same.join(mission("greedy-coalition"))
    assert same.mission is not None and same.refusal is None
    from hmrta.rl.checkpoint_info import checkpoint_path

    by_path = _agent(graph, "rl@coalition-team")  # the board names it by path: the same file
    by_path.join(mission(f"rl@{checkpoint_path('coalition-team')}"))
    assert by_path.mission is not None and by_path.refusal is None
