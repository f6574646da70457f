"""The operator interface over real DDS: tasks submitted and cancelled at run time with
``hmrta-task`` (hmrta-task-request/1 on /hmrta/task_requests), every request answered on
/hmrta/task_events (hmrta-task-event/1), the added task done by the mission."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import save_instance
from hmrta.generators import ScenarioGenerator

rclpy = pytest.importorskip("rclpy")
from std_msgs.msg import String  # noqa: E402

from hmrta_msgs_py import topics  # noqa: E402
from hmrta_msgs_py import codec as C  # noqa: E402
from test_mission import BoardWatch, robots_of, wait_board_exit  # noqa: E402

BIN = Path(sys.executable).parent


def task_cli(domain: int, tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOG_DIR": str(tmp_path / "ros")}
    return subprocess.run([str(BIN / "hmrta-task"), "--timeout", "20", *args], capture_output=True, text=True,
                          timeout=60, env=env)


def watched_mission(tmp_path: Path, graph, mission_procs, time_scale: float, name: str):
    """(instance, processes, watching node, its BoardWatch, the task events it hears) of a started
    6-robot, 10-task greedy mission (seed 1) paced at ``time_scale``."""
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    procs = mission_procs(save_instance(inst, tmp_path / "inst.yaml"), robots_of(inst), seed=1, time_scale=time_scale,
                          board_params={"progress_period": 0.0, "heartbeat_timeout": 10.0})
    node = graph.node(name)
    watch = BoardWatch(node)
    events: list[C.TaskEvent] = []
    node.create_subscription(String, topics.TASK_EVENTS, lambda m: events.append(C.task_event_from_msg(m)),
                             topics.TASK_EVENT_QOS)
    return inst, procs, node, watch, events


def test_a_task_added_in_map_metres(tmp_path, domain, graph, mission_procs):
    """--metres: the location is divided by the mission's scale, read from its board (1 m per
    unit here); a point outside the map is refused before anything is sent."""
    inst, procs, node, watch, events = watched_mission(tmp_path, graph, mission_procs, 1.5, "metres_watch")
    graph.spin_until(lambda: watch.board is not None and watch.board.phase in ("decide", "wait"), 60, "the start")
    off = task_cli(domain, tmp_path, "add", "--metres", "--location", "2.5,0.5", "--requirements", "1,0,0",
                   "--duration", "1")
    assert off.returncode == 2 and "--location 2.5,0.5 m is outside the mission's map, [0, 1] m" in off.stderr, \
        off.stderr
    metres = task_cli(domain, tmp_path, "add", "--metres", "--location", "0.5,0.5", "--requirements", "1,0,0",
                      "--duration", "1", "--id", "by-metres")
    assert metres.returncode == 0 and "by-metres: add accepted" in metres.stdout, metres.stdout + metres.stderr
    graph.spin_until(lambda: any(e.id == "by-metres" and e.event == "accepted" for e in events), 10, "the event")


def test_tasks_added_and_cancelled_at_run_time(tmp_path, domain, graph, mission_procs):
    """Added first and cancelled last, the long 'spare' task keeps the mission (about 22 s at
    1.5x) running through every hmrta-task run, however long each takes to start and discover
    the board (added fifth and cancelled at once, it kept nothing running: where the runs before
    it were slow, the mission could end first and `list` find no board)."""
    inst, procs, node, watch, events = watched_mission(tmp_path, graph, mission_procs, 1.5, "operator_watch")
    graph.spin_until(lambda: watch.board is not None and watch.board.phase in ("decide", "wait"), 60, "the start")
    extra = task_cli(domain, tmp_path, "add", "--location", "0.9,0.1", "--requirements", "0,1,0", "--duration", "500",
                     "--id", "spare")
    assert extra.returncode == 0, extra.stderr
    add = task_cli(domain, tmp_path, "add", "--location", "0.3,0.7", "--requirements", "1,0,0", "--duration", "1",
                   "--id", "inspect-7")
    assert add.returncode == 0 and "inspect-7: add accepted" in add.stdout, add.stdout + add.stderr
    dup = task_cli(domain, tmp_path, "add", "--location", "0.3,0.7", "--requirements", "1,0,0", "--duration", "1",
                   "--id", "inspect-7")
    assert dup.returncode == 3 and "exists already" in dup.stderr
    big = task_cli(domain, tmp_path, "add", "--location", "0.3,0.7", "--requirements", "99,0,0", "--duration", "1")
    assert big.returncode == 3 and "skill 0" in big.stderr
    assert task_cli(domain, tmp_path, "cancel", "nope").returncode == 3
    listed = task_cli(domain, tmp_path, "list")
    assert listed.returncode == 0 and "inspect-7" in listed.stdout and "spare" in listed.stdout
    assert "mission clock " in listed.stdout and "not heard" not in listed.stdout, listed.stdout
    bad = task_cli(domain, tmp_path, "add", "--location", "x", "--requirements", "1", "--duration", "1")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    cancel = task_cli(domain, tmp_path, "cancel", "spare")
    assert cancel.returncode == 0, cancel.stderr
    wait_board_exit(graph, procs, 120)
    graph.spin_until(lambda: any(e.id == "inspect-7" and e.event == "done" for e in events), 10, "inspect-7 done")
    mine = [(e.id, e.event) for e in events if e.id == "inspect-7"]
    assert mine[0] == ("inspect-7", "accepted") and ("inspect-7", "started") in mine
    assert ("spare", "cancelled") in [(e.id, e.event) for e in events]
    result = json.loads((tmp_path / "result.json").read_text())
    assert len(result["tasks"]) == inst.n_tasks + 2
    assert result["tasks"][inst.n_tasks + 1]["finish"] is not None  # inspect-7 (spare is task n_tasks)
    assert result["undone_tasks"] == [inst.n_tasks]  # the cancelled one


def test_a_task_added_while_the_robots_drive_home_is_done(tmp_path, domain, graph, mission_procs):
    """Every task done, the robots on their way home (board phase "closing"): an operator's task
    reopens the mission; the robots turn round, do it, and go home."""
    inst, procs, node, watch, events = watched_mission(tmp_path, graph, mission_procs, 1.0, "operator_late")
    requests = node.create_publisher(String, topics.TASK_REQUESTS, topics.TASK_REQUEST_QOS)  # found by the start
    graph.spin_until(lambda: watch.board is not None and watch.board.phase == "closing", 120, "the robots going home")
    task = {"location": [0.95, 0.95], "requirements": [1, 1, 0], "duration": 1.0}
    requests.publish(C.task_request_to_msg(C.TaskRequest("add", "late", task, "n1")))
    graph.spin_until(lambda: any(e.id == "late" for e in events), 20, "the answer to the request")
    answer = next(e for e in events if e.id == "late")
    assert answer.event == "accepted", answer
    wait_board_exit(graph, procs, 120)
    graph.spin_until(lambda: any(e.id == "late" and e.event == "done" for e in events), 10, "the late task done")
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["success"] and len(result["tasks"]) == inst.n_tasks + 1
    assert result["tasks"][inst.n_tasks]["finish"] is not None and result["makespan"] > answer.t
    # live == offline: the mission that knew the task would come at the time it was accepted
    from hmrta.core import MissionState
    from hmrta.methods import decider, rules

    ref = MissionState(inst, seed=1, rules=rules("greedy"))
    ref.schedule({"type": "add_task", "t": answer.t, "task": task, "name": "late"})
    decide = decider("greedy", 1)[0]
    while not ref.done:
        ref.step(decide(ref))
    assert result["routes"] == ref.routes and result["makespan"] == ref.makespan


def test_check_offline_replays_the_journal_of_a_mission_an_operator_changed(tmp_path, domain):
    """``hmrta-mission --check-offline`` on a mission that an operator changed (a task added while it
    runs): no offline rollout has that task, so the board's journal is replayed and every decision
    checked against the method's on the same state."""
    out = tmp_path / "mission.json"
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_LOG_DIR": str(tmp_path / "ros")}
    env.pop("ROS_DOMAIN_ID", None)
    proc = subprocess.Popen([str(BIN / "hmrta-mission"), "--method", "greedy", "--time-scale", "2.0",
                             "--agents-per-process", "5", "--out", str(out), "--no-plot", "--quiet",
                             "--check-offline", "--domain-id", str(domain), "--timeout", "120"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 90
        while True:  # the board accepts once the mission has started (before: "not running", exit 3)
            add = task_cli(domain, tmp_path, "add", "--location", "0.5,0.5", "--requirements", "1,0,0,0,0",
                           "--duration", "1", "--id", "op-1")
            if add.returncode == 0 or proc.poll() is not None or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert add.returncode == 0, add.stdout + add.stderr
        so, se = proc.communicate(timeout=150)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, 9)
            proc.wait(10)
    assert proc.returncode == 0, so + se
    assert "offline replay of the journal (greedy; the mission changed while it ran: 1 add_task)" in so, so
    assert "decisions the method's on the same state: yes" in so
    assert json.loads(out.read_text())["live_events"] == {"add_task": 1}


def test_list_says_what_each_task_is_doing_at_the_mission_clock():
    """The board's state runs ahead of the mission clock (a coalition formed now starts when its
    last member arrives): `list` says so in words, not with the bare status."""
    from hmrta.core import MissionState
    from hmrta.generators import ScenarioGenerator
    from hmrta.methods import decider
    from hmrta_coordinator.task_cli import task_words

    decide, rules = decider("greedy")
    st = MissionState(ScenarioGenerator("MA-AT", 6, 3, 6, 3).instance(0, 0), seed=0, rules=rules)
    while not st.done and not (st.status == 2).any():  # until a coalition is formed
        st.step(decide(st))
    t = st.snapshot()["tasks"]
    words = [task_words(t, m, 0.0) for m in range(len(t["status"]))]
    m = t["status"].index("in_progress")
    assert words[m].startswith(f"coalition of {len(t['members'][m])} on its way: starts t={t['start'][m]:.3f}")
    assert task_words(t, m, t["start"][m] + 1e-3).startswith("under way since t=")
    assert all(w == "no robot committed yet" for w, s in zip(words, t["status"]) if s == "empty")
    assert all(w.startswith("coalition forming: ") for w, s in zip(words, t["status"]) if s == "open")
