"""Decentralised missions over real DDS (rclpy, Fast DDS), each test in its own ROS domain.

Sim-time mission == offline rollout; robot loss; hostile traffic; late join; a drop-in robot
driven by an external fake driver on remapped topics; the console scripts."""
from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from conftest import save_instance
from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.core import MissionState
from hmrta.generators import ScenarioGenerator
from hmrta.methods import solve
from hmrta.replica import Replica
from hmrta.sim import simulate

rclpy = pytest.importorskip("rclpy")
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from hmrta_msgs_py import topics  # noqa: E402
from hmrta_msgs_py import codec as C  # noqa: E402

BIN = Path(sys.executable).parent


def robots_of(inst) -> list[str]:
    return [f"robot_{a}" for a in range(inst.n_agents)]


def assert_same_as_offline(result: dict, inst, seed: int, method: str = "greedy", ref=None) -> None:
    ref = json.loads(json.dumps((ref or solve(inst, method, seed)).to_dict()))
    for k in ("success", "routes", "tasks", "agents", "makespan", "awt", "redundancy"):
        assert result[k] == ref[k], f"{k}: ROS mission differs from the offline rollout"


class BoardWatch:
    """Follows the board from a test node as an agent does: a replica of its state built from the
    keyframes and the stream, asking for a keyframe when it needs one. ``board`` is the latest
    version the replica holds (header, every robot's legs, the state snapshot), ``msg`` its stream
    message, ``versions`` every version it held."""

    def __init__(self, node):
        self.msg: String | None = None
        self.board: C.Board | None = None
        self.versions: list[int] = []
        self.changed_at = time.monotonic()
        self.replica = Replica()
        self.inst = None
        self._early: tuple | None = None
        self._sessions: set[str] = set()
        self._texts: dict[int, str] = {}  # stream messages by version (the latest few)
        node.create_subscription(String, topics.MISSION, self._on_mission, topics.MISSION_QOS)
        node.create_subscription(String, topics.BOARD, self._on, topics.BOARD_QOS)
        node.create_subscription(String, topics.KEYFRAME, self._on_keyframe, topics.KEYFRAME_QOS)
        self._ask = node.create_publisher(String, topics.KEYFRAME_REQUESTS, topics.KEYFRAME_REQUEST_QOS)
        node.create_timer(0.3, self._request)

    def _on_mission(self, msg: String) -> None:
        self.inst = C.mission_from_msg(msg).instance
        if self._early is not None:
            self._on_keyframe(*self._early)

    def _on_keyframe(self, msg: String, latched: bool | None = None) -> None:
        b = C.board_from_msg(msg)
        if latched is None:  # the first keyframe of a session may be an old one (latched)
            latched = b.session not in self._sessions
            self._sessions.add(b.session)
        if self.inst is None:
            self._early = (msg, latched)
            return
        self._take(b, lambda: (b.legs, b.state), latched)

    def _on(self, msg: String) -> None:
        b = C.board_from_msg(msg)
        self._texts[b.version] = msg.data
        for v in [v for v in self._texts if v < b.version - 50]:
            del self._texts[v]
        self._take(b, None, False)

    def _take(self, b, keyframe, latched: bool) -> None:
        r = self.replica
        r.receive(b, keyframe, self.inst, latched)
        if r.current and (self.board is None or r.version != self.board.version):
            head = r.head
            self.board = dataclasses.replace(head, legs=tuple(r.legs(a) for a in range(r.state.A)),
                                             state=r.state.snapshot(), until=None, keyframe=False)
            text = self._texts.get(r.version) or C.board_to_msg(dataclasses.replace(self.board, legs=None)).data
            self.msg = String(data=text)
            self.versions.append(r.version)
            self.changed_at = time.monotonic()
        self._request()

    def _request(self) -> None:
        ask = self.replica.request()
        if ask is not None:
            self._ask.publish(C.keyframe_request_to_msg(C.KeyframeRequest(self.replica.session or "", *ask,
                                                                          "test BoardWatch")))

    def stable(self, seconds: float) -> bool:
        return self.board is not None and time.monotonic() - self.changed_at > seconds


