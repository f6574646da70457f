"""hmrta_msgs_py.console: the body of every console script. A Ctrl-C while a node module loads
rclpy, numpy or torch ends the process with one line and status 130, never a traceback."""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

SRC = Path(__file__).resolve().parents[2] / "ros2_ws" / "src"
HEAVY = ("rclpy", "numpy", "torch", "std_msgs", "hmrta")  # what a node module loads at the top


def declared_scripts() -> list[tuple[str, str, str, str]]:
    """(package, script, module, function) of every console script in the packages' setup.py."""
    out = []
    for setup in sorted(SRC.glob("*/setup.py")):
        for n in ast.walk(ast.parse(setup.read_text())):
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and " = " in n.value and ":" in n.value:
                name, target = (s.strip() for s in n.value.split(" = "))
                module, func = target.split(":")
                out.append((setup.parent.name, name, module, func))
    return out


def run_python(code: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, **env))


def test_every_console_script_goes_through_a_light_entry_module():
    scripts = declared_scripts()
    assert {s[1] for s in scripts} >= {"agent_node", "task_board", "sim_robot", "recorder", "hmrta-mission",
                                        "mission", "hmrta-task"}
    for pkg, name, module, func in scripts:
        assert module == f"{pkg}.entry", f"{name}: {module} (expected {pkg}.entry)"
        # what the generated script imports before it calls anything: nothing heavy
        probe = (f"import sys; from {module} import {func}; "
                 f"print(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r}))")
        out = run_python(probe)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == "[]", f"{name}: importing {module} loads {out.stdout.strip()}"


