"""The task board survives its own crash: real processes, real SIGKILL, the real launcher.

``hmrta-mission`` journals the board (``<out>_logs/journal.jsonl``); when the board process is
killed mid-mission the launcher restarts it on its journal, the new board replays it (same
session, same versions) and agents and robots resynchronise from its latched board. In simulated
time the mission then equals the uninterrupted one (the offline rollout)."""
from __future__ import annotations

import json
import os
import signal
import time

import pytest

from hmrta.board import read_journal

rclpy = pytest.importorskip("rclpy")
from test_crash import assert_same_as_offline, children, finish, kill_mid_mission, launch, launched  # noqa: E402,F401


def test_killed_board_is_restarted_on_its_journal_and_the_mission_equals_offline(tmp_path, graph, launched):
    launcher, out = launch(tmp_path, graph)
    launched.append(launcher)
    pid, done_then, seen = kill_mid_mission(graph, launcher, "hmrta_coordinator.task_board", 6)
    version_then = seen["b"].version
    t_kill = time.monotonic()
    graph.spin_until(lambda: launcher.poll() is not None or (seen["b"].n_done > done_then
                                                           and seen["b"].version > version_then), 40,
                     "progress after the restart")
    print(f"board killed with {done_then} tasks done (version {version_then}); the next task was done "
          f"{time.monotonic() - t_kill:.2f} s after the kill")
    rc, so, se = finish(launcher, 60)
    assert rc == 0, so + se
    assert "board process died (SIGKILL) at t=" in se and "restarted on its journal (1/3)" in se
    result = json.loads(out.read_text())
    assert result["success"] and result["undone_tasks"] == [] and result["lost_robots"] == []
    assert result["board_restarts"] == 1
    assert any("board process died (SIGKILL)" in line for line in result["incidents"])
    assert_same_as_offline(result)
    header, recs, _, dropped = read_journal(tmp_path / "mission_logs" / "journal.jsonl")
    assert dropped is None and [r["v"] for r in recs] == list(range(1, len(recs) + 1))
    assert sum(e["type"] == "resume" for r in recs for e in r.get("ev", ())) == 1
    log = (tmp_path / "mission_logs" / "task_board.log").read_text()
    assert "restarted by hmrta-mission" in log and "resumed from journal" in log


def test_a_board_stopped_by_a_plain_kill_is_restarted_on_its_journal(tmp_path, graph, launched):
    """SIGTERM (kill's default) stops the board cleanly, exit status 0, before the mission
    finished: hmrta-mission restarts it on its journal like a crashed one, and the mission
    completes as offline."""
    launcher, out = launch(tmp_path, graph)
    launched.append(launcher)
    kill_mid_mission(graph, launcher, "hmrta_coordinator.task_board", 6, sig=signal.SIGTERM)
    rc, so, se = finish(launcher, 90)
    assert rc == 0, so + se
    assert "board process stopped before the mission finished (exit status 0)" in se, se
    result = json.loads(out.read_text())
    assert result["success"] and result["board_restarts"] == 1
    assert_same_as_offline(result)
    assert "stopped by SIGTERM before the mission finished" in (tmp_path / "mission_logs" / "task_board.log").read_text()


def test_a_board_stopped_longer_than_the_heartbeat_timeout_resumes_without_dropping_anyone(tmp_path, graph,
                                                                                          launched):
    """SIGSTOP the board for three heartbeat timeouts, then SIGCONT: the heartbeats sent meanwhile
    wait in its queues (or are repaired by the middleware), so nobody is lost and the mission
    completes."""
    launcher, out = launch(tmp_path, graph, "--heartbeat-timeout", "5")
    launched.append(launcher)
    pid, done_then, _ = kill_mid_mission(graph, launcher, "hmrta_coordinator.task_board", 4, sig=signal.SIGSTOP)
    try:
        time.sleep(15.0)
    finally:
        os.kill(pid, signal.SIGCONT)
    rc, so, se = finish(launcher, 90)
    assert rc == 0, so + se
    result = json.loads(out.read_text())
    assert result["success"] and result["lost_robots"] == [] and result["undone_tasks"] == []
    log = (tmp_path / "mission_logs" / "task_board.log").read_text()
    assert "the board did not run for" in log, log[-2000:]
    assert "nothing heard on" not in log, log[-2000:]  # the board stalled, not the mission clock


def test_incident_time_falls_back_to_the_journal(tmp_path):
    """A process that dies before the launcher has heard the mission clock is reported at the clock
    of the board's last journaled version (the launcher's monitor may still be discovering topics)."""
    import json
    import math

    from hmrta_coordinator.mission import journal_clock

    p = tmp_path / "journal.jsonl"
    assert math.isnan(journal_clock(p))  # no journal yet
    lines = [{"format": "hmrta-journal/1"}, {"v": 1, "rev": 0, "n_done": 0, "phase": "starting", "clock": 0.0},
             {"v": 2, "rev": 3, "n_done": 1, "phase": "decide", "clock": 3.5}]
    p.write_text("".join(json.dumps(x) + "\n" for x in lines) + '{"v": 3, "clo')  # and a torn last line
    assert journal_clock(p) == 3.5
    p.write_text(json.dumps(lines[0]) + "\n")
    assert math.isnan(journal_clock(p))  # a header only


def test_a_board_restarted_without_its_journal_stops_on_the_running_missions_clock(tmp_path, graph, mission_procs):
    """SIGKILL a board that has no journal mid-mission and start it again: sim_robot keeps the
    mission it started with and its clock runs on, so the new board's mission could never move (it
    followed that clock and waited forever for arrivals nobody drove to). The new board names the
    clock another mission's, says how to resume or restart, and exits 2 within seconds."""
    import subprocess
    from pathlib import Path

    import hmrta
    from hmrta.formats import load_instance
    from test_mission import BoardWatch, robots_of

    example = Path(hmrta.__file__).resolve().parent / "data" / "example.yaml"
    procs = mission_procs(example, robots_of(load_instance(example)), time_scale=2.0, agents_per_process=5,
                          board_params={"progress_period": 0.0, "heartbeat_timeout": 30.0})
    watch = BoardWatch(graph.node("restart_watch"))
    graph.spin_until(lambda: watch.board is not None and watch.board.n_done >= 2, 90, "two tasks done")
    procs.board.proc.kill()
    procs.board.proc.wait()
    with open(tmp_path / "board_again.log", "w") as log:
        again = subprocess.Popen(procs.board.cmd, stdout=log, stderr=subprocess.STDOUT, env=procs.env)
        try:
            rc = again.wait(timeout=60)
        finally:
            if again.poll() is None:
                again.kill()
                again.wait()
    text = (tmp_path / "board_again.log").read_text()
    assert rc == 2, text[-3000:]
    assert "it is another mission's clock" in text and "-p journal:=FILE" in text, text[-3000:]
    assert "stopping (exit status 2)" in text