def run_mission(tmp_path, domain: int, inst, seed: int, method: str, *extra: str) -> tuple[subprocess.CompletedProcess, dict]:
    """``hmrta-mission`` on ``inst`` (6 agents per process): the finished process and its result."""
    path = save_instance(inst, tmp_path / "inst.yaml")
    out = tmp_path / "mission.json"
    proc = subprocess.run([str(BIN / "hmrta-mission"), str(path), "--seed", str(seed), "--out", str(out), "--quiet",
                           "--no-plot", "--method", method, *extra, "--domain-id", str(domain),
                           "--agents-per-process", "6", "--timeout", "150"], capture_output=True, text=True, timeout=200)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc, json.loads(out.read_text())


def assert_routes_equal(result: dict, ref: dict) -> None:
    for k in ("success", "routes", "tasks", "makespan"):
        assert result[k] == ref[k], f"{k}: ROS mission differs from the offline rollout"


def wait_board_exit(graph, procs, timeout: float, statuses: tuple[int, ...] = (0,)) -> int:
    """Wait for the board to exit; its exit status (0; 3: the mission failed) must be one of
    ``statuses``. A board still running at the timeout is asked for its threads' Python stacks
    (SIGUSR1), which the failure shows with the end of its log."""
    try:
        graph.spin_until(lambda: procs.board.proc.poll() is not None, timeout, "the task board to finish the mission")
    except AssertionError as e:
        procs.board.proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        raise AssertionError(f"{e}; the board's log ends (after SIGUSR1: its stacks):\n"
                             f"{procs.board.log.read_text()[-6000:]}") from None
    assert procs.board.proc.returncode in statuses, (procs.board.log.read_text()[-3000:])
    return procs.board.proc.returncode


