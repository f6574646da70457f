"""Every executable's ``--help``: exits 0 at once, starts nothing, lists the node's ROS parameters;
and each node's parameter table (``hmrta_msgs_py.params``) is what the node really declares."""
from __future__ import annotations

import ast
import os
import random
import subprocess
import sys
from pathlib import Path

import pytest

from hmrta_msgs_py import params as P

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "ros2_ws" / "src"
BIN = Path(sys.executable).parent
NODE_SOURCES = {
    "task_board": SRC / "hmrta_coordinator" / "hmrta_coordinator" / "task_board.py",
    "sim_robot": SRC / "hmrta_coordinator" / "hmrta_coordinator" / "sim_robot.py",
    "agent_node": SRC / "hmrta_agent" / "hmrta_agent" / "agent_node.py",
    "recorder": SRC / "hmrta_coordinator" / "hmrta_coordinator" / "recorder.py",
}
_AST_TYPES = {bool: P.BOOL, int: P.INTEGER, float: P.DOUBLE, str: P.STRING}


def declared_parameters(source: Path) -> dict[str, tuple[str, object]]:
    """name -> (type, default) of every parameter a node source declares: ``declare_parameter(
    "name", default)`` calls (also through an alias such as ``P = self.declare_parameter``) and
    the method parameters when it calls ``declare_method_parameters``."""
    tree = ast.parse(source.read_text(), str(source))
    aliases = {t.id for n in ast.walk(tree) if isinstance(n, ast.Assign)
               and isinstance(n.value, ast.Attribute) and n.value.attr == "declare_parameter"
               for t in n.targets if isinstance(t, ast.Name)}
    out: dict[str, tuple[str, object]] = {}
    for n in ast.walk(tree):
        if not isinstance(n, ast.Call):
            continue
        f = n.func
        fname = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
        if fname == "declare_parameters":
            raise AssertionError(f"{source.name}: declare_parameters(...) is not understood by this test")
        if fname == "declare_method_parameters":
            out.update({p.name: (p.type, p.default) for p in P.method_parameters()})
        if not (fname == "declare_parameter" or (isinstance(f, ast.Name) and f.id in aliases)):
            continue
        assert n.args and isinstance(n.args[0], ast.Constant), f"{source.name}:{n.lineno}: parameter name not a literal"
        name, default = n.args[0].value, n.args[1] if len(n.args) > 1 else None
        if isinstance(default, ast.Attribute) and default.attr == "STRING_ARRAY":
            out[name] = (P.STRING_ARRAY, [])
        else:
            try:
                value = ast.literal_eval(default)
            except ValueError:
                raise AssertionError(f"{source.name}:{n.lineno}: default of {name!r} is not a literal") from None
            out[name] = (_AST_TYPES[type(value)], value)
    return out


@pytest.mark.parametrize("node", sorted(NODE_SOURCES))
def test_parameter_table_matches_the_node(node):
    declared = declared_parameters(NODE_SOURCES[node])
    table = {p.name: (p.type, p.default) for p in P.node_parameters(node)}
    assert len(table) == len(P.node_parameters(node)), f"{node}: a parameter is listed twice"
    missing, extra = sorted(set(declared) - set(table)), sorted(set(table) - set(declared))
    assert not missing, f"{node} declares {missing} but hmrta_msgs_py/params.py does not list them"
    assert not extra, f"hmrta_msgs_py/params.py lists {extra} but {node} does not declare them"
    for name, (typ, default) in declared.items():
        assert table[name] == (typ, default), f"{node}.{name}: declared {typ} {default!r}, table {table[name]}"
        assert P.by_name(P.node_parameters(node))[name].help, f"{node}.{name}: no meaning in the table"


def test_declared_parameters_sees_every_kind():
    """The AST reader finds literal, aliased, array and method declarations."""
    board = declared_parameters(NODE_SOURCES["task_board"])
    assert board["robot_names"] == (P.STRING_ARRAY, []) and board["scale"] == (P.DOUBLE, 1.0)
    assert board["method"] == (P.STRING, "portfolio") and "checkpoint" in board
    assert declared_parameters(NODE_SOURCES["agent_node"])["robot"] == (P.STRING, "")
    assert "method" not in declared_parameters(NODE_SOURCES["sim_robot"])


def _env() -> dict[str, str]:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(random.randint(200, 232)))
    return env


def _help(exe: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / exe), "--help", *extra], capture_output=True, text=True, timeout=60, env=_env())


@pytest.mark.parametrize("exe,node", [("task_board", "task_board"), ("sim_robot", "sim_robot"),
                                      ("agent_node", "agent_node"), ("recorder", "recorder"), ("mission", None),
                                      ("hmrta-mission", None)])
