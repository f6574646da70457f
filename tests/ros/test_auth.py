"""Authenticated robots (hmrta.keys) over real DDS: signed choices and heartbeats, the board
rejecting unsigned, forged and replayed choices, and the live mission still equal to the offline
rollout; bad keys are user errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections import Counter

import pytest

from conftest import save_instance
from hmrta import keys as K
from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.core import MissionState
from hmrta.generators import ScenarioGenerator

rclpy = pytest.importorskip("rclpy")
from geometry_msgs.msg import PoseStamped  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from hmrta_msgs_py import topics  # noqa: E402
from hmrta_msgs_py import codec as C  # noqa: E402
from test_mission import BoardWatch, assert_same_as_offline, robots_of, wait_board_exit  # noqa: E402


# ---------------------------------------------------------------------------------------------
# codec: signing and what the board's verifier sees
# ---------------------------------------------------------------------------------------------
def test_signed_codec_round_trip_and_verification():
    keys = {"robot_0": bytes(range(32)), "robot_1": bytes(32)}
    signer, verifier = K.Signer({"robot_0": keys["robot_0"]}), K.Verifier(keys)
    msg = C.choice_to_msg(C.Choice("robot_0", "s1", 7, 3, seq=2, compute_ms=0.5), signer)
    c = C.choice_from_msg(msg)
    assert c == C.Choice("robot_0", "s1", 7, 3, seq=2, compute_ms=0.5)  # the signature is no part of the choice
    assert verifier.verify(c.payload) is None
    assert K.rejection_code(verifier.verify(C.choice_from_msg(msg).payload)) == "replayed"
    tampered = json.loads(msg.data)
    tampered["node"] = 4
    reason = verifier.verify(C.choice_from_msg(String(data=json.dumps(tampered))).payload)
    assert K.rejection_code(reason) == "forged"
    unsigned = C.choice_from_msg(C.choice_to_msg(C.Choice("robot_1", "s1", 7, 3)))
    assert K.rejection_code(verifier.verify(unsigned.payload)) == "unsigned"
    # statuses: one MAC per robot listed; a process can sign only for the robots whose keys it holds
    s = C.status_from_msg(C.status_to_msg(C.Status(("robot_0", "robot_1"), "s1", 1), K.Signer(keys)))
    assert verifier.verify(s.payload) is None and set(s.payload["mac"]) == {"robot_0", "robot_1"}
    with pytest.raises(KeyError):
        C.status_to_msg(C.Status(("robot_0", "robot_1"), "s1", 1), signer)
    # malformed signature fields are malformed messages
    for bad in ({"counter": "12"}, {"counter": -1}, {"mac": "ab"}, {"counter": True}):
        d = {**json.loads(msg.data), **bad}
        with pytest.raises(C.DecodeError):
            C.choice_from_msg(String(data=json.dumps(d)))


def test_missing_or_foreign_keys_are_user_errors(tmp_path, domain):
    ks = tmp_path / "keys"
    K.create_keystore(ks, ["robot_0", "robot_1"])
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOG_DIR": str(tmp_path / "ros")}
    inst = save_instance(ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(7, 0), tmp_path / "inst.yaml")
    cases = [
        (["hmrta_agent.agent_node", "--robots", "robot_5", "--ros-args", "-p", f"keystore:={ks}"], "no key for robot_5"),
        (["hmrta_agent.agent_node", "--robots", "robot_1", "--ros-args", "-p",
          f"key_file:={ks / 'robots' / 'robot_0.key.json'}"], "the key of 'robot_0', not of 'robot_1'"),
        (["hmrta_coordinator.task_board", "--ros-args", "-p", f"instance:={inst}", "-p", f"keystore:={ks}"],
         "no key for robot_2"),
        (["hmrta_coordinator.mission", str(inst), "--method", "greedy", "--keystore", str(ks), "--out",
          str(tmp_path / "m.json")],
         "no key for robot_2"),
    ]
    for args, text in cases:
        p = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=60, env=env)
        assert p.returncode == 2 and text in p.stderr and "Traceback" not in p.stderr, (args, p.stderr)
        assert len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_a_robot_a_scenario_adds_has_its_key_in_an_authenticated_mission(tmp_path, domain):
    """``hmrta-mission --authenticate`` on a scenario that adds a robot: the keystore holds the
    added robot's key too (and ``hmrta keys create --instance`` of the scenario), the board takes
    it, the added robot's choices count (it takes the task only it completes), and the live
    mission equals the offline rollout."""
    mission = tmp_path / "two.yaml"
    mission.write_text(json.dumps({
        "format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2, "skills": 2,
        "species": [{"traits": [1, 0], "count": 2, "depot": [0.0, 0.0]}, {"traits": [0, 1], "count": 2, "depot": [1.0, 1.0]}],
        "tasks": [{"location": [0.5, 0.1], "requirements": [1, 0], "duration": 2},
                  {"location": [0.2, 0.8], "requirements": [1, 1], "duration": 3}]}))
    scen = tmp_path / "scen.yaml"
    scen.write_text(json.dumps({"format": "hmrta-scenario/1", "instance": str(mission), "events": [
        {"t": 0.5, "type": "add_robot", "species": 0},
        {"t": 1.0, "type": "add_task", "id": "big", "location": [0.3, 0.3], "requirements": [3, 0], "duration": 1}]}))
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOG_DIR": str(tmp_path / "ros")}
    from hmrta.cli import main

    assert main(["keys", "create", "--instance", str(scen), "--out", str(tmp_path / "ks")]) == 0
    assert sorted(K.load_keystore(tmp_path / "ks")) == [f"robot_{a}" for a in range(5)]
    out = tmp_path / "m.json"
    p = subprocess.run([sys.executable, "-m", "hmrta_coordinator.mission", "--scenario", str(scen), "--method",
                        "greedy", "--authenticate", "--out", str(out), "--no-plot", "--quiet", "--check-offline",
                        "--timeout", "120"], capture_output=True, text=True, timeout=200, env=env)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "same routes and makespan: yes" in p.stdout, p.stdout
    sol = json.loads(out.read_text())
    assert sol["success"] and sol["routes"][4] == [2], sol["routes"]  # the added robot did the added task


# ---------------------------------------------------------------------------------------------
# a live mission with a keystore: forged, unsigned and replayed choices change nothing
# ---------------------------------------------------------------------------------------------
def test_forged_unsigned_and_replayed_choices_are_rejected_and_the_mission_equals_offline(
        tmp_path, graph, mission_procs):
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(7, 0)
    robots = robots_of(inst)
    seed = 2
    ks = tmp_path / "keys"
    keys = K.create_keystore(ks, robots)
    d = MissionState(inst, seed=seed, rules=GREEDY_RULES).agent  # the first decider: played by this test
    me = robots[d]
    other = robots[(d + 1) % len(robots)]  # the attacker holds this robot's key
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots, seed=seed, no_agent=[me],
                          keystore=ks,
                          board_params={"heartbeat_timeout": 0.0, "decision_timeout": 0.0, "progress_period": 0.0})
    node = graph.node("attacker")
    watch = BoardWatch(node)
    missions: list[C.Mission] = []
    rejections: list[C.Rejection] = []
    recorded: list[String] = []  # choices of the robots' agents, as sent
    sent: set[str] = set()  # this test's own choices
    node.create_subscription(String, topics.MISSION, lambda m: missions.append(C.mission_from_msg(m)),
                             topics.MISSION_QOS)
    node.create_subscription(String, topics.REJECTIONS, lambda m: rejections.append(C.rejection_from_msg(m)),
                             topics.REJECTION_QOS)
    record = node.create_subscription(String, topics.CHOICE,
                                      lambda m: recorded.append(m) if m.data not in sent else None,
                                      topics.CHOICE_QOS)
    choice = node.create_publisher(String, topics.CHOICE, topics.CHOICE_QOS)
    status = node.create_publisher(String, topics.STATUS, topics.STATUS_QOS)
    goal = node.create_publisher(PoseStamped, topics.robot_topic(me, topics.GOAL), topics.GOAL_QOS)
    graph.spin_until(lambda: missions, 60, "the mission")
    session = missions[0].session
    mine = K.Signer({me: keys[me]})  # the legitimate robot's key
    graph.spin_until(lambda: status.get_subscription_count() > 0, 30, "the board to listen to heartbeats")
    status.publish(C.status_to_msg(C.Status((me,), session, 0)))  # an unsigned heartbeat keeps nobody alive: the mission cannot start on it
    time.sleep(0.5)
    beat = node.create_timer(0.3, lambda: status.publish(C.status_to_msg(C.Status((me,), session, 0), mine)))
    graph.spin_until(lambda: watch.board and watch.board.phase == "decide" and watch.board.decider == d, 90,
                     f"{me}'s turn")
    graph.spin_until(lambda: choice.get_subscription_count() > 0 and goal.get_subscription_count() > 0, 30,
                     "the board and the simulated robot to listen")
    # the other robots choose right after my choice; a choice sent before this test hears its sender
    # is lost to the test (volatile topic), so wait for every agent's publisher (and my own)
    graph.spin_until(lambda: record.get_publisher_count() >= len(procs.agents) + 1, 30,
                     "this test to hear every agent's choice publisher")
    v, text = watch.board.version, watch.msg.data
    seq0 = watch.board.legs[d][0]
    state = MissionState.from_snapshot(inst, watch.board.state)
    good = Greedy()(state)
    admissible = [n for n, ok in enumerate(state.mask()) if ok]
    bad = next((n for n in admissible if n != good), good)  # would change the plan if it were applied

    # the attack: right session and version, an admissible node, in the decider's name
    base = json.loads(C.choice_to_msg(C.Choice(me, session, v, bad)).data)
    own = K.Signer({me: keys[other], other: keys[other]}).sign(base, robots=[me, other])  # every MAC by my key
    tampered = json.loads(C.choice_to_msg(C.Choice(me, session, v, bad), mine).data)
    tampered["robot"] = other  # the decider's valid signature under another robot's name
    forged = [
        C.choice_to_msg(C.Choice(me, session, v, bad)),  # unsigned
        String(data=json.dumps(K.Signer({me: keys[other]}).sign(base))),  # signed with another robot's key
        String(data=json.dumps(own)),  # plus the sender's own valid MAC
        String(data=json.dumps(tampered)),
    ]
    sent.update(m.data for m in forged)
    for m in forged:
        choice.publish(m)
    graph.spin_until(lambda: len(rejections) >= len(forged), 30, "every forged choice to be rejected")
    assert [r.reason for r in rejections] == ["unsigned", "forged", "forged", "unsigned"], rejections
    assert all(r.robot in (me, other) and r.version == v for r in rejections)
    assert watch.board.version == v and watch.msg.data == text  # the board never changed

    # the real choice is applied; the same message sent again is a replay
    real = C.choice_to_msg(C.Choice(me, session, v, good), mine)
    sent.add(real.data)
    choice.publish(real)
    graph.spin_until(lambda: watch.board.version > v, 30, "the valid choice to be applied")
    seq, legs = watch.board.legs[d]
    for _, x, y, depart in legs[len(legs) - (seq - seq0):]:  # drive my robot as an agent would
        goal.publish(C.pose_to_msg((x, y), depart))
    choice.publish(real)
    graph.spin_until(lambda: len(rejections) > len(forged), 30, "the replay to be rejected")
    assert rejections[-1].reason == "replayed" and rejections[-1].robot == me
    # a recorded valid choice of another robot, sent again
    graph.spin_until(lambda: recorded, 60, "another robot's choice")
    n = len(rejections)
    choice.publish(recorded[0])
    graph.spin_until(lambda: len(rejections) > n, 30, "the recorded choice's replay to be rejected")
    assert rejections[-1].reason == "replayed"

    # an agent process holding my key takes over my robot; the mission completes as offline
    graph.spin_until(lambda: watch.stable(2.0), 90, "the board to wait for me")
    node.destroy_timer(beat)
    procs.agents.append(procs._spawn("late_agent", "hmrta_agent.agent_node",
                                     ["--robots", me, "--ros-args", "-p", f"seed:={seed}", "-p", f"keystore:={ks}"]))
    wait_board_exit(graph, procs, 120)
    result = json.loads((tmp_path / "result.json").read_text())
    assert_same_as_offline(result, inst, seed)
    assert result["authenticated"] is True
    assert result["auth_rejections"]["choice"] == {"unsigned": 2, "forged": 2, "replayed": 2}
    assert result["auth_rejections"]["status"].get("unsigned", 0) >= 1
    assert Counter(result["rejected_messages"]) == Counter({"unsigned": 2, "forged": 2, "replayed": 2})
    assert "rejected: choice of" in procs.board.log.read_text() and "bad MAC (forged)" in procs.board.log.read_text()


# ---------------------------------------------------------------------------------------------
# a choice lost on the way (a flood can push it out of the board's queue) is sent again
# ---------------------------------------------------------------------------------------------
def test_agent_sends_a_choice_again_while_the_board_waits_for_it(graph, monkeypatch):
    from rclpy.parameter import Parameter

    from hmrta_agent import agent_node

    monkeypatch.setattr(agent_node, "RESEND_AFTER", 0.2)
    key = bytes(range(32))
    host = agent_node.Host()
    host.signer = K.Signer({"robot_1": key})
    agent = agent_node.AgentNode(host, context=graph.context, namespace="/robot_1", start_parameter_services=False,
                                 enable_rosout=False, parameter_overrides=[Parameter("robot", value="robot_1")])
    graph.nodes.append(agent)
    graph.executor.add_node(agent)
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(7, 0)
    agent.mission = C.Mission("s1", inst, tuple(robots_of(inst)), 0, "greedy", rules=GREEDY_RULES)
    agent.index = 1
    got: list[C.Choice] = []
    graph.node("board").create_subscription(String, topics.CHOICE, lambda m: got.append(C.choice_from_msg(m)),
                                            topics.CHOICE_QOS)
    graph.spin_until(lambda: agent.choice_pub.get_subscription_count() > 0, 10, "the subscriber")

    def board(version: int, decider: int = 1, phase: str = "decide") -> C.Board:
        return C.Board("s1", version, 0, phase, decider, 0.0, 0.0, 0, 0, inst.n_tasks)

    agent._send(5, 3, 1.5)
    agent.resend(board(5))  # too early (before RESEND_AFTER, however long delivery takes): nothing
    graph.spin_until(lambda: len(got) == 1, 10, "the choice")
    time.sleep(0.25)
    for b in (board(6), board(5, decider=2), board(5, phase="wait")):  # the board moved on: nothing
        agent.resend(b)
    t_end = time.monotonic() + 0.5
    while time.monotonic() < t_end:
        graph.executor.spin_once(timeout_sec=0.05)
    assert len(got) == 1
    agent.resend(board(5))  # still waiting for it: sent again, freshly signed
    graph.spin_until(lambda: len(got) == 2, 10, "the resent choice")
    first, again = got
    assert (again.robot, again.session, again.version, again.node, again.compute_ms) == ("robot_1", "s1", 5, 3, 1.5)
    verifier = K.Verifier({"robot_1": key})
    assert verifier.verify(first.payload) is None and verifier.verify(again.payload) is None  # not a replay