# ---------------------------------------------------------------------------------------------
def test_console_scripts_are_installed():
    for name in ("agent_node", "task_board", "sim_robot", "mission", "hmrta-mission"):
        assert (BIN / name).exists(), f"{name} is not installed next to {sys.executable}"
    out = subprocess.run([str(BIN / "hmrta-mission"), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--agents-per-process" in out.stdout
    out = subprocess.run([str(BIN / "agent_node"), "--help", "--ros-args", "-p", "seed:=1"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0 and "--robots" in out.stdout


@pytest.mark.parametrize("per_process", [1, 3], ids=["process-per-agent", "3-agents-per-process"])
def test_sim_time_mission_equals_offline_solve(tmp_path, domain, per_process):
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    path = save_instance(inst, tmp_path / "inst.yaml")
    out = tmp_path / "mission.json"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE=os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"])
    proc = subprocess.run([str(BIN / "hmrta-mission"), str(path), "--method", "greedy", "--seed", "3", "--out", str(out), "--quiet",
                           "--no-plot", "--check-offline", "--domain-id", str(domain),
                           "--agents-per-process", str(per_process), "--timeout", "150"],
                          capture_output=True, text=True, timeout=200, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "same routes and makespan: yes" in proc.stdout
    result = json.loads(out.read_text())
    assert_same_as_offline(result, inst, 3)
    assert result["lost_robots"] == [] and result["undone_tasks"] == []
    assert result["transport"] == "ros2" and result["decision_latency_ms"]["n"] > 0


def test_two_missions_on_one_domain_in_two_mission_namespaces(tmp_path, domain):
    """Two missions with the same robot names at once on one ROS domain, one in the root
    namespace and one in /fleet_b (every node's mission_namespace): neither hears the other's
    board, clock or robots, so each equals its own offline rollout; the namespaced one is
    recorded, and its recording replays with its robots' tracks."""
    from hmrta.replay import read_recording

    runs = []
    for ns, seed in (("/", 4), ("/fleet_b", 5)):
        inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(seed, 0)
        d = tmp_path / ns.strip("/") if ns != "/" else tmp_path / "root"
        d.mkdir()
        path = save_instance(inst, d / "inst.yaml")
        # recorded and paced: an unpaced mission can be over before the recorder has discovered the
        # robots' publishers on a loaded machine (tests/ros/test_record.py)
        record = ["--record", str(d / "mission.mcap"), "--time-scale", "5"] if ns != "/" else []
        proc = subprocess.Popen([str(BIN / "hmrta-mission"), str(path), "--method", "greedy", "--seed", "3",
                                 "--out", str(d / "mission.json"), "--quiet", "--no-plot", "--check-offline",
                                 "--domain-id", str(domain), "--agents-per-process", "3", "--timeout", "150",
                                 "--mission-namespace", ns, *record],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        runs.append((ns, inst, d, proc))
    for ns, inst, d, proc in runs:
        try:
            out, _ = proc.communicate(timeout=200)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0, f"mission in {ns}:\n{out}"
        assert "same routes and makespan: yes" in out
        result = json.loads((d / "mission.json").read_text())
        assert_same_as_offline(result, inst, 3)
        assert result["lost_robots"] == [] and "incidents" not in result
    rec = read_recording(tmp_path / "fleet_b" / "mission.mcap")
    assert rec.plan_source == "result" and sorted(rec.tracks) == robots_of(runs[1][1])
    assert all(t.startswith("/fleet_b/") or t == "/rosout" for t in rec.counts), sorted(rec.counts)


def test_a_second_board_in_the_namespace_gives_way_and_the_running_mission_is_not_disturbed(tmp_path, graph,
                                                                                            mission_procs):
    """A task board started in the mission namespace of a running mission (same robot names)
    stops at once (exit 2, it gives way to the earlier mission); the agents keep to the running
    mission, which completes equal to its offline rollout with nobody lost."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    path = save_instance(inst, tmp_path / "inst.yaml")
    procs = mission_procs(path, robots_of(inst), seed=3, agents_per_process=6, time_scale=3.0,
                          board_params={"progress_period": 0.0})
    watch = BoardWatch(graph.node("observer"))
    graph.spin_until(lambda: watch.board is not None and watch.board.n_done >= 1, 90, "the mission under way")
    log = open(tmp_path / "second.log", "w")
    second = subprocess.Popen([str(BIN / "task_board"), "--ros-args", "-p", f"instance:={path}",
                               "-p", "exit_on_done:=false"], env=procs.env, stdout=log, stderr=subprocess.STDOUT)
    try:
        assert second.wait(timeout=60) == 2, (tmp_path / "second.log").read_text()
    finally:
        if second.poll() is None:
            second.kill()
        log.close()
    assert "this board gives way" in (tmp_path / "second.log").read_text()
    wait_board_exit(graph, procs, 150)
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["lost_robots"] == []
    assert_same_as_offline(result, inst, 3)


def test_a_board_started_with_portfolio_chooses_and_agents_started_with_it_run_the_choice(tmp_path, graph,
                                                                                          mission_procs):
    """method:=portfolio on every node (as fleet.launch.py passes one method to all): the board
    simulates the candidates on its mission, publishes the chosen one as the mission's method
    (here rl@broad, a candidate with its own checkpoint), and the agents run it. SIGKILLed
    mid-mission and restarted on its journal with other candidates, the board keeps the method its
    mission started with. The mission equals the offline portfolio on the same mission."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(3, 0)
    path = save_instance(inst, tmp_path / "inst.yaml")
    ref = solve(inst, "portfolio", 3, candidates="rl@broad,greedy")
    assert ref.extra["portfolio"]["chosen"] == "rl@broad"  # (greedy: the nodes' default, 20% longer here)
    procs = mission_procs(path, robots_of(inst), seed=3, agents_per_process=3, time_scale=3.0, method="portfolio",
                          method_options={"candidates": "rl@broad,greedy"}, journal=tmp_path / "journal.jsonl",
                          board_params={"progress_period": 0.0, "heartbeat_timeout": 30.0})
    watch = BoardWatch(graph.node("portfolio_watch"))
    graph.spin_until(lambda: watch.board is not None and watch.board.n_done >= 2, 90, "two tasks done")
    board_log = procs.board.log.read_text()
    assert "method portfolio: chose rl@broad" in board_log, board_log[-2000:]
    procs.board.proc.kill()
    procs.board.proc.wait()
    with open(tmp_path / "board_again.log", "w") as log:  # greedy alone would be chosen now
        again = subprocess.Popen(procs.board.cmd + ["-p", "candidates:=greedy"], stdout=log,
                                 stderr=subprocess.STDOUT, env=procs.env)
        try:
            assert again.wait(timeout=120) == 0, (tmp_path / "board_again.log").read_text()[-3000:]
        finally:
            if again.poll() is None:
                again.kill()
                again.wait()
    text = (tmp_path / "board_again.log").read_text()
    assert "method portfolio: rl@broad, as chosen when the mission started" in text, text[-3000:]
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["method"] == "rl@broad" and result["lost_robots"] == [] and result["board_restarts"] == 1
    assert_same_as_offline(result, inst, 3, ref=ref)
    # what was chosen and the network that ran, as offline (the restarted board: from its journal)
    assert result["checkpoint"]["sha256"] == ref.extra["checkpoint"]["sha256"]
    agent_logs = "".join(a.log.read_text() for a in procs.agents)
    assert agent_logs.count("running rl@broad, the board's choice") == inst.n_agents, agent_logs[-2000:]


def test_mission_namespace_errors():
    """A bad namespace is a one-line user error of hmrta-mission and hmrta-task (exit 2), before
    anything starts."""
    for cmd in (["hmrta-mission", "--mission-namespace", "fleet 1"], ["hmrta-task", "--mission-namespace", "/1x", "list"]):
        proc = subprocess.run([str(BIN / cmd[0]), *cmd[1:]], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and "--mission-namespace: expected an absolute ROS namespace" in proc.stderr, \
            proc.stderr


@pytest.mark.parametrize("method", ["portfolio", "rl-s3"])
def test_a_chosen_or_sampled_method_is_reported_as_asked(tmp_path, domain, method):
    """portfolio: the result names it and what it chose (as offline), and the chosen method's live
    mission equals its offline rollout; rl-sample: each robot samples its own decisions live, so
    --check-offline says it does not compare (no rollout repeats those samples)."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    path = save_instance(inst, tmp_path / "inst.yaml")
    out = tmp_path / "mission.json"
    extra = ["--candidates", "greedy,greedy-coalition"] if method == "portfolio" else []
    proc = subprocess.run([str(BIN / "hmrta-mission"), str(path), "--method", method, *extra, "--out", str(out),
                           "--quiet", "--no-plot", "--check-offline", "--domain-id", str(domain),
                           "--agents-per-process", "6", "--timeout", "150"],
                          capture_output=True, text=True, timeout=200, env=dict(os.environ))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(out.read_text())
    if method == "portfolio":
        assert result["method"] == "portfolio" and result["portfolio"]["chosen"] in ("greedy", "greedy-coalition")
        assert set(result["portfolio"]["candidates"]) == {"greedy", "greedy-coalition"}
        assert "same routes and makespan: yes" in proc.stdout
    else:
        assert result["method"] == "rl-sample" and result["success"]
        assert "offline rollout: not compared: live, rl-sample samples each decision" in proc.stdout


def test_a_bad_checkpoint_is_a_user_error_before_any_process_starts(tmp_path):
    proc = subprocess.run([str(BIN / "hmrta-mission"), "--method", "rl", "--checkpoint", str(tmp_path / "nosuch.pt"),
                           "--out", str(tmp_path / "m.json")], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert proc.returncode == 2 and "nosuch.pt" in proc.stderr.splitlines()[-1], proc.stderr
    assert "processes on ROS domain" not in proc.stdout and not list(tmp_path.iterdir())


def test_lost_board_messages_are_recovered_from_keyframes_and_the_mission_equals_offline(tmp_path, graph,
                                                                                       mission_procs):
    """Both agent processes drop the board messages of some versions once, as if DDS had lost them
    (agent_node --ignore-board-version): a replica that gets a later version sees the gap, asks the
    board for a keyframe and resynchronises; one whose lost version was the latest gets it again
    when the idle board repeats it. The sim-time mission still equals the offline rollout."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    robots, seed = robots_of(inst), 3
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots, seed=seed, no_agent=robots,
                          board_params={"progress_period": 0.0})
    lost = [x for v in range(4, 60, 3) for x in ("--ignore-board-version", str(v))]
    for i, group in enumerate((robots[:3], robots[3:])):
        procs.agents.append(procs._spawn(f"lossy_agents_{i}", "hmrta_agent.agent_node",
                                         ["--robots", ",".join(group), *lost, "--ros-args", "-p", f"seed:={seed}"]))
    wait_board_exit(graph, procs, 150)
    result = json.loads((tmp_path / "result.json").read_text())
    assert_same_as_offline(result, inst, seed)
    assert result["lost_robots"] == [] and result["board_keyframes"].get("requested", 0) >= 1
    logs = [agent.log.read_text() for agent in procs.agents]
    for log in logs:
        assert "ignoring the board header of version 4 " in log and "ignoring the board header of version 25 " in log
        assert "diverged" not in log and "does not load" not in log
    gaps = sum(log.count("asking for a keyframe (missed version(s)") for log in logs)
    print(f"{result['board_versions']} versions, keyframes {result['board_keyframes']}; {gaps} gaps asked for")
    assert gaps >= 1 and "keyframe asked for by" in procs.board.log.read_text()


def test_robot_loss_releases_commitments_and_completes_satisfiable_tasks(tmp_path, graph, mission_procs):
    # single-skill species of two robots each: losing one makes tasks needing 2 of its skill impossible
    inst = ScenarioGenerator("SA-AT", 6, 3, 12, 3).instance(2, 0)
    robots = robots_of(inst)
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots, seed=1, time_scale=6.0,
                          # the timeout is well above the pauses of six agent processes starting on two
                          # loaded cores (at 1.5 s, live agents were dropped as they started, once in CI)
                          board_params={"heartbeat_timeout": 4.0, "progress_period": 0.0})
    watch = BoardWatch(graph.node("observer"))
    graph.spin_until(lambda: watch.board is not None and watch.board.n_done >= 2, 90, "two tasks done")
    # kill the agent of a robot that is on its way to a task (crash: SIGKILL)
    b = watch.board
    busy = [a for a, e in enumerate(b.legs) if e and e[1] and e[1][-1][0] > 0]
    victim = robots[busy[0] if busy else 0]
    procs.agent_of(victim).proc.kill()
    rc = wait_board_exit(graph, procs, 120, statuses=(0, 3))
    result = json.loads((tmp_path / "result.json").read_text())
    assert rc == (0 if result["success"] else 3)  # a board whose mission failed says so
    print(f"lost {victim}; undone tasks {result['undone_tasks']}; success {result['success']}")
    assert result["lost_robots"] == [victim]
    assert "agent heartbeat" in result["lost_reasons"][victim]
    lost = robots.index(victim)
    team = inst.traits[[a for a in range(inst.n_agents) if a != lost]].sum(0)
    undone = result["undone_tasks"]
    for m, t in enumerate(result["tasks"]):
        satisfiable = bool((inst.requirements[m] <= team).all())
        if m in undone:
            assert not satisfiable and t["finish"] is None
        else:  # completed by a coalition that satisfies it
            c = inst.traits[t["members"]].sum(0)
            assert (c >= inst.requirements[m]).all() and t["finish"] is not None
    assert result["success"] == (undone == [])
    # the robots that survived are home
    assert all(r["return_time"] is not None for a, r in enumerate(result["agents"]) if a != lost) or undone


def test_hostile_traffic_never_changes_the_board_and_late_joiners_get_it(tmp_path, graph, mission_procs):
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(7, 0)
    robots = robots_of(inst)
    seed = 2
    d = MissionState(inst, seed=seed, rules=GREEDY_RULES).agent  # the first decider: played by this test
    me = robots[d]
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots, seed=seed, no_agent=[me],
                          board_params={"heartbeat_timeout": 0.0, "decision_timeout": 0.0, "progress_period": 0.0})
    node = graph.node("hostile")
    watch = BoardWatch(node)
    missions: list[C.Mission] = []
    rejections: list[C.Rejection] = []
    node.create_subscription(String, topics.MISSION, lambda m: missions.append(C.mission_from_msg(m)),
                             topics.MISSION_QOS)
    node.create_subscription(String, topics.REJECTIONS, lambda m: rejections.append(C.rejection_from_msg(m)),
                             topics.REJECTION_QOS)
    choice = node.create_publisher(String, topics.CHOICE, topics.CHOICE_QOS)
    status = node.create_publisher(String, topics.STATUS, topics.STATUS_QOS)
    goal = node.create_publisher(PoseStamped, topics.robot_topic(me, topics.GOAL), topics.GOAL_QOS)
    graph.spin_until(lambda: missions, 60, "the mission")
    session = missions[0].session
    node.create_timer(0.3, lambda: status.publish(C.status_to_msg(C.Status((me,), session, 0))))  # my heartbeat
    graph.spin_until(lambda: watch.board and watch.board.phase == "decide" and watch.board.decider == d, 90,
                     f"{me}'s turn")
    graph.spin_until(lambda: choice.get_subscription_count() > 0 and goal.get_subscription_count() > 0, 30,
                     "the board and the simulated robot to listen")
    v, text = watch.board.version, watch.msg.data
    seq0 = watch.board.legs[d][0]
    state = MissionState.from_snapshot(inst, watch.board.state)
    good = Greedy()(state)
    masked = [n for n, ok in enumerate(state.mask()) if not ok]

    def send(payload) -> None:
        if isinstance(payload, C.Choice):
            choice.publish(C.choice_to_msg(payload))
        else:
            raw = String()
            raw.data = payload
            choice.publish(raw)

    hostile = ["garbage", '{"format": "hmrta-choice/1"}',
               json.dumps({"format": "hmrta-choice/1", "robot": me, "session": session, "version": "x", "node": 1}),
               C.Choice("intruder", session, v, good),
               C.Choice(me, "another-run", v, good),
               C.Choice(robots[(d + 1) % len(robots)], session, v, good),
               C.Choice(me, session, v, inst.n_tasks + 5),
               C.Choice(me, session, v, -1),
               C.Choice(me, session, v - 1, good),
               C.Choice(me, session, v + 3, good)]
    expected = Counter({"malformed": 3, "unknown_robot": 1, "foreign_session": 1, "not_your_turn": 1, "masked": 2,
                        "stale": 2})
    if masked:
        hostile.append(C.Choice(me, session, v, masked[0]))
        expected["masked"] += 1
    for h in hostile:
        send(h)
    graph.spin_until(lambda: len(rejections) >= len(hostile), 30, "every hostile message to be rejected")
    assert Counter(r.reason for r in rejections) == expected
    assert watch.board.version == v and watch.msg.data == text  # the board never changed
    # the real choice is applied; replaying it is a duplicate and changes nothing
    send(C.Choice(me, session, v, good))
    graph.spin_until(lambda: watch.board.version > v, 30, "the valid choice to be applied")
    assert watch.board.rev > C.board_from_msg(String(data=text)).rev
    # drive my robot like an agent would: a goal for each new leg the board lists for it
    seq, legs = watch.board.legs[d]
    for _, x, y, depart in legs[len(legs) - (seq - seq0):]:
        goal.publish(C.pose_to_msg((x, y), depart))
    send(C.Choice(me, session, v, good))
    graph.spin_until(lambda: len(rejections) > len(hostile), 30, "the duplicate to be rejected")
    assert rejections[-1].reason == "duplicate"
    # the mission goes on until it needs me again; then the board stays put
    # (held for my choice: 2 s unchanged; held otherwise, e.g. for my robot that no agent drives: 5 s,
    # which a busy machine's pause does not reach while the mission moves)
    graph.spin_until(lambda: watch.stable(2.0) and (
        (watch.board.phase == "decide" and watch.board.decider == d) or watch.stable(5.0)), 90,
                     "the board to wait for me")
    latest = watch.board.version
    expected["duplicate"] += 1
    b = watch.board
    if b.phase == "decide" and b.decider == d:  # choosing a task that is already closed changes nothing
        state = MissionState.from_snapshot(inst, b.state)
        closed = [m for m in range(inst.n_tasks) if state.status[m] >= 2]
        if closed:
            send(C.Choice(me, session, b.version, 1 + closed[0]))
            graph.spin_until(lambda: sum(expected.values()) + 1 == len(rejections), 30, "the closed task's rejection")
            assert rejections[-1].reason == "masked"
            expected["masked"] += 1
            assert watch.board.version == latest
            print(f"choosing closed task {closed[0]} was rejected")
    late = graph.node("late_joiner")
    late_watch = BoardWatch(late)
    t0 = time.monotonic()
    graph.spin_until(lambda: late_watch.board is not None, 10, "the late joiner's first board")
    assert late_watch.board.version == latest and late_watch.msg.data == watch.msg.data
    print(f"late joiner got board {latest} after {time.monotonic() - t0:.2f} s")
    # a late-joining agent process takes over my robot and the mission completes as offline
    procs.agents.append(procs._spawn("late_agent", "hmrta_agent.agent_node",
                                     ["--robots", me, "--ros-args", "-p", f"seed:={seed}"]))
    wait_board_exit(graph, procs, 120)
    result = json.loads((tmp_path / "result.json").read_text())
    assert_same_as_offline(result, inst, seed)
    assert result["rejected_messages"] == dict(expected)


def test_drop_in_robot_on_remapped_topics(tmp_path, graph, mission_procs):
    """robot_1 is not simulated: an external driver (here a fake) consumes its goals and publishes
    its pose under its own topic names; remaps connect it. With real-time departures (no
    back-dating, as real robots need) the mission equals the offline rollout under those rules."""
    inst = ScenarioGenerator("SA-AT", 9, 3, 12, 3).instance(1, 0)  # postponements happen here
    robots = robots_of(inst)
    ext, seed = "robot_1", 5
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots, seed=seed, external=[ext],
                          agents_per_process=4,
                          agent_ros_args={ext: ["-r", "goal_pose:=/fake1/cmd_goal"]},
                          board_ros_args=["-r", f"/{ext}/pose:=/fake1/odom_pose"],
                          board_params={"arrival_tolerance": 0.01, "progress_period": 0.0,
                                        "real_time_departures": True})
    driver = graph.node("fake_driver", namespace="/fake1")
    where = [tuple(inst.depots[1])]
    goals: list[tuple[float, float]] = []
    pose_pub = driver.create_publisher(PoseStamped, "odom_pose", qos_profile_sensor_data)

    def report() -> None:
        pose_pub.publish(C.pose_to_msg(where[0], 0.0))

    def on_goal(msg: PoseStamped) -> None:
        x, y, _ = C.pose_from_msg(msg)
        goals.append((x, y))
        where[0] = (x + 0.002, y - 0.002)  # "drives" there at once, stops within tolerance
        report()

    driver.create_subscription(PoseStamped, "cmd_goal", on_goal, 10)
    driver.create_timer(0.25, report)
    views: list[C.MarkerView] = []  # RViz markers are published while someone listens
    driver.create_subscription(MarkerArray, topics.MARKERS, lambda m: views.append(C.markers_from_msg(m)),
                               topics.MARKER_QOS)
    wait_board_exit(graph, procs, 150)
    assert views and len(views[-1].tasks) == inst.n_tasks and len(views[-1].robots) == inst.n_agents
    result = json.loads((tmp_path / "result.json").read_text())
    assert_same_as_offline(result, inst, seed,
                           ref=simulate(inst, Greedy(), seed, dataclasses.replace(GREEDY_RULES, backdate=False)))
    assert result["makespan"] != solve(inst, "greedy", seed).makespan  # back-dating would have changed it
    depot = tuple(inst.depots[1])
    route = [tuple(inst.task_locations[m]) for m in result["routes"][1]]
    assert route and [g for g in goals if g != depot] == route
    assert goals[-1] == depot


@pytest.mark.parametrize("policy", ["rl", "rl-lookahead", "rl@coalition-team"])
def test_rl_policy_mission_equals_offline(tmp_path, domain, policy):
    """--method rl goes through hmrta.methods.decider in every agent (one shared copy of the
    weights per process); greedy decoding is deterministic, so the mission equals the offline
    rollout. Uses the shipped checkpoint, or an untrained one when none is shipped yet: the
    default observes greedy-coalition's start estimates too (scale mission+coalition);
    rl@coalition-team runs under its own team-scaled open-task cap, which the board applies."""
    torch = pytest.importorskip("torch")
    try:
        from hmrta.rl import inference
        from hmrta.rl.model import ModelConfig, PolicyNet
    except ImportError as e:
        pytest.skip(f"learned policy unavailable: {e}")
    checkpoint = []
    try:
        inference.load_policy()
    except inference.CheckpointError:
        torch.manual_seed(0)
        cfg = ModelConfig(ff_hidden=128)
        ck = tmp_path / "untrained.pt"
        torch.save({"config": {"model": cfg.to_dict(), "rules": {"max_open": 2, "safety": True}},
                    "model": PolicyNet(cfg).state_dict()}, ck)
        checkpoint = ["--checkpoint", str(ck)]
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    _, result = run_mission(tmp_path, domain, inst, 1, policy, *checkpoint)
    ref = json.loads(json.dumps(solve(inst, policy, 1, **({"checkpoint": checkpoint[1]} if checkpoint else {})).to_dict()))
    assert_routes_equal(result, ref)


def test_portfolio_mission_runs_the_chosen_candidate_with_its_own_checkpoint(tmp_path, domain):
    """--method portfolio choosing rl@broad: the board and every agent run rl with the shipped
    broad.pt (its rules and its weights), and the mission equals that candidate's offline rollout."""
    pytest.importorskip("torch")
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 5)
    chosen = solve(inst, "portfolio", 1).extra["portfolio"]
    assert chosen["chosen"] == "rl@broad" and chosen["candidates"]["rl@broad"] < chosen["candidates"]["rl"]
    proc, result = run_mission(tmp_path, domain, inst, 1, "portfolio")
    assert "method chosen by simulation: rl with checkpoint broad" in proc.stdout
    assert_routes_equal(result, json.loads(json.dumps(solve(inst, "rl@broad", 1).to_dict())))


def test_coalition_greedy_mission_equals_offline(tmp_path, domain):
    """--method greedy-coalition: every agent runs the coalition-aware greedy through
    hmrta.methods.decider on the board's state; the live mission equals the offline simulation."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 1)
    _, result = run_mission(tmp_path, domain, inst, 2, "greedy-coalition")
    ref = json.loads(json.dumps(solve(inst, "greedy-coalition", 2).to_dict()))
    assert ref["routes"] != json.loads(json.dumps(solve(inst, "greedy", 2).to_dict()))["routes"]  # a different policy
    assert_routes_equal(result, ref)