def test_help_lists_parameters_and_exits_0(exe, node):
    out = _help(exe)
    assert out.returncode == 0, f"{exe} --help exited {out.returncode}: {out.stderr[-2000:]}"
    text = out.stdout
    assert text.startswith("usage: "), text[:200]
    prog = text.split()[1]
    assert f"{prog}: {prog}" not in text + out.stderr, f"{exe} --help repeats its name"
    if node is None:
        assert "--method" in text and "--out" in text
        return
    assert "ROS parameters" in text
    assert "[--ros-args -p NAME:=VALUE" in text.split("\n\n")[0], f"{exe} --help usage omits --ros-args"
    for p in P.node_parameters(node):
        assert f"\n  {p.name} ({p.type}, default {p.default!r}): " in text, f"{exe} --help lacks {p.name}"


def test_help_before_ros_args():
    out = _help("task_board", "--ros-args", "-p", "seed:=1")
    assert out.returncode == 0 and "instance (string" in out.stdout


@pytest.mark.parametrize("module", ["hmrta_coordinator.task_board", "hmrta_coordinator.sim_robot",
                                    "hmrta_coordinator.recorder"])
def test_help_starts_no_rclpy(module, monkeypatch, capsys):
    import importlib

    import rclpy

    def boom(*a, **k):
        raise AssertionError("--help started rclpy")

    monkeypatch.setattr(rclpy, "init", boom)
    mod = importlib.import_module(module)
    with pytest.raises(SystemExit) as e:
        mod.main([module.rsplit(".", 1)[1], "-h"])
    assert e.value.code == 0 and "ROS parameters" in capsys.readouterr().out


def test_help_requested_ignores_ros_args_and_other_flags():
    from hmrta_msgs_py.runtime import help_requested

    help_requested(["x", "--ros-args", "-p", "a:=--help"], "x", "d", ())  # returns: not a help request
    help_requested(["x"], "x", "d", ())
    with pytest.raises(SystemExit) as e:
        help_requested(["x", "-h"], "x", "d", P.SIM_ROBOT)
    assert e.value.code == 0


@pytest.mark.parametrize("param,text,value", [
    (P.Param("a", P.BOOL, True, "h"), "false", False), (P.Param("a", P.BOOL, True, "h"), "True", True),
    (P.Param("a", P.INTEGER, 0, "h"), "7", 7), (P.Param("a", P.DOUBLE, 0.0, "h"), "0.25", 0.25),
    (P.Param("a", P.STRING_ARRAY, [], "h"), "robot_1, robot_2", ["robot_1", "robot_2"]),
    (P.Param("a", P.STRING_ARRAY, [], "h"), "['robot_1']", ["robot_1"]),
    (P.Param("a", P.STRING_ARRAY, [], "h"), "", []), (P.Param("a", P.STRING, "", "h"), " x ", " x "),
])
def test_param_parse(param, text, value):
    assert param.parse(text) == value


@pytest.mark.parametrize("typ,text", [(P.BOOL, "maybe"), (P.INTEGER, "1.5"), (P.DOUBLE, "fast")])
def test_param_parse_rejects(typ, text):
    with pytest.raises(ValueError, match=r"^a: expected"):
        P.Param("a", typ, None, "h").parse(text)


