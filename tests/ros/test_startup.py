"""How the node executables start and stop for a ROS user: Ctrl-C at any moment of start-up,
malformed ``--ros-args``, parameters of the wrong type or unknown ones, exit statuses (a refusing
agent, a failed mission, a stopped board) and the warning when no board is heard. Real
executables over real DDS, each test on its own ROS domain."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import save_instance
from hmrta.generators import ScenarioGenerator

pytest.importorskip("rclpy")

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
EXAMPLE = ROOT / "policy" / "hmrta" / "data" / "example.yaml"
NODES = ("task_board", "agent_node", "sim_robot", "recorder")


def _env(domain: int, tmp_path: Path) -> dict[str, str]:
    return dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain),
                ROS_LOG_DIR=str(tmp_path / "ros_logs"))


class Proc:
    """One executable, its stdout and stderr in a log file."""

    def __init__(self, exe: str, args: list[str], env: dict[str, str], log: Path):
        self.exe, self.log = exe, log
        self._fh = open(log, "w")
        self.proc = subprocess.Popen([str(BIN / exe), *args], stdout=self._fh, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, env=env)

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_for(self, text: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.text():
            if self.proc.poll() is not None and text not in self.text():
                raise AssertionError(f"{self.exe} exited ({self.proc.returncode}) without {text!r}:\n{self.text()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.exe}: no {text!r} after {timeout:g} s:\n{self.text()}")
            time.sleep(0.1)

    def stop(self, sig: int = signal.SIGINT, timeout: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        rc = self.proc.wait(timeout=timeout)
        self._fh.close()
        return rc

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._fh.close()


@pytest.fixture
def start(tmp_path, domain):
    """start(exe, *args) -> a running Proc on this test's domain; every one is killed at teardown."""
    made: list[Proc] = []

    def make(exe: str, *args: str, name: str | None = None) -> Proc:
        p = Proc(exe, list(args), _env(domain, tmp_path), tmp_path / f"{name or exe}.log")
        made.append(p)
        return p

    yield make
    for p in made:
        p.kill()