def test_ctrl_c_while_the_node_module_loads_is_one_line_and_130(tmp_path):
    # a node module whose imports are interrupted (deterministic: it raises what Ctrl-C raises)
    (tmp_path / "interrupted_node.py").write_text("raise KeyboardInterrupt\n")
    out = run_python("from hmrta_msgs_py.console import run; run('some_node', 'interrupted_node')",
                     PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    assert out.returncode == 130
    assert out.stderr == "some_node: interrupted during start-up\n" and "Traceback" not in out.stdout


def test_an_extension_interrupted_while_it_initialises_is_one_line_and_130(tmp_path):
    # pybind11 turns a Ctrl-C inside an extension's initialisation into an ImportError caused by it
    (tmp_path / "ext_node.py").write_text(
        "try:\n    raise KeyboardInterrupt\nexcept KeyboardInterrupt as e:\n"
        "    raise ImportError('initialization failed') from e\n")
    (tmp_path / "broken_node.py").write_text("raise ImportError('no module named nothing')\n")
    env = {"PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    out = run_python("from hmrta_msgs_py.console import run; run('some_node', 'ext_node')", **env)
    assert out.returncode == 130 and out.stderr == "some_node: interrupted during start-up\n"
    # an ImportError of its own is not hidden
    out = run_python("from hmrta_msgs_py.console import run; run('some_node', 'broken_node')", **env)
    assert out.returncode == 1 and "ImportError: no module named nothing" in out.stderr


def test_an_interrupt_inside_an_extensions_own_python_code_still_ends_with_130(tmp_path):
    """rclpy's pybind11 module runs Python code with ``PyRun_String`` while it loads: a Ctrl-C
    there left CPython's note of an unhandled KeyboardInterrupt set although start-up handled it,
    and a node started as ``python -m hmrta_msgs_py.run_node`` (by hmrta-mission) then died of
    SIGINT (-2) after its one line. Deterministic: the module raises it through PyRun_String."""
    (tmp_path / "pyrun_node.py").write_text(
        "import ctypes\nrun = ctypes.pythonapi.PyRun_String\nrun.restype = ctypes.py_object\n"
        "run.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]\n"
        "run(b'raise KeyboardInterrupt', 257, {'__builtins__': __builtins__}, {})\n")
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    out = subprocess.run([sys.executable, "-m", "hmrta_msgs_py.run_node", "some_node", "pyrun_node"],
                         capture_output=True, text=True, timeout=60, env=env)
    assert (out.returncode, out.stderr) == (130, "some_node: interrupted during start-up\n")


def test_run_exits_with_what_main_returns(tmp_path):
    (tmp_path / "node_a.py").write_text("def main():\n    return 3\n")
    (tmp_path / "node_b.py").write_text("def main():\n    print('ran')\n")
    env = {"PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    assert run_python("from hmrta_msgs_py.console import run; run('a', 'node_a')", **env).returncode == 3
    b = run_python("from hmrta_msgs_py.console import run; run('b', 'node_b')", **env)
    assert b.returncode == 0 and b.stdout == "ran\n"


def test_a_ctrl_c_that_a_library_swallows_during_start_up_still_ends_it(tmp_path):
    """A library that catches what its imports raise (an optional extension's ImportError, a bare
    except) may swallow the KeyboardInterrupt of a Ctrl-C: start-up notes every Ctrl-C and ends
    with one line and 130 all the same, while the module loads or while its nodes are built."""
    swallow = ("import os, signal, time\ntry:\n    os.kill(os.getpid(), signal.SIGINT)\n    time.sleep(1.0)\n"
               "except BaseException:\n    pass\n")
    (tmp_path / "swallowing_import.py").write_text(swallow + "def main():\n    print('ran')\n")
    (tmp_path / "swallowing_build.py").write_text(
        "from hmrta_msgs_py.runtime import starting\n\ndef main():\n    with starting('some_node'):\n"
        + "".join("        " + line + "\n" for line in swallow.splitlines()) + "    print('spun')\n")
    env = {"PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    for module in ("swallowing_import", "swallowing_build"):
        out = run_python(f"from hmrta_msgs_py.console import run; run('some_node', '{module}')", **env)
        assert (out.returncode, out.stderr, out.stdout) == (130, "some_node: interrupted during start-up\n", ""), \
            (module, out)


def test_a_logger_half_built_when_the_signal_came_says_nothing_at_exit():
    """A SIGINT inside rclpy's RcutilsLogger.__init__ (seen in a start-up signal test) leaves a
    logger whose finalizer fails at exit: "Exception ignored ... Traceback" after the one line.
    Once a process was stopped, that failure is not reported; any other unraisable exception is."""
    code = ("import sys\n"
            "from rclpy.impl.rcutils_logger import RcutilsLogger\n"
            "if sys.argv[1] == 'stopped':\n"
            "    from hmrta_msgs_py.console import quiet_half_built_loggers\n"
            "    quiet_half_built_loggers(); quiet_half_built_loggers()\n"
            "o = RcutilsLogger.__new__(RcutilsLogger)\n"  # as an interrupted __init__ leaves it
            "del o\n"
            "class Other:\n"
            "    def __del__(self): raise AttributeError('other')\n"
            "x = Other(); del x\n")
    for mode, loggers in (("running", 1), ("stopped", 0)):
        err = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True, timeout=60).stderr
        assert err.count("RcutilsLogger.__del__") == loggers and err.count("Other.__del__") == 1, (mode, err)


def test_a_start_up_signal_inside_a_deferred_block_is_raised_when_it_ends():
    """console.signals_deferred (around torch's import, which a KeyboardInterrupt raised inside
    aborts in C++): the signal is noted, the block finishes, then KeyboardInterrupt is raised."""
    code = ("import os, signal\n"
            "from hmrta_msgs_py import console\n"
            "signal.signal(signal.SIGTERM, console._noted)\n"
            "signal.signal(signal.SIGINT, console._noted)\n"
            "try:\n"
            "    with console.signals_deferred():\n"
            "        os.kill(os.getpid(), signal.SIGTERM)\n"
            "        print('block finished', flush=True)\n"
            "    print('not reached', flush=True)\n"
            "except KeyboardInterrupt:\n"
            "    print('interrupted after the block', console.INTERRUPTED == [signal.SIGTERM], flush=True)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stdout
    assert out.splitlines() == ["block finished", "interrupted after the block True"], out


def test_a_signal_right_after_the_start_up_warnings_stops_a_running_node(tmp_path):
    """spin_nodes warns about unknown parameters as the nodes start to spin; a supervisor (or a
    test) that sends SIGTERM as soon as it reads that warning gets a running node's stop (the
    stop line, exit 0), never a start-up interruption (exit 143), whatever the scheduling."""
    (tmp_path / "warned_node.py").write_text(
        "import os, signal\n"
        "import rclpy\n"
        "from hmrta_msgs_py import runtime\n"
        "from hmrta_msgs_py.runtime import spin_nodes, starting\n"
        "def warn(nodes):\n"  # the warnings, then the supervisor's signal at once
        "    print('warned', flush=True)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "runtime.warn_unknown_parameters = warn\n"
        "def main():\n"
        "    with starting('some_node', args=['some_node']):\n"
        "        node = rclpy.create_node('some_node', enable_rosout=False, start_parameter_services=False)\n"
        "    sig = spin_nodes([node], stopped=lambda s: f'stopped by {s} while waiting')\n"
        "    print('spin returned', sig, flush=True)\n"
        "    return 0\n")
    out = run_python("from hmrta_msgs_py.console import run; run('some_node', 'warned_node')",
                     PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
                     ROS_DOMAIN_ID="97", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    assert out.returncode == 0, (out.returncode, out.stdout, out.stderr)
    assert out.stdout.splitlines() == ["warned", "spin returned SIGTERM"], out.stdout
    assert "stopped by SIGTERM while waiting" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_sigusr1_prints_every_threads_stack_and_the_process_goes_on(tmp_path):
    """A node that seems stuck says where: ``kill -USR1 PID`` dumps its Python stacks on stderr."""
    import signal
    import time

    import threading

    (tmp_path / "sleepy_node.py").write_text(  # blocked on line 4 until the test writes a line
        "import sys\ndef main():\n    print('up', flush=True)\n    sys.stdin.readline()\n    return 0\n")
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    p = subprocess.Popen([sys.executable, "-c", "from hmrta_msgs_py.console import run; run('some_node', 'sleepy_node')"],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(p.stderr.readline, "")), daemon=True)
    try:
        assert p.stdout.readline() == "up\n"
        reader.start()
        p.send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + 30.0
        while not any("in main" in line for line in lines) and time.monotonic() < deadline:
            time.sleep(0.05)
        p.stdin.write("go on\n")  # the dump is on stderr: let the node finish
        p.stdin.close()
        p.wait(timeout=30)
        reader.join(timeout=10)
    finally:
        if p.poll() is None:
            p.kill()
    err = "".join(lines)
    assert p.returncode == 0, err
    assert "most recent call first" in err and "sleepy_node.py\", line 4 in main" in err, err


def test_a_fatal_signal_prints_where_before_the_process_dies(tmp_path):
    """A crash in native code (the middleware's segmentation fault) leaves the Python stack of
    every thread on stderr, the node's log, and the process still dies of its signal (a
    supervisor sees the same status)."""
    import signal

    (tmp_path / "crashing_node.py").write_text(
        "import os, signal\n"
        "def crash_in_native_code():\n"
        "    os.kill(os.getpid(), signal.SIGSEGV)\n"
        "def main():\n"
        "    crash_in_native_code()\n"
        "    return 0\n")
    out = run_python("from hmrta_msgs_py.console import run; run('some_node', 'crashing_node')",
                     PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
                     PYTHONFAULTHANDLER="")
    assert out.returncode == -signal.SIGSEGV, (out.returncode, out.stderr)
    assert "Fatal Python error: Segmentation fault" in out.stderr, out.stderr
    assert 'crashing_node.py", line 3 in crash_in_native_code' in out.stderr, out.stderr


@pytest.mark.parametrize("where,status", [("destroy_node", 3), ("exit", 3), ("crash", 1), ("gil", 1)])
def test_a_teardown_that_hangs_ends_the_process_with_its_status(tmp_path, where, status):
    """Once a console script's nodes have stopped, the rest of its life is bounded: a teardown that
    hangs (a node's destroy_node, a non-daemon thread the interpreter waits for at exit, a call
    into C that holds the interpreter's lock at exit) ends the process after
    HMRTA_TEARDOWN_TIMEOUT seconds with the status it would have had (here 3), printing where it
    hung; 1 after a crash (its traceback printed too), and 1 where no Python code can run (the
    backstop, FINAL_GRACE seconds later). The mission's work is done by then."""
    import time

    (tmp_path / "stuck_node.py").write_text(
        "import atexit, re, threading, time\n"
        "import rclpy\n"
        "from rclpy.node import Node\n"
        "from rclpy.task import Future\n"
        "from hmrta_msgs_py.runtime import spin_nodes, starting\n"
        f"WHERE = {where!r}\n"
        "class Stuck(Node):\n"
        "    def destroy_node(self):\n"
        "        if WHERE in ('destroy_node', 'crash'):\n"
        "            time.sleep(3600)\n"
        "        return super().destroy_node()\n"
        "def boom():\n"
        "    raise RuntimeError('boom in a callback')\n"
        "def main():\n"
        "    with starting('stuck_node', args=['stuck_node']):\n"
        "        node = Stuck('stuck_node', enable_rosout=False, start_parameter_services=False)\n"
        "    done = Future()\n"
        "    node.create_timer(0.2, boom if WHERE == 'crash' else lambda: done.set_result(True))\n"
        "    spin_nodes([node], until=done, exit_status=lambda: 3)\n"
        "    if WHERE == 'exit':\n"
        "        threading.Thread(target=time.sleep, args=(3600,), name='left_running').start()\n"
        "    if WHERE == 'gil':  # a regular expression that backtracks for ages, holding the lock\n"
        "        atexit.register(re.fullmatch, '(a|aa)+b', 'a' * 80)\n"
        "    print('finished', flush=True)\n"
        "    return 3\n")
    t0 = time.monotonic()
    out = run_python("from hmrta_msgs_py.console import run; run('stuck_node', 'stuck_node')",
                     PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
                     ROS_DOMAIN_ID="96", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", HMRTA_TEARDOWN_TIMEOUT="2")
    assert out.returncode == status, (out.returncode, out.stdout, out.stderr)
    assert time.monotonic() - t0 < 50
    if where == "gil":  # the backstop: faulthandler's, 2 + 5 s
        assert out.stdout == "finished\n" and "Timeout (0:00:07)!" in out.stderr, out.stderr
        return
    assert "stuck_node: still shutting down 2 s after its nodes stopped" in out.stderr, out.stderr
    assert f"exiting with status {status}" in out.stderr
    if where == "exit":
        assert out.stdout == "finished\n", out.stdout  # main returned; the interpreter waited at exit
    else:
        assert "finished" not in out.stdout and "in destroy_node" in out.stderr, out.stderr
    if where == "crash":
        assert "it had crashed:" in out.stderr and "RuntimeError: boom in a callback" in out.stderr


@pytest.mark.parametrize("drain", [0.0, 3.0])
def test_a_stopped_node_takes_what_it_already_received_when_asked_to_drain(tmp_path, drain, graph):
    """``spin_nodes(drain=S)``: on SIGTERM the messages already in the node's reader are taken
    (what the recorder asks for, so that a stopped recording keeps them); without it the spin
    ends after the callback that runs. A slow callback (0.2 s a message) leaves a backlog when
    the signal comes, as the first message is taken."""
    import signal
    import threading
    import time

    from std_msgs.msg import String

    from hmrta_msgs_py import topics

    (tmp_path / "slow_node.py").write_text(
        "import time\n"
        "import rclpy\n"
        "from std_msgs.msg import String\n"
        "from hmrta_msgs_py import topics\n"
        "from hmrta_msgs_py.runtime import spin_nodes, starting\n"
        "def main():\n"
        "    got = []\n"
        "    with starting('slow_node', args=['slow_node']):\n"
        "        node = rclpy.create_node('slow_node', enable_rosout=False, start_parameter_services=False)\n"
        "        def take(m):\n"
        "            got.append(m.data)\n"
        "            print('took', m.data, flush=True)\n"
        "            time.sleep(0.2)\n"
        "        node.create_subscription(String, '/slow', take, topics.CHOICE_QOS)\n"
        "    print('up', flush=True)\n"
        f"    spin_nodes([node], on_exit=lambda: print('got', len(got), flush=True), drain={drain})\n"
        "    return 0\n")
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
               ROS_DOMAIN_ID=str(graph.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               HMRTA_EXECUTOR="single")  # (the recorder's)
    p = subprocess.Popen([sys.executable, "-c", "from hmrta_msgs_py.console import run; run('slow_node', 'slow_node')"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(p.stdout.readline, "")), daemon=True)
    reader.start()
    try:
        pub = graph.node("sender").create_publisher(String, "/slow", topics.CHOICE_QOS)
        graph.spin_until(lambda: p.poll() is not None or (lines and pub.get_subscription_count() > 0), 60,
                         "the slow node to start and subscribe")
        time.sleep(0.5)  # (the reader's side of the matching)
        for i in range(8):  # (a burst: all in the node's reader within milliseconds)
            pub.publish(String(data=str(i)))
        graph.spin_until(lambda: p.poll() is not None or "took 0\n" in lines, 60, "the first message taken")
        p.send_signal(signal.SIGTERM)  # the first message taken, seven waiting
        assert p.wait(timeout=60) == 0, p.stderr.read()
        reader.join(timeout=10)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    got = int(next(line for line in lines if line.startswith("got")).split()[1])
    if drain:
        assert got == 8, lines
    else:
        assert got < 8, lines
