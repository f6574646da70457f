"""Any process of a mission may die: real processes, real SIGKILL, the real launcher.

``hmrta-mission`` restarts a simulated-robot or agent process that dies; the new process
resynchronises from the latched board and the mission completes (and still equals the offline
rollout). When the board dies without a journal (``--no-journal``) the launcher ends at once with a
partial result and a non-zero exit (with one it is restarted: tests/ros/test_board_crash.py).
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hmrta.formats import load_instance
from hmrta.methods import solve

rclpy = pytest.importorskip("rclpy")
from std_msgs.msg import String  # noqa: E402

from hmrta_coordinator.mission import default_instance  # noqa: E402
from hmrta_msgs_py import topics  # noqa: E402
from hmrta_msgs_py.codec import board_from_msg  # noqa: E402

BIN = Path(sys.executable).parent
TIME_SCALE = 8.0  # sim seconds per wall second: the example mission (makespan ~33) lasts ~4 s


def launch(tmp_path: Path, graph, *extra: str) -> tuple[subprocess.Popen, Path]:
    """Start ``hmrta-mission`` on the example; its output is read as it comes (``proc.lines``:
    {"out": [...], "err": [...]}), so a test can wait for what the launcher reports. The test's
    own board subscription (``proc.seen``, :func:`kill_mid_mission`) is made first, so that its
    DDS discovery (about 2 s) runs while the mission starts, not into the mission's few seconds."""
    seen: dict = {"n_done": {}}  # the latest board ("b") and every version's tasks done

    def on_board(m: String) -> None:
        seen["b"] = b = board_from_msg(m, state=False)
        seen["n_done"][b.version] = b.n_done

    node = graph.node("crash_observer")
    node.create_subscription(String, topics.BOARD, on_board, topics.BOARD_QOS)
    out = tmp_path / "mission.json"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_DOMAIN_ID", None)
    proc = subprocess.Popen([str(BIN / "hmrta-mission"), "--method", "greedy", "--agents-per-process", "5",
                             "--time-scale", str(TIME_SCALE),
                             "--out", str(out), "--no-plot", "--domain-id", str(graph.domain), "--timeout", "90",
                             "--heartbeat-timeout", "20", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)
    proc.lines, proc.seen = {"out": [], "err": []}, seen
    proc.readers = [threading.Thread(target=lambda f=f, k=k: proc.lines[k].extend(iter(f.readline, "")), daemon=True)
                    for f, k in ((proc.stdout, "out"), (proc.stderr, "err"))]
    for t in proc.readers:
        t.start()
    return proc, out


def reported(launcher: subprocess.Popen) -> int:
    """The most tasks the launcher has reported done so far (its progress lines, printed without a
    terminal at the first board version it hears and every quarter of the tasks); -1: none yet."""
    found = [re.match(r"mission: (\d+)/", line) for line in list(launcher.lines["err"])]
    return max((int(m.group(1)) for m in found if m), default=-1)


def children(pid: int) -> dict[int, str]:
    """{pid: command line} of the launcher's child processes."""
    try:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return {}
    out = {}
    for k in kids:
        try:
            out[int(k)] = Path(f"/proc/{k}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            pass
    return out


def child_pid(launcher: subprocess.Popen, needle: str) -> int:
    found = [p for p, cmd in children(launcher.pid).items() if needle in cmd]
    assert len(found) == 1, f"expected one child running {needle!r}, found {children(launcher.pid)}"
    return found[0]


def kill_mid_mission(graph, launcher: subprocess.Popen, needle: str, n_done: int,
                     sig: int = signal.SIGKILL) -> tuple[int, int, dict]:
    """SIGKILL (or ``sig``) the launcher's child whose command line has ``needle`` once ``n_done`` tasks are
    done (and the mission is not) and the launcher follows the board (what it reports after the
    crash comes from what it heard: on a loaded machine its DDS discovery can lag the mission's
    first seconds); returns (its pid, the tasks done then, {"b": latest board, "reported": the
    most tasks the launcher had reported done before the kill, and what :func:`launch` keeps})."""
    seen = launcher.seen
    graph.spin_until(lambda: launcher.poll() is not None or (
        "b" in seen and seen["b"].n_done >= n_done and reported(launcher) >= 0), 60,
                     f"{n_done} tasks done and the launcher following the board")
    assert launcher.poll() is None, "the mission ended before the crash: " + "".join(launcher.lines["err"])
    b = seen["b"]
    assert b.phase != "done" and b.n_done < b.n_tasks
    pid = child_pid(launcher, needle)
    seen["reported"] = reported(launcher)
    os.kill(pid, sig)
    return pid, b.n_done, seen


def finish(launcher: subprocess.Popen, timeout: float) -> tuple[int, str, str]:
    def output() -> tuple[str, str]:
        for t in launcher.readers:
            t.join(timeout=10)
        return "".join(launcher.lines["out"]), "".join(launcher.lines["err"])

    try:
        launcher.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(launcher.pid, signal.SIGINT)
        launcher.wait(timeout=30)
        so, se = output()
        raise AssertionError(f"hmrta-mission did not end within {timeout:g} s:\n{so}\n{se}")
    so, se = output()
    return launcher.returncode, so, se


@pytest.fixture
def launched():
    made: list[subprocess.Popen] = []
    yield made
    for p in made:  # a failed test: never leave a mission behind
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def assert_same_as_offline(result: dict) -> None:
    ref = json.loads(json.dumps(solve(load_instance(default_instance()), "greedy", seed=0).to_dict()))
    for k in ("success", "routes", "tasks", "agents", "makespan", "awt", "redundancy"):
        assert result[k] == ref[k], f"{k}: the mission differs from the offline rollout"


def test_killed_sim_robot_is_restarted_resynchronises_and_the_mission_equals_offline(tmp_path, graph, launched):
    launcher, out = launch(tmp_path, graph)
    launched.append(launcher)
    pid, done_then, seen = kill_mid_mission(graph, launcher, "hmrta_coordinator.sim_robot", 6)
    t_kill = time.monotonic()
    graph.spin_until(lambda: launcher.poll() is not None or any(
        "hmrta_coordinator.sim_robot" in cmd and p != pid for p, cmd in children(launcher.pid).items()),
        20, "the restarted sim_robot")
    t_new = time.monotonic() - t_kill
    graph.spin_until(lambda: launcher.poll() is not None or seen["b"].n_done > done_then, 30, "progress")
    print(f"sim_robot killed with {done_then} tasks done; a new one runs {t_new:.2f} s later, the next task is "
          f"done {time.monotonic() - t_kill:.2f} s after the kill")
    rc, so, se = finish(launcher, 60)
    assert rc == 0, so + se
    assert "sim_robot process died (SIGKILL) at t=" in so and "restarted (1/3)" in so
    result = json.loads(out.read_text())
    assert result["success"] and result["undone_tasks"] == [] and result["lost_robots"] == []
    assert any("sim_robot process died (SIGKILL)" in line for line in result["incidents"])
    log = (tmp_path / "mission_logs" / "sim_robot.log").read_text()
    assert "restarted by hmrta-mission" in log and "resuming the mission at t=" in log
    assert_same_as_offline(result)


def test_killed_agent_process_is_restarted_and_the_mission_completes(tmp_path, graph, launched):
    launcher, out = launch(tmp_path, graph)
    launched.append(launcher)
    kill_mid_mission(graph, launcher, "--robots robot_5,robot_6,robot_7,robot_8,robot_9", 6)
    rc, so, se = finish(launcher, 60)
    assert rc == 0, so + se
    assert "agents_001 process died (SIGKILL) at t=" in so
    result = json.loads(out.read_text())
    assert result["success"] and result["undone_tasks"] == [] and result["lost_robots"] == []
    assert any("agents_001 process died (SIGKILL)" in line for line in result["incidents"])
    assert_same_as_offline(result)


def test_killed_board_ends_the_launcher_with_a_partial_result(tmp_path, graph, launched):
    launcher, out = launch(tmp_path, graph, "--no-journal")  # with its journal the board is restarted
    launched.append(launcher)
    _, done_then, seen = kill_mid_mission(graph, launcher, "hmrta_coordinator.task_board", 6)
    t_kill = time.monotonic()
    rc, so, se = finish(launcher, 30)
    ended = time.monotonic() - t_kill
    print(f"board killed with {done_then} tasks done; the launcher ended {ended:.2f} s later")
    assert rc == 1, so + se
    assert "the mission did not complete (board process died (SIGKILL) at t=" in se
    assert "; not restarted (the board's state lives in that process))" in se  # why it ended, on the console
    result = json.loads(out.read_text())
    assert result["success"] is False and result["partial"] is True and result["journal"] is None
    assert result["failure"].startswith("board process died (SIGKILL) at t=")
    done = [m for m, t in enumerate(result["tasks"]) if t["finish"] is not None]
    # the state of a board version the launcher held (its latest keyframe and the versions after it
    # without a gap: it may lag the test's own view), never the whole mission
    assert len(done) == result["tasks_done"] < len(result["tasks"])
    v = result["board_version"]
    if v is None:  # neither a keyframe nor the stream from version 1 reached the launcher before the
        assert result["tasks_done"] == 0  # board died (DDS discovery): nothing reported as done
    else:
        assert v not in seen["n_done"] or seen["n_done"][v] == len(done), (v, len(done))
    assert sorted(result["undone_tasks"] + done) == list(range(len(result["tasks"])))
    assert all(m in {n for r in result["routes"] for n in r} for m in done)  # done tasks are on routes
    assert ended < 60  # (not the mission's --timeout of 90 s: the launcher saw the board die)


def _test_board():
    """tests/policy/test_board.py: the board's own test drivers."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "policy"))
    import test_board

    return test_board


def _streamed(tb, b, clock: float) -> list[str]:
    """Drive board ``b`` with the test drivers of ``tb`` up to ``clock``; every version it
    published, as the ROS codec writes it on the stream."""
    from hmrta_msgs_py.codec import Board, board_to_msg

    tail: list[str] = []
    pump = tb.pump

    def streamed(board):
        v = pump(board)
        if v is not None and v.version > len(tail):
            tail.append(board_to_msg(Board(v.session, v.version, v.rev, v.phase, v.decider, v.clock, v.horizon,
                                           v.n_done, v.n_cancelled, v.n_tasks, v.lost, prev=v.prev, events=v.events,
                                           digest=v.digest)).data)
        return v

    tb.pump = streamed
    try:
        tb.drive(b, clock=clock)
    finally:
        tb.pump = pump
    return tail


def test_a_partial_result_without_any_keyframe_is_rebuilt_from_the_stream_from_version_1(tmp_path):
    """The launcher's keyframe subscription may match after the board died (DDS discovery): with
    the stream from version 1 it rebuilds the board's state from the mission's initial state, so
    the partial result still says what was done. No processes: the board's own test drivers play
    the mission, every version goes through the ROS codec."""
    from types import SimpleNamespace

    from hmrta.core import IN_PROGRESS
    from hmrta.methods import rules
    from hmrta_coordinator.mission import partial_result

    tb = _test_board()
    b = tb.started_board()
    tail = _streamed(tb, b, 10.0)
    assert 0 < b.state.n_done < tb.INST.n_tasks and tb.RULES == rules("greedy")
    procs = SimpleNamespace(last_board=None, board_tail=tail, method="greedy", method_options={},
                            robots=b.names, incidents=[], journal=tmp_path / "journal.jsonl")
    sol = partial_result(tb.INST, procs, "greedy", tb.SEED, 1.0, "board process died (SIGKILL)")
    assert sol.extra["journal"] is None  # none was written
    procs.journal.write_text("{}\n")
    sol = partial_result(tb.INST, procs, "greedy", tb.SEED, 1.0, "board process died (SIGKILL)")
    assert sol.extra["journal"] == str(procs.journal)  # the journal that can resume the mission
    d = sol.to_dict()
    assert d["board_version"] == b.version and d["tasks_done"] == b.state.n_done > 0
    assert d["routes"] == [list(r) for r in b.state.routes]
    # the coalitions under way at that version are listed with their times (the tasks say nothing of them)
    running = [m for m in range(tb.INST.n_tasks) if b.state.status[m] == IN_PROGRESS]
    assert [(r["task"], r["start"], r["members"]) for r in d.get("in_progress", [])] == [
        (m, float(b.state.start[m]), sorted(b.state.members[m])) for m in running]
    # without version 1 (the stream matched late too) nothing can be rebuilt: nothing is reported done
    procs.board_tail = tail[1:]
    d = partial_result(tb.INST, procs, "greedy", tb.SEED, 1.0, "board process died (SIGKILL)").to_dict()
    assert d["board_version"] is None and d["tasks_done"] == 0


def test_a_partial_result_follows_the_boards_journal_where_the_launcher_heard_less(tmp_path):
    """Stopped at once, the board's last versions may still be on their way to the launcher (an
    interrupted mission reported 1/5 tasks done while the board's log and journal said 2/5): the
    partial result takes the journal's state where the journal goes further."""
    from types import SimpleNamespace

    from hmrta_coordinator.mission import partial_result

    tb = _test_board()
    journal = tmp_path / "journal.jsonl"
    b = tb.started_board(journal=journal)
    tail = _streamed(tb, b, 25.0)
    b.close()
    from std_msgs.msg import String

    from hmrta_msgs_py.codec import board_from_msg

    done = [board_from_msg(String(data=text), legs=False, state=False).n_done for text in tail]  # per version
    first_done = done.index(1)  # the launcher heard up to the version of the first completion
    procs = SimpleNamespace(last_board=None, board_tail=tail[:first_done + 1], method="greedy", method_options={},
                            robots=b.names, incidents=[], journal=journal)
    d = partial_result(tb.INST, procs, "greedy", tb.SEED, 1.0, "interrupted").to_dict()
    assert d["board_version"] == b.version and d["tasks_done"] == b.state.n_done > 1
    last = board_from_msg(String(data=tail[-1]), legs=False, state=False)  # the clock of the last version
    assert d["routes"] == [list(r) for r in b.state.routes] and d["board_clock"] == pytest.approx(last.clock)
    procs.journal = tmp_path / "none.jsonl"  # without the journal: what the launcher heard
    d = partial_result(tb.INST, procs, "greedy", tb.SEED, 1.0, "interrupted").to_dict()
    assert d["board_version"] == first_done + 1 and d["tasks_done"] == 1