# ---- 1. Ctrl-C during start-up ----------------------------------------------------------------
def test_a_signal_before_the_nodes_spin_leaves_the_context_valid(tmp_path, domain):
    """Between rclpy.init and spinning, rclpy's own handlers (which shut the context down under
    the node being built: an RCLError, or a C++ abort) are not installed: SIGINT is a plain
    KeyboardInterrupt, and starting() turns it into one line and exit 130."""
    code = ("import os, signal, rclpy\n"
            "from std_msgs.msg import String\n"
            "from hmrta_msgs_py.runtime import starting\n"
            "with starting('some_node', args=['some_node']):\n"
            "    node = rclpy.create_node('n')\n"
            "    try:\n"
            "        os.kill(os.getpid(), signal.SIGINT)\n"
            "    except KeyboardInterrupt:\n"
            "        print('context ok:', rclpy.ok())\n"
            "    node.create_publisher(String, 't', 10)\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    node.create_publisher(String, 'u', 10)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       env=_env(domain, tmp_path))
    assert r.stdout == "context ok: True\n", r.stdout + r.stderr
    assert r.returncode == 130 and r.stderr == "some_node: interrupted during start-up\n", r.stderr


def _wait_until_start_up_handles_signals(proc: subprocess.Popen, timeout: float = 30.0) -> None:
    """Until the process catches SIGINT and SIGTERM (/proc/PID/status, SigCgt): the first thing
    the console scripts' body (and ``run_node``'s first line) does, before any heavy import. A
    signal sent at once lands in start-up on any machine, and later moments count from it:
    observed, not guessed from the start (a fast machine was past start-up 0.2 s after it, a
    slow one had not yet installed the handlers 0.15 s after it)."""
    bits = 1 << (signal.SIGTERM - 1) | 1 << (signal.SIGINT - 1)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            status = Path(f"/proc/{proc.pid}/status").read_text()
        except OSError:
            status = ""
        caught = next((int(line.split()[1], 16) for line in status.splitlines() if line.startswith("SigCgt:")), 0)
        if caught & bits == bits:
            return
        if proc.poll() is not None:
            raise AssertionError(f"exited ({proc.returncode}) before its start-up handled signals")
        time.sleep(0.001)
    raise AssertionError(f"no SIGINT and SIGTERM handlers after {timeout:g} s")


START_UP_SIGNALS = {  # signal: (moments to send it, exit status and last line during start-up)
    # seconds after start-up handles signals (the first: always start-up)
    signal.SIGINT: ((0.0, 0.15, 0.3, 0.4, 0.5, 0.6, 0.75, 0.9, 1.1, 1.3), 130, "interrupted during start-up"),
    signal.SIGTERM: ((0.0, 0.15, 0.5, 1.3), 143, "terminated during start-up (SIGTERM)"),
}


@pytest.mark.parametrize("sig", list(START_UP_SIGNALS), ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("exe,args", [
    ("task_board", ["--ros-args", "-p", f"instance:={EXAMPLE}"]),
    ("agent_node", ["--ros-args", "-p", "robot:=robot_0"]),
])
def test_ctrl_c_or_sigterm_at_any_moment_of_start_up_is_one_line(exe, args, sig, tmp_path, domain):
    """SIGINT (or SIGTERM, kill's default) as soon as start-up handles signals, then from 0.15 s
    to 1.3 s after that (before it, the interpreter itself starts): while the modules load, while
    the node is built (130 for SIGINT, 143 for SIGTERM, one line), or once it spins (rc 0,
    'stopped by SIGINT'); never a traceback or an abort. (SIGTERM once ended the process without
    a word.)"""
    delays, status, line = START_UP_SIGNALS[sig]
    name = signal.Signals(sig).name
    outcomes = []
    for k, delay in enumerate(delays):
        log = tmp_path / f"{exe}_{k}.log"
        with open(log, "w") as fh:
            p = subprocess.Popen([str(BIN / exe), *args], stdout=fh, stderr=subprocess.STDOUT,
                                 env=_env(domain, tmp_path))
            _wait_until_start_up_handles_signals(p)
            time.sleep(delay)
            p.send_signal(sig)
            rc = p.wait(timeout=30)
        out = log.read_text()
        outcomes.append(rc)
        assert "Traceback" not in out and "terminate called" not in out, f"{name} after {delay} s:\n{out}"
        if rc == status:
            assert out.splitlines()[-1] == f"{exe}: {line}", out
        else:
            assert rc == 0 and f"stopped by {name}" in out, f"{name} after {delay} s: rc {rc}\n{out}"
    assert outcomes[0] == status, outcomes  # (sent as soon as start-up handled signals)
    print(f"{exe}: exit statuses after {name} {outcomes}")


def _ignore_sigint() -> None:  # in the child: as a shell script's `node &` starts it
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def test_a_node_started_with_sigint_ignored_still_stops_on_it_at_start_up(tmp_path, domain):
    """A node whose parent left SIGINT ignored (a background job of a shell script) takes it over
    in start-up as it does once it runs: a SIGINT then ends it (130, one line); it was ignored
    until the node spun, so an early stop left an agent waiting for a board for ever."""
    outcomes = []
    for k, delay in enumerate((0.0, 0.3)):
        log = tmp_path / f"agent_{k}.log"
        with open(log, "w") as fh:
            p = subprocess.Popen([str(BIN / "agent_node"), "--ros-args", "-p", "robot:=robot_0"], stdout=fh,
                                 stderr=subprocess.STDOUT, env=_env(domain, tmp_path), preexec_fn=_ignore_sigint)
            try:
                _wait_until_start_up_handles_signals(p)
                time.sleep(delay)
                p.send_signal(signal.SIGINT)
                rc = p.wait(timeout=30)
            finally:
                if p.poll() is None:
                    p.kill()
        out = log.read_text()
        outcomes.append(rc)
        assert "Traceback" not in out and ((rc == 130 and out.splitlines()[-1] == "agent_node: interrupted during "
                                            "start-up") or (rc == 0 and "stopped by SIGINT" in out)), (delay, rc, out)
    assert outcomes[0] == 130, outcomes


@pytest.mark.parametrize("exe,module,args", [
    ("task_board", "hmrta_coordinator.task_board", ["--ros-args", "-p", f"instance:={EXAMPLE}"]),
    ("agent_node", "hmrta_agent.agent_node", ["--ros-args", "-p", "robot:=robot_0"]),
])
def test_a_node_as_hmrta_mission_starts_it_says_a_ctrl_c_at_start_up_in_one_line(exe, module, args, tmp_path, domain):
    """hmrta-mission's children (``python -m hmrta_msgs_py.run_node``, SIGINT ignored until its
    first line): a Ctrl-C in their first second left a KeyboardInterrupt traceback in their logs
    when they were started as ``python -m MODULE``. (One lost while the interpreter starts is
    followed by the launcher's SIGTERM.) The first Ctrl-C comes as soon as ``run_node`` handles
    signals (always start-up), the others at moments after that: none is lost."""
    from hmrta_coordinator.mission import _die_with_parent

    outcomes = []
    for k, delay in enumerate((0.0, 0.1, 0.2, 0.35, 0.5, 0.7, 0.9, 1.2)):
        log = tmp_path / f"{exe}_{k}.log"
        with open(log, "w") as fh:
            p = subprocess.Popen([sys.executable, "-u", "-m", "hmrta_msgs_py.run_node", exe, module, *args], stdout=fh,
                                 stderr=subprocess.STDOUT, env=_env(domain, tmp_path), preexec_fn=_die_with_parent)
            _wait_until_start_up_handles_signals(p)
            time.sleep(delay)
            p.send_signal(signal.SIGINT)
            rc = p.wait(timeout=30)
        out = log.read_text()
        outcomes.append(rc)
        assert "Traceback" not in out and "terminate called" not in out, f"SIGINT after {delay} s:\n{out}"
        assert (rc == 130 and out.splitlines()[-1] == f"{exe}: interrupted during start-up") or (
            rc == 0 and "stopped by SIG" in out), f"SIGINT after {delay} s: rc {rc}\n{out}"
    assert outcomes[0] == 130, outcomes
    print(f"{exe}: exit statuses {outcomes}")


# ---- 2. malformed --ros-args ------------------------------------------------------------------
@pytest.mark.parametrize("exe", NODES)
@pytest.mark.parametrize("args,says", [
    (["-p", "seed"], "cannot parse '-p seed': expected -p NAME:=VALUE"),
    (["-p", "seed:="], "cannot parse '-p seed:=': expected -p NAME:=VALUE"),
    (["-r", "__ns:=robot_1"], "-r __ns:=robot_1: expected an absolute namespace such as /robot_1"),
    (["-r", "__ns:=/robot_1/"], "-r __ns:=/robot_1/: expected a namespace such as /robot_1"),
    (["--params-file", "/no/such/params.yaml"], "cannot parse '--params-file /no/such/params.yaml': expected"),
    (["-r", "goal_pose"], "cannot parse '-r goal_pose': expected -r FROM:=TO"),
    (["-p", "pose_types:=[robot_0:Odometry,robot_1:Odometry]"],  # unquoted: not YAML rcl can read
     """entries with a colon need quotes: -p 'pose_types:=["robot_0:Odometry", "robot_1:Odometry"]'"""),
])
def test_malformed_ros_args_are_one_line_user_errors(exe, args, says, tmp_path, domain):
    r = subprocess.run([str(BIN / exe), "--ros-args", *args], capture_output=True, text=True, timeout=60,
                       env=_env(domain, tmp_path))
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert r.stderr.count("\n") == 1 and r.stderr.startswith(f"{exe}: --ros-args: ") and says in r.stderr, r.stderr
    assert r.stdout == ""


# ---- 4. parameters of the wrong type ----------------------------------------------------------
@pytest.mark.parametrize("exe,arg,says", [
    ("task_board", "scale:=2", "scale: expected a decimal number, got 2 (an integer); write it with a decimal "
                               "point: -p scale:=2.0"),
    ("task_board", "seed:=1.5", "seed: expected an integer, got 1.5 (a decimal number)"),
    ("task_board", "queue_depth:=lots", "queue_depth: expected an integer, got lots (a string)"),
    ("task_board", "wait_for_robots:=3", "wait_for_robots: expected a boolean (true or false), got 3 (an integer)"),
    ("task_board", "frame_id:=true", "frame_id: expected a string, got true (a boolean); quote it"),
    ("agent_node", "robot:=7", "robot: expected a string, got 7 (an integer); quote it"),
    ("sim_robot", "time_scale:=1", "time_scale: expected a decimal number, got 1 (an integer); write it"),
])
def test_a_parameter_of_the_wrong_type_says_what_was_expected(exe, arg, says, tmp_path, domain):
    extra = ["-p", f"instance:={EXAMPLE}"] if exe == "task_board" else []
    r = subprocess.run([str(BIN / exe), "--ros-args", *extra, "-p", arg], capture_output=True, text=True,
                       timeout=60, env=_env(domain, tmp_path))
    assert r.returncode == 2 and r.stderr.startswith(f"{exe}: {says}"), r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    # the decimal-point hint only where it helps: a double parameter given an integer
    assert ("decimal point" in r.stderr) == ("expected a decimal number, got" in says and "(an integer)" in says)


# ---- 3. unknown parameters, 5. pose_types of strangers, 6. a board stopped by SIGTERM --------
def test_unknown_parameters_are_warned_with_the_closest_name(tmp_path, start):
    params = tmp_path / "params.yaml"
    params.write_text("task_board:\n  ros__parameters:\n    progres_period: 1.0\n")
    board = start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}", "-p", "methd:=rl",
                  "-p", 'pose_types:=["robot_99:Odometry", "robot_1:Odometry"]', "--params-file", str(params),
                  "-p", "real_time_departures:=true",  # real robots on the default 1 m x 1 m area
                  "-p", "method:=greedy", "-p", "candidates:=rl")  # an option the method does not take
    agent = start("agent_node", "--ros-args", "-p", "robot:=robot_0", "-p", "temprature:=0.2",
                  "-p", "instance:=x.yaml", "-p", "use_sim_time:=true")
    board.wait_for("unknown parameter 'progres_period'", 60)
    agent.wait_for("unknown parameter 'temprature'", 60)
    assert board.stop(signal.SIGTERM) == 0 and agent.stop(signal.SIGINT) == 0
    b, a = board.text(), agent.text()
    assert "unknown parameter 'methd' ignored: /task_board has no such parameter; did you mean method?" in b, b
    assert "unknown parameter 'progres_period' ignored" in b and "did you mean progress_period?" in b, b
    assert "method greedy takes no candidates: it is ignored" in b, b
    assert "pose_types: 'robot_99' is not a robot of the mission" in b and "'robot_1' is not" not in b, b
    assert "its robots are robot_0, robot_1" in b
    assert "arrival_tolerance 0.25 m is 25% of the mission area's side (scale 1 m per mission unit)" in b, b
    assert "stopped by SIGTERM before the mission finished: t=0.000, 0/20 tasks done" in b, b
    assert "did you mean temperature?" in a and "unknown parameter 'instance' ignored" in a, a
    assert "(instance is a parameter of task_board)" in a and "stopped by SIGINT" in a, a
    assert "use_sim_time:=true changes nothing here: the mission runs on its own clock" in a, a
    assert "use_sim_time" not in b  # (not given to the board)
    assert "Traceback" not in a + b