@pytest.mark.parametrize("exe,args,flag", [
    ("hmrta-mission", ["--time-scale", "-1"], "--time-scale"),
    ("hmrta-mission", ["--timeout", "-5"], "--timeout"),
    ("hmrta-mission", ["--timeout", "nan"], "--timeout"),
    ("hmrta-mission", ["--heartbeat-timeout", "0"], "--heartbeat-timeout"),
    ("hmrta-mission", ["--plot", "x.png", "--no-plot"], "--plot and --no-plot: give one of them, not both"),
    ("hmrta-mission", ["--agents-per-process", "0"], "hmrta-mission: error: --agents-per-process: expected an "
                                                     "integer >= 1, got 0"),
    ("hmrta-mission", ["--method", "foo"], "hmrta-mission: error: unknown method 'foo'"),
    # outputs that cannot be written: refused before the method is chosen or any process starts
    ("hmrta-mission", ["--method", "greedy", "--out", "/proc/hmrta/m.json"], "--out /proc/hmrta/m.json: cannot write"),
    ("hmrta-mission", ["--method", "greedy", "--record", "/proc/x.mcap"], "--record /proc/x.mcap: cannot write"),
    ("hmrta-mission", ["--domain-id", "500"], "--domain-id"),
    ("hmrta-mission", ["--seed", "-1"], "--seed"),
    ("hmrta-task", ["--domain-id", "500", "list"], "--domain-id"),
    ("hmrta-task", ["list", "--clock-topic", "/clock"], "--clock-topic: expected an absolute topic other than /clock"),
    ("hmrta-task", ["list", "--clock-topic", "/my clock"], "--clock-topic: '/my clock' is not a topic name"),
    ("hmrta-task", ["add", "--location", "0.1,0.2", "--requirements", "1,0", "--duration", "nan"], "--duration"),
    ("hmrta-task", ["add", "--location", "0.1,0.2", "--requirements", "1,0", "--duration", "inf"], "--duration"),
    ("hmrta-task", ["add", "--location", "nan,0.2", "--requirements", "1,0", "--duration", "1"], "--location"),
    ("hmrta-task", ["add", "--location", "0.1,0.2", "--requirements", "inf,0", "--duration", "1"], "--requirements"),
    # a mission file's bounds (hmrta.instance.MAX_VALUE, the unit square), before any ROS
    ("hmrta-task", ["add", "--location", "0.1,0.2", "--requirements", "1,0", "--duration", "1.5e9"],
     "--duration: expected a number in [0, 1e+09], got 1.5e+09"),
    ("hmrta-task", ["add", "--location", "0.1,0.2", "--requirements", "2e9,0", "--duration", "1"],
     "--requirements: expected numbers in [0, 1e+09]"),
    ("hmrta-task", ["add", "--location", "0.1,0.2", "--requirements", "0,0", "--duration", "1"],
     "at least one of them non-zero"),
    ("hmrta-task", ["add", "--location", "0.1,1.5", "--requirements", "1,0", "--duration", "1"],
     "--location: expected x,y in the unit square [0, 1], got 0.1,1.5"),
    ("hmrta-task", ["add", "--location", "0.1,0.5", "--requirements", "1,0", "--duration", "1", "--id", ""],
     "--id: expected a task id"),
    ("hmrta-task", ["add", "--location", "0.1,1.5", "--requirements", "1,0", "--duration", "1"],
     "(see hmrta-task add --help)"),  # the subcommand's help, where its options are
    ("hmrta-task", ["cancel", " "], "hmrta-task cancel: error: id: expected a task id"),
    ("hmrta-task", ["add", "--location", "0.1,0.5", "--requirements", "1,0", "--duration", "1", "--id", "a\nb"],
     "--id: expected a task id on one line, got a control character in 'a\\nb'"),  # (the board refuses it too)
    ("hmrta-task", ["cancel", "x\x1by"], "id: expected a task id on one line, got a control character"),
    ("hmrta-task", [], "the following arguments are required: {add,cancel,list}"),
    ("agent_node", ["--robots", "robot_0,,robot_1"], "expected distinct comma-separated robot names"),
])
def test_bad_values_are_user_errors_before_anything_starts(exe, args, flag, tmp_path):
    r = subprocess.run([str(BIN / exe), *args], capture_output=True, text=True, timeout=60, cwd=tmp_path,
                       env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert r.returncode == 2 and flag in r.stderr.splitlines()[-1], r.stderr
    assert "Traceback" not in r.stderr and not list(tmp_path.iterdir())  # no output folder either


@pytest.mark.parametrize("exe,args,says", [
    ("task_board", ["-p", "heartbeat_timeout:=10"], "write it with a decimal point: -p heartbeat_timeout:=10.0"),
    ("task_board", ["-p", "robot_names:=[" + ",".join([f"r{i}" for i in range(14)] + ["r3"]) + "]"],
     "robot_names: expected 15 distinct names, got 'r3' more than once"),
    ("task_board", ["-p", "robot_names:=[a,b]"], "robot_names: expected 15 names (one per robot of the mission), got 2"),
    # a method option is checked even for a method that does not take it: the board and the agents agree
    ("task_board", ["-p", "temperature:=-1.0"], "temperature: expected a number >= 0.01, got -1.0"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "temperature:=-1.0"], "temperature: expected a number >= 0.01"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "method:=rl-sample", "-p", "temperature:=0.0001"],
     "temperature: expected a number >= 0.01, got 0.0001"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "board_silence_warning:=-1.0"], "board_silence_warning: expected"),
    ("agent_node", ["-p", "robot:=1abc"], "robot: '1abc' is not a robot name"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "index:=-2"], "index: expected an integer >= 0, or -1 (not set)"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "species:=-3"], "species: expected an integer >= 0, or -1"),
    ("sim_robot", ["-p", "board_silence_warning:=-1.0"], "board_silence_warning: expected"),
    ("task_board", ["-p", "heartbeat_timeout:=-1.0"], "heartbeat_timeout: expected a finite number >= 0"),
    ("task_board", ["-p", "queue_depth:=0"], "queue_depth: expected"),
    ("sim_robot", ["-p", "rate:=0.0", "-p", "time_scale:=1.0"], "rate: expected"),
    ("sim_robot", ["-p", "time_scale:=-1.0"], "time_scale: expected"),
    ("sim_robot", ["-p", "heartbeat_period:=0.0"], "heartbeat_period: expected"),
    ("task_board", ["-p", "scale:=.inf"], "scale: expected a positive number of metres per mission unit, got inf"),
    # (an option outside --ros-args, such as task_board --method greedy, is not silently left out)
    ("task_board", ["-p", "seed:=1", "--", "--method", "greedy"], "unrecognized arguments: --method greedy"),
    ("sim_robot", ["--", "--bogus"], "sim_robot: unrecognized arguments: --bogus (its settings are ROS parameters"),
    ("recorder", ["--", "--bogus"], "recorder: unrecognized arguments: --bogus"),
    ("task_board", ["-p", "output:=/tmp"], "output: /tmp: is a folder, expected a file name"),
    ("task_board", ["-p", "output:=/proc/nope/r.json"], "output: /proc/nope/r.json: cannot write in /proc"),
    ("task_board", ["-p", "output:=/proc/r.json"], "output: /proc/r.json: cannot write in /proc"),  # (ran, then lost it)
    ("task_board", ["-p", "journal:=/tmp"], "journal: /tmp: is a folder, expected a file name"),  # (a traceback)
    ("task_board", ["-p", "journal:=/proc/j.jsonl"], "journal: /proc/j.jsonl: cannot write in /proc"),
    ("recorder", ["-p", "discovery_period:=.inf"], "discovery_period: expected a number of seconds in [0.001, 86400]"),
    ("recorder", ["-p", "discovery_period:=.nan"], "discovery_period: expected a number of seconds in [0.001, 86400]"),
    # timer periods: 1e300 s overflowed rclpy's nanoseconds (a traceback); 1e-300 s spun, deaf to SIGINT
    ("sim_robot", ["-p", "heartbeat_period:=1e300"], "heartbeat_period: expected a number of seconds in [0.001, 86400]"),
    ("sim_robot", ["-p", "heartbeat_period:=1e-300"], "heartbeat_period: expected a number of seconds in [0.001, 86400]"),
    ("sim_robot", ["-p", "rate:=1e9", "-p", "time_scale:=1.0"], "rate: expected a number of ticks per second in ["),
    ("task_board", ["-p", "marker_period:=1e-300"], "marker_period: expected a number of seconds in [0.001, 86400] (0: none)"),
    ("recorder", ["-p", "discovery_period:=1e300"], "discovery_period: expected a number of seconds in [0.001, 86400]"),
    ("recorder", ["-p", "robots:=[1abc]"], "robots: '1abc' is not a robot name"),
    ("recorder", ["-p", "topics:=['bad topic']"], "topics: expected absolute topic names such as /scan, got 'bad topic'"),
    ("recorder", ["-p", "topics:=[/bad topic]"], "topics: '/bad topic' is not a topic name (Invalid topic name: topic name must not"),
    ("recorder", ["-p", "topics:=[scan]"], "topics: expected absolute topic names such as /scan, got 'scan'"),
    ("recorder", ["-p", "output:=/proc/nope/x.mcap"], "output: /proc/nope/x.mcap: cannot write in /proc"),
    ("task_board", ["-p", "instance:=/no/such/mission.yaml"], "instance: /no/such/mission.yaml: no such file"),
    ("task_board", ["-p", "method:=rl-s0"], "rl-s0: option samples: expected an integer in [1, 10000], got 0"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "method:=rl-s0"], "rl-s0: option samples: expected an integer"),
    # a checkpoint that is no file: the board died with a traceback; a portfolio agent took it
    ("task_board", ["-p", "method:=rl", "-p", "checkpoint:=nosuch"], "nosuch: no such checkpoint (shipped: "),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "checkpoint:=nosuch"], "nosuch: no such checkpoint"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "candidates:=cpsat,greedy"], "cpsat cannot be a candidate"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "candidates:=rl@nosuch"],
     "portfolio: option candidates: rl@nosuch: nosuch: no such checkpoint"),
    ("agent_node", ["-p", "robot:=robot_0", "-p", "method:=rl", "-p", "checkpoint:=/etc/passwd"],
     "/etc/passwd: not a readable hmrta checkpoint (not a torch checkpoint file)"),
])
def test_bad_node_parameters_are_one_line_user_errors(exe, args, says, domain):
    example = ROOT / "policy" / "hmrta" / "data" / "example.yaml"
    extra = ["-p", f"instance:={example}"] if exe == "task_board" else []
    r = subprocess.run([str(BIN / exe), "--ros-args", *extra, *args], capture_output=True, text=True, timeout=60,
                       env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain)))
    assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("args,says", [
    (["--bogus"], "unrecognized arguments: --bogus"),
    (["--torch-threads", "0"], "--torch-threads: expected a number of threads in [1, 1024], got 0"),
    (["--torch-threads", "99999"], "--torch-threads: expected a number of threads in [1, 1024], got 99999"),
    (["--torch-threads", "2147483648"], "--torch-threads: expected a number of threads in [1, 1024], got 2147483648"),
    (["--robots", "a,a"], "argument --robots: expected distinct comma-separated robot names, got 'a,a'"),
])
def test_agent_node_flags_are_one_line_user_errors(args, says, domain):
    r = subprocess.run([str(BIN / "agent_node"), *args, "--ros-args", "-p", "robot:=robot_0"], capture_output=True,
                       text=True, timeout=60,
                       env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain)))
    assert r.returncode == 2 and r.stderr == f"agent_node: error: {says} (see agent_node --help)\n", r.stderr