# ---- 6. exit statuses -------------------------------------------------------------------------
def test_a_board_whose_mission_failed_exits_3(tmp_path, start):
    """No agent ever answers: every robot is dropped, no task can be done, the mission fails."""
    inst = save_instance(ScenarioGenerator("SA-AT", 4, 2, 4, 2).instance(0, 0), tmp_path / "small.yaml")
    out = tmp_path / "result.json"
    board = start("task_board", "--ros-args", "-p", f"instance:={inst}", "-p", "wait_for_robots:=false",
                  "-p", "heartbeat_timeout:=0.5", "-p", f"output:={out}")
    assert board.proc.wait(timeout=60) == 3, board.text()
    assert "mission failed: 4 task(s) cancelled" in board.text() and "(exit status 3)" in board.text()
    assert out.exists()


def test_agents_that_refuse_to_take_part_exit_2(tmp_path, start):
    board = start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}")
    agents = {"species": start("agent_node", "--ros-args", "-p", "robot:=robot_0", "-p", "species:=1",
                               name="species"),
              "rules": start("agent_node", "--ros-args", "-p", "robot:=robot_1", "-p", "method:=random", name="rules"),
              "joining": start("agent_node", "--ros-args", "-r", "__ns:=/robot_new", "-p", "species:=1",
                               "-p", "method:=random", name="joining"),
              "index": start("agent_node", "--ros-args", "-p", "robot:=robot_3", "-p", "index:=5", name="index")}
    says = {"species": "robot 'robot_0' is species 1 but the mission lists it as species 0: not taking part",
            "rules": "robot_1: method random but mission example runs rl@coalition-team",  # (the board's choice)
            "joining": "robot_new: method random but mission example runs",
            "index": "robot 'robot_3' (index 5) is not in mission example"}
    for k, p in agents.items():
        assert p.proc.wait(timeout=60) == 2, (k, p.text())
        assert says[k] in p.text() and "stopping (exit status 2)" in p.text(), (k, p.text())
    # the robots of the mission whose agents refused: the board says why at once, and waits on for
    # the others (robot_new is not in the mission; robot_3's agent took index 5, another robot's)
    for k, robot in (("species", "robot_0"), ("rules", "robot_1")):
        board.wait_for(f"robot '{robot}': its agent refuses the mission: {says[k]}", 30)
    assert "robot 'robot_3': its agent refuses" not in board.text() and "robot_new" not in board.text()
    assert board.proc.poll() is None
    assert board.stop(signal.SIGTERM) == 0


def test_a_board_whose_every_robot_is_refused_by_its_agent_fails_at_once(tmp_path, start):
    """Agents that refuse the mission tell the board before they stop: once every robot's agent
    has refused, the board starts without them and the mission fails, naming the reason, without
    waiting out its start-up timeout (120 s here)."""
    inst = save_instance(ScenarioGenerator("SA-AT", 2, 2, 3, 2).instance(0, 0), tmp_path / "two.yaml")
    out = tmp_path / "result.json"
    board = start("task_board", "--ros-args", "-p", f"instance:={inst}", "-p", "method:=greedy",
                  "-p", f"output:={out}", "-p", "startup_timeout:=120.0")
    agents = [start("agent_node", "--ros-args", "-p", f"robot:=robot_{a}", "-p", "method:=random", name=f"a{a}")
              for a in range(2)]
    t0 = time.monotonic()
    assert board.proc.wait(timeout=90) == 3, board.text()
    assert time.monotonic() - t0 < 90  # (not the start-up timeout)
    for p in agents:
        assert p.proc.wait(timeout=30) == 2, p.text()
    text = board.text()
    assert "the agents of every robot refuse the mission: it starts without them" in text, text
    assert ("2 of 2 robot(s) refused by their agents (robot_0, robot_1), robot_0's saying: robot_0: method random "
            "but mission ") in text and " runs greedy: not taking part" in text, text
    result = json.loads(out.read_text())
    assert result["lost_robots"] == ["robot_0", "robot_1"] and not result["success"]
    assert result["lost_reasons"]["robot_1"].startswith("its agent refused the mission: robot_1: method random")