def test_a_recorder_output_that_is_a_folder_is_refused_and_nothing_is_left(tmp_path, domain):
    """A folder as the recording's file was taken at start and crashed at the end (the recording
    left beside it as <folder>.part); it is refused at start, and a recorder that did not start
    leaves no .part file."""
    (tmp_path / "work").mkdir()
    for args in (["-p", f"output:={tmp_path / 'work'}"],
                 ["-p", f"output:={tmp_path / 'x.mcap'}", "-p", "discovery_period:=-1.0"]):
        r = subprocess.run([str(BIN / "recorder"), "--ros-args", *args], capture_output=True, text=True,
                           timeout=60, cwd=tmp_path,
                           env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain)))
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert r.stderr.strip().splitlines()[-1].startswith("recorder: output: " if "work" in args[1] else
                                                            "recorder: discovery_period: "), r.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == ["work"], args


def test_a_bad_hmrta_checkpoint_is_one_line_before_a_portfolio_simulates(domain):
    """$HMRTA_CHECKPOINT naming no checkpoint: the board logged that it was simulating the
    candidates, then failed; it is now the one line, naming the variable."""
    example = ROOT / "policy" / "hmrta" / "data" / "example.yaml"
    r = subprocess.run([str(BIN / "task_board"), "--ros-args", "-p", f"instance:={example}"], capture_output=True,
                       text=True, timeout=60, env=dict(os.environ, HMRTA_CHECKPOINT="nosuch", ROS_DOMAIN_ID=str(domain),
                                                       ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert r.returncode == 2 and r.stderr.startswith(
        "task_board: nosuch (named by $HMRTA_CHECKPOINT): no such checkpoint") and r.stderr.count("\n") == 1, r.stderr
    assert "simulating" not in r.stdout + r.stderr


def test_an_output_or_journal_that_is_a_fifo_is_refused_at_start(tmp_path, domain):
    """A FIFO as the board's journal blocked its start until a signal; as the board's result or a
    recording it was replaced by a regular file at the end. Each is one line at start now, and the
    FIFO is left as it was."""
    import stat

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    example = ROOT / "policy" / "hmrta" / "data" / "example.yaml"
    for exe, args in (("task_board", ["-p", f"instance:={example}", "-p", f"journal:={fifo}"]),
                      ("task_board", ["-p", f"instance:={example}", "-p", f"output:={fifo}"]),
                      ("recorder", ["-p", f"output:={fifo}"])):
        r = subprocess.run([str(BIN / exe), "--ros-args", *args], capture_output=True, text=True, timeout=60,
                           env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain)))
        name = args[-1].split(":=")[0]
        assert r.returncode == 2 and r.stderr == f"{exe}: {name}: {fifo}: exists and is not a regular file\n", r.stderr
        assert stat.S_ISFIFO(fifo.stat().st_mode) and sorted(p.name for p in tmp_path.iterdir()) == ["pipe"]


@pytest.mark.parametrize("period", ["0", "1e300", "1e-300"])
def test_an_agent_heartbeat_period_out_of_range_is_refused(period):
    r = subprocess.run([str(BIN / "agent_node"), "--heartbeat-period", period], capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert r.returncode == 2 and r.stderr.startswith(
        "agent_node: error: --heartbeat-period: expected a number of seconds in [0.001, 86400]"), r.stderr