# ---- 7. no board heard ------------------------------------------------------------------------
def test_no_board_heard_and_a_board_gone_silent_are_warned(tmp_path, start):
    # (3 s: a board repeats itself every 0.25 s; a loaded machine can stall a process for a second)
    agent = start("agent_node", "--ros-args", "-p", "robot:=robot_0", "-p", "board_silence_warning:=3.0")
    sim = start("sim_robot", "--ros-args", "-p", "board_silence_warning:=3.0")
    for p in (agent, sim):
        p.wait_for("no task board heard for ", 60)  # (the seconds it has waited: 3 or more)
        assert "a task board is heard" not in p.text()
    assert "ROS_DOMAIN_ID" in agent.text() and "ROS_AUTOMATIC_DISCOVERY_RANGE (LOCALHOST)" in agent.text()
    assert "nothing on /hmrta/mission or /hmrta/board" in agent.text() and "mission_namespace (/)" in agent.text()
    assert "A mission that is over has no board" in agent.text()  # a robot joining a mission that ended
    board = start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}", "-p", "wait_for_robots:=true")
    agent.wait_for("robot_0: agent 0 (species 0) of mission example", 60)
    sim.wait_for("simulating 15 robot(s)", 60)
    for p in (agent, sim):  # the silence warned of ends, and they say so
        p.wait_for("a task board is heard, after ", 30)
    time.sleep(2.0)  # heard all along: no warning
    for p in (agent, sim):
        assert "has not been heard" not in p.text(), p.text()
    board.kill()  # as if it crashed
    for p in (agent, sim):
        p.wait_for("the task board has not been heard for ", 30)
        assert "heard again" not in p.text()
    board = start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}", "-p", "wait_for_robots:=true")
    for p in (agent, sim):  # (a board without the journal: what they hear is another session)
        p.wait_for("the task board is heard again after ", 60)
        assert p.stop() == 0 and "Traceback" not in p.text()
    board.kill()


def test_a_node_in_another_mission_namespace_than_the_board_is_told_where_the_board_is(tmp_path, start):
    """A board in the root namespace, an agent and a sim_robot given mission_namespace /f1: they
    hear no board, and the warning names their own topics and the namespace a board publishes in."""
    board = start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}", name="board")
    agent = start("agent_node", "--ros-args", "-r", "__ns:=/f1/robot_0", "-p", "mission_namespace:=/f1",
                  "-p", "board_silence_warning:=3.0", name="agent")
    sim = start("sim_robot", "--ros-args", "-p", "mission_namespace:=/f1", "-p", "board_silence_warning:=3.0",
                name="sim")
    for p in (agent, sim):  # (a warning due before discovery found the board does not name it yet: a later one does)
        p.wait_for("a board publishes in mission namespace /: is this node's mission_namespace right?", 60)
        assert "(nothing on /f1/hmrta/mission or /f1/hmrta/board)" in p.text() and "mission_namespace (/f1)" in p.text()
        assert p.stop() == 0
    assert board.stop(signal.SIGTERM) == 0


def test_a_second_mission_in_the_same_mission_namespace_is_refused(tmp_path, start):
    """A second task board in a mission namespace where a mission was created first (its latched
    mission message, another session) stops at once with exit status 2 and says why, also while
    the first still waits for its robots (neither has started); the first warns and goes on."""
    first = start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}", "-p", "mission_namespace:=/f1",
                  "-p", "exit_on_done:=false", name="first")
    first.wait_for("waiting for every robot's agent and pose", 60)
    second = start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}", "-p", "mission_namespace:=/f1",
                   "-p", "exit_on_done:=false", name="second")
    assert second.proc.wait(timeout=60) == 2, second.text()
    says = "in mission namespace /f1 on this ROS domain: two missions in one mission namespace mix"
    assert says in second.text() and "this board gives way; stopping (exit status 2)" in second.text()
    assert "Traceback" not in second.text()
    first.wait_for(says, 60)
    assert first.proc.poll() is None
    assert first.stop(signal.SIGTERM) == 0


def test_a_namespace_that_would_not_keep_missions_apart_is_refused(tmp_path, start):
    """The mission's topics are absolute names in its mission namespace: a board or sim_robot in a
    node namespace, or --robots moved into one namespace, would mix with another mission on the
    domain; a mission namespace that is not one is refused too; each is one line, exit 2."""
    procs = {"board": start("task_board", "--ros-args", "-p", f"instance:={EXAMPLE}", "-r", "__ns:=/fleet1",
                            name="board"),
             "sim": start("sim_robot", "--ros-args", "-r", "__ns:=/fleet1", name="sim"),
             "agents": start("agent_node", "--robots", "robot_0,robot_1", "--ros-args", "-r", "__ns:=/fleet1",
                             name="agents"),
             "both": start("sim_robot", "--ros-args", "-p", "robots:=[robot_1]", "-p", "external:=[robot_1]",
                           name="both"),
             "bad": start("agent_node", "--robots", "robot_0", "--ros-args", "-p", "mission_namespace:=fleet 1",
                          name="bad")}
    says = {"board": "namespace /fleet1: the task board takes no node namespace",
            "sim": "namespace /fleet1: sim_robot takes no node namespace",
            "agents": "--robots: each robot's agent runs in its own namespace (/robot_0/agent), but -r __ns:= moved "
                      "it to /fleet1",
            "both": "robots and external both name robot_1",
            "bad": "mission_namespace: expected an absolute ROS namespace such as / or /fleet1, got 'fleet 1'"}
    for k, p in procs.items():
        assert p.proc.wait(timeout=60) == 2, (k, p.text())
        assert says[k] in p.text() and "Traceback" not in p.text(), (k, p.text())


def test_an_agent_whose_robot_driver_never_listens_says_why_and_ends_with_the_mission(tmp_path, start):
    """robot_1 is external and its driver never subscribes to the agent's goal topic: the agent
    says what it waits for, and ends when the board drops the robot and the mission is over."""
    inst = save_instance(ScenarioGenerator("SA-AT", 4, 2, 4, 2).instance(0, 0), tmp_path / "small.yaml")
    board = start("task_board", "--ros-args", "-p", f"instance:={inst}", "-p", "startup_timeout:=20.0")
    sim = start("sim_robot", "--ros-args", "-p", "external:=[robot_1]")
    agents = start("agent_node", "--robots", "robot_0,robot_2,robot_3", name="agents")
    agent = start("agent_node", "--ros-args", "-r", "__ns:=/robot_1", "-r", "goal_pose:=/tb3_1/goal_pose",
                  name="agent1")
    agent.wait_for("waiting for a subscriber to its goal topic /tb3_1/goal_pose", 60)
    assert "robot_1: not taking part yet after " in agent.text()
    for p in (board, sim, agents, agent):
        assert p.proc.wait(timeout=90) in (0, 3), (p.exe, p.text())
    assert "Traceback" not in agent.text()


def test_hmrta_mission_takes_a_failed_mission_from_the_board_without_restarting_it(tmp_path, domain):
    """A scenario loses every robot: the board finishes, fails and exits 3; the launcher reports
    the failed mission (exit 3) and restarts nothing (the journal is on)."""
    inst = save_instance(ScenarioGenerator("SA-AT", 4, 2, 4, 2).instance(0, 0), tmp_path / "small.yaml")
    sc = tmp_path / "scenario.yaml"
    sc.write_text("format: hmrta-scenario/1\n"
                  f"instance: {str(inst)!r}\n"
                  "events:\n" + "".join(f"  - {{t: 0.01, type: lose_robot, robot: {a}}}\n" for a in range(4)))
    out = tmp_path / "mission.json"
    r = subprocess.run([str(BIN / "hmrta-mission"), "--scenario", str(sc), "--method", "greedy", "--out", str(out),
                        "--quiet", "--no-plot", "--domain-id", str(domain), "--agents-per-process", "4",
                        "--timeout", "120"], capture_output=True, text=True, timeout=180,
                       env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert r.returncode == 3, r.stdout + r.stderr
    assert "restarted" not in r.stdout + r.stderr and "board process died" not in r.stdout + r.stderr
    board_log = (tmp_path / "mission_logs" / "task_board.log").read_text()
    assert "mission failed: " in board_log and "exit status 3" in board_log, board_log[-2000:]
    assert out.exists()
