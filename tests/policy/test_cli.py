"""The hmrta command line: bench on a user's missions, one --out spelling, help text, convert's robot
mapping, evaluate/bound on folders, missing optional dependencies, progress bars."""
from __future__ import annotations

import argparse
import csv
import io
import json
import re
import shutil
import sys
import time
from pathlib import Path

import pytest

from hmrta.cli import SolveProgress, build_parser, main
from hmrta.formats import load_instance

DATA = Path(__file__).parent / "data"
CTAS = DATA / "ctas_small"
EXAMPLE = DATA / "example.yaml"


def _missions(tmp_path, n=2) -> Path:
    folder = tmp_path / "fleet"
    assert main(["generate", "--scenario", "MA-AT", "--agents", "6", "--species", "2", "--tasks", "6",
                 "--skills", "3", "--count", str(n), "--seed", "3", "--out", str(folder)]) == 0
    return folder


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


# ---------------------------------------------------------------------------------------------
# bench on the user's own missions
# ---------------------------------------------------------------------------------------------
def test_bench_on_a_folder_and_a_ctas_folder(tmp_path, capsys):
    from hmrta.methods import solve

    folder = _missions(tmp_path)
    out = tmp_path / "res"
    argv = ["bench", str(folder), str(CTAS), "--methods", "greedy,greedy-coalition",
            "--compare", "greedy-coalition,greedy", "--out", str(out), "--no-progress"]
    capsys.readouterr()
    assert main(argv) == 0
    printed = capsys.readouterr().out
    data = json.loads((out / "results.json").read_text())
    assert [(r["name"], r["kind"], r["results"]["greedy"]["n"]) for r in data["rows"]] == [
        ("fleet", "missions", 2), ("ctas_small", "missions", 1)]
    assert data["provenance"]["command"] == "hmrta " + " ".join(argv)
    # the figures are those of solving each mission
    files = sorted(folder.glob("*.yaml"))
    assert data["rows"][0]["makespans"]["greedy"] == [solve(load_instance(f), "greedy").makespan for f in files]
    assert data["rows"][1]["makespans"]["greedy-coalition"] == [
        solve(load_instance(CTAS), "greedy-coalition").makespan]
    assert [(c["a"], c["b"], c["n"]) for c in data["rows"][0]["comparisons"]] == [("greedy-coalition", "greedy", 2)]
    md = (out / "results.md").read_text()
    assert md + "\n" == printed
    assert "### Missions (3 instances)" in md and "Table" not in md and "paper" not in md
    assert "| fleet | 6, 2, 6, 3 | Greedy | 100% |" in md and "| ctas_small | 5, 3, 3, 3 | Greedy |" in md
    assert "| fleet | Greedy-coalition vs Greedy |" in md
    rows = list(csv.DictReader(io.StringIO((out / "results.csv").read_text())))
    assert [(r["row"], r["method"]) for r in rows] == [
        ("missions:fleet", "greedy"), ("missions:fleet", "greedy-coalition"),
        ("missions:ctas_small", "greedy"), ("missions:ctas_small", "greedy-coalition")]


def test_bench_json_output_and_user_errors(tmp_path, capsys):
    folder = _missions(tmp_path, 1)
    capsys.readouterr()
    assert main(["bench", str(folder), "--methods", "greedy", "--json", "--no-progress"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["rows"][0]["name"] == "fleet" and "provenance" in data
    for argv, msg in (
        (["bench", str(folder), "--methods", "greedy", "--compare", "rl,greedy"], "'rl' is not one of"),
        (["bench", str(folder), "--methods", "greedy", "--compare", "greedy"], "expected two methods A,B"),
        (["bench", str(folder), "--suite", "paper"], "not both INSTANCE and --suite"),
        (["bench", str(folder), "--out", str(tmp_path / "r.json")], "expected a folder"),
        (["bench", str(tmp_path / "nope.yaml")], "nope.yaml: no such file"),
    ):
        assert main(argv) == 2, argv
        assert msg in _one_error_line(capsys)


# ---------------------------------------------------------------------------------------------
# one CLI language
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("argv", [
    ["convert", str(CTAS), "-o", "x.yaml"],
    ["convert", str(CTAS), "--output", "x.yaml"],
    ["bench", "--suite", "paper", "--out-dir", "x"],
    ["bench", "--suite", "paper", "--markdown", "x.md"],
])
def test_old_output_spellings_are_gone(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    capsys.readouterr()


def test_options_may_stand_between_positional_arguments(tmp_path, capsys, monkeypatch):
    """``hmrta solve a.yaml --method greedy b.yaml`` reads both missions, as the same options
    before or after them would; a subcommand's own errors are unchanged."""
    folder = _missions(tmp_path)
    a, b = sorted(folder.glob("*.yaml"))
    capsys.readouterr()
    assert main(["solve", str(a), "--method", "greedy", str(b), "--json"]) == 0
    mixed = json.loads(capsys.readouterr().out)
    assert main(["solve", str(a), str(b), "--method", "greedy", "--json"]) == 0
    assert [s["makespan"] for s in mixed] == [s["makespan"] for s in json.loads(capsys.readouterr().out)]
    sol = tmp_path / "a.json"
    assert main(["solve", str(a), "--method", "greedy", "--out", str(sol)]) == 0
    capsys.readouterr()
    assert main(["bound", str(a), "--json", str(sol)]) == 0
    assert json.loads(capsys.readouterr().out)
    # after --, every argument is a positional: a mission file whose name starts with a dash
    (tmp_path / "-m.yaml").write_text(a.read_text())
    monkeypatch.chdir(tmp_path)
    assert main(["solve", "--method", "greedy", "--json", "--", "-m.yaml"]) == 0
    assert json.loads(capsys.readouterr().out)["makespan"] == mixed[0]["makespan"]
    for argv, said in ((["solve", str(a), "--bogus", str(b)], "hmrta solve: error: unrecognized arguments: --bogus"),
                       (["solve", "--method", "greedy"], "the following arguments are required: INSTANCE"),
                       (["checkpoint", "average", "--out", str(tmp_path / "x.pt")], "required: CHECKPOINT")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2 and said in _one_error_line(capsys), argv


def _parsers(p: argparse.ArgumentParser, name: str = "hmrta"):
    yield name, p
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            for sub_name, sub in a.choices.items():
                yield from _parsers(sub, f"{name} {sub_name}")


def test_help_shows_each_default_once_and_never_none():
    parsers = list(_parsers(build_parser()))
    assert {n for n, _ in parsers} >= {"hmrta solve", "hmrta bench", "hmrta convert", "hmrta evaluate",
                                       "hmrta bound", "hmrta train", "hmrta render", "hmrta demo"}
    for name, p in parsers:
        fmt = p._get_formatter()
        for a in p._actions:
            if not a.help or a.help == argparse.SUPPRESS:
                continue
            text = fmt._expand_help(a)
            assert "(default: None)" not in text, (name, a.dest, text)
            if text != a.help % {**vars(a), "prog": p.prog}:  # the formatter appended "(default: X)" ...
                assert "default" not in a.help.lower(), (name, a.dest, text)  # ... and the help has none
        assert "(default: None)" not in " ".join(p.format_help().split()), name
    bench = dict(parsers)["hmrta bench"]
    assert "(default: 50)" in " ".join(bench.format_help().split())  # real defaults still shown


# ---------------------------------------------------------------------------------------------
# convert writes the robot id mapping
# ---------------------------------------------------------------------------------------------
def test_convert_writes_the_robot_mapping(tmp_path, capsys):
    out = tmp_path / "ctas.yaml"
    assert main(["convert", str(CTAS), "--out", str(out)]) == 0
    mp = tmp_path / "ctas.mapping.json"
    assert f"wrote {mp}" in capsys.readouterr().out
    mapping = json.loads(mp.read_text())
    # robots 0, 2 / 1, 4 share pose and skills; robot 3 only the pose: species-major renumbering
    assert mapping["robot_to_agent"] == {"0": 0, "2": 1, "1": 2, "4": 3, "3": 4}
    assert mapping["agent_to_robot"] == ["0", "2", "1", "4", "3"]
    tasks = sorted(json.loads((CTAS / "config.json").read_text())["tasks"], key=int)
    assert mapping["index_to_task"] == tasks and mapping["task_to_index"] == {t: m for m, t in enumerate(tasks)}
    inst = load_instance(out)  # the instance file itself stays a plain hmrta-instance/1
    raw = json.loads((CTAS / "config.json").read_text())["robots"]
    for robot, agent in mapping["robot_to_agent"].items():
        r = raw[robot]
        assert list(inst.depots[agent]) == [r["pose"]["x"], r["pose"]["y"]]
        assert list(inst.traits[agent]) == [r["skillset"][str(k)] for k in range(inst.skills)]
    # an hmrta instance has no other robot ids: no mapping
    assert main(["convert", str(EXAMPLE), "--out", str(tmp_path / "ex.yaml")]) == 0
    assert "mapping" not in capsys.readouterr().out and not (tmp_path / "ex.mapping.json").exists()
    # nor has the same mission written as JSON (read as an hmrta-instance/1, not as CTAS-D)
    (tmp_path / "ex.json").write_text(json.dumps(load_instance(EXAMPLE).to_dict()))
    assert main(["convert", str(tmp_path / "ex.json"), "--out", str(tmp_path / "exj.yaml")]) == 0
    assert "mapping" not in capsys.readouterr().out and not (tmp_path / "exj.mapping.json").exists()
    assert load_instance(tmp_path / "exj.yaml").to_dict() == load_instance(EXAMPLE).to_dict()
    # a CTAS-D config with a byte-order mark reads as the loader reads it
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf" + (CTAS / "config.json").read_bytes())
    assert main(["convert", str(bom), "--out", str(tmp_path / "bom.yaml")]) == 0
    assert json.loads((tmp_path / "bom.mapping.json").read_text())["robot_to_agent"] == mapping["robot_to_agent"]
    # the mapping is never written over an input: a config named like the mapping of --out
    src = tmp_path / "c.mapping.json"
    src.write_bytes((CTAS / "config.json").read_bytes())
    capsys.readouterr()
    assert main(["convert", str(src), "--out", str(tmp_path / "c.yaml")]) == 2
    assert "the robot mapping of --out" in _one_error_line(capsys) and not (tmp_path / "c.yaml").exists()
    assert src.read_bytes() == (CTAS / "config.json").read_bytes()


# ---------------------------------------------------------------------------------------------
# evaluate and bound accept folders
# ---------------------------------------------------------------------------------------------
def test_bound_says_cpsat_needs_a_mission_known_at_the_start(tmp_path, capsys):
    """A mission with tasks released later has bounds (one of them the releases'), but no CP-SAT
    bound: --time-limit said 'method cpsat is an offline solver ... (use portfolio, ...)'."""
    import dataclasses

    inst = load_instance(EXAMPLE)
    late = dataclasses.replace(inst, tasks=(dataclasses.replace(inst.tasks[0], release=2.0), *inst.tasks[1:]))
    path = tmp_path / "late.yaml"
    path.write_text(late.to_yaml())
    assert main(["bound", str(path), "--time-limit", "1"]) == 2
    assert capsys.readouterr().err == (f"hmrta: error: --time-limit: {path}: CP-SAT plans a mission known at the "
                                       f"start, and this one has tasks released later; run without --time-limit "
                                       f"for its other bounds\n")
    assert main(["bound", str(path)]) == 0 and "release" in capsys.readouterr().out


def test_evaluate_and_bound_accept_folders(tmp_path, capsys):
    folder = _missions(tmp_path)
    sols = tmp_path / "sols"
    assert main(["solve", str(folder), "--method", "greedy", "--out", str(sols), "--no-progress"]) == 0
    capsys.readouterr()
    solved = {p.stem: json.loads(p.read_text()) for p in sols.glob("*.json")}
    assert len(solved) == 2
    assert main(["evaluate", str(folder), str(sols), "--json"]) == 0
    evaluated = json.loads(capsys.readouterr().out)
    assert [e["makespan"] for e in evaluated] == [solved[f.stem]["makespan"] for f in sorted(folder.glob("*.yaml"))]
    assert main(["bound", str(folder), str(sols), "--json"]) == 0
    reports = json.loads(capsys.readouterr().out)
    assert [r["instance"] for r in reports] == sorted(solved)
    for r in reports:
        (s,) = r["solutions"]
        assert s["makespan"] == solved[r["instance"]]["makespan"] and s["gap"] >= 0
        assert r["best"] <= s["makespan"]
    # a single instance still takes a folder of solutions, and prints a text report
    one = sorted(folder.glob("*.yaml"))[0]
    assert main(["bound", str(one), str(sols)]) == 0
    assert f"greedy: makespan {solved[one.stem]['makespan']:.3f}" in capsys.readouterr().out
    # errors name the file
    assert main(["evaluate", str(folder), str(sols / f"{one.stem}.json")]) == 2
    assert "expected a folder of <instance stem>.json routes" in _one_error_line(capsys)
    (sols / f"{one.stem}.json").unlink()
    assert main(["evaluate", str(folder), str(sols)]) == 2
    assert f"{sols / one.stem}.json: no such file" in _one_error_line(capsys)
    assert main(["bound", str(folder), str(sols)]) == 2
    assert f"{sols / one.stem}.json: no such file" in _one_error_line(capsys)


def test_deadlocking_routes_are_named_by_their_file_in_evaluate_and_bound(tmp_path, capsys):
    mission = tmp_path / "dl.yaml"
    mission.write_text("format: hmrta-instance/1\nrequirement_type: additive\nvelocity: 0.2\nskills: 1\n"
                       "species:\n  - {traits: [1], count: 2, depot: [0.1, 0.8]}\n"
                       "tasks:\n  - {location: [0.5, 0.9], requirements: [2], duration: 1}\n"
                       "  - {location: [0.2, 0.2], requirements: [2], duration: 1}\n")
    routes = tmp_path / "crossed.json"
    routes.write_text('{"routes": [[0, 1], [1, 0]]}')  # each robot waits at the task the other does last
    for cmd in ("evaluate", "bound"):
        assert main([cmd, str(mission), str(routes)]) == 2, cmd
        line = _one_error_line(capsys)
        assert line.startswith(f"hmrta: error: {routes}: deadlock"), line


def test_routes_files_are_read_alike_by_evaluate_bound_and_render(tmp_path, capsys):
    """A routes file (``{"routes": ...}``, as ``hmrta evaluate`` takes it): ``bound`` and ``render``
    take it too, and a bad one gets the routes reader's error in all three (not the solution
    reader's "missing key 'format'")."""
    pytest.importorskip("matplotlib")
    inst = load_instance(EXAMPLE)
    good = tmp_path / "routes.json"
    from hmrta.methods import solve

    good.write_text(json.dumps({"routes": solve(inst, "greedy").routes}))
    assert main(["render", str(EXAMPLE), str(good), "--out", str(tmp_path / "r.png"), "--no-progress"]) == 0
    assert (tmp_path / "r.png").stat().st_size > 0
    capsys.readouterr()
    bad = tmp_path / "short.json"
    bad.write_text('{"routes": [[0]]}')
    for cmd in (["evaluate"], ["bound"], ["render", "--out", str(tmp_path / "b.png")]):
        assert main([cmd[0], str(EXAMPLE), str(bad), *cmd[1:]]) == 2, cmd
        line = _one_error_line(capsys)
        assert f"{bad}: routes: expected a list of {inst.n_agents} routes" in line, (cmd, line)


def test_a_damaged_solution_file_is_refused_not_re_simulated(tmp_path, capsys):
    """``bound`` and ``render`` re-simulate a routes file, never a solution file that fails its
    checks: its own error is the answer (it used to be re-simulated from its routes, exit 0)."""
    pytest.importorskip("matplotlib")
    from hmrta.methods import solve

    sol = solve(load_instance(EXAMPLE), "greedy")
    good = tmp_path / "sol.json"
    sol.save(good)
    d = json.loads(good.read_text())
    for change, message in (({"format": "hmrta-solution/9"}, "format: expected 'hmrta-solution/1'"),
                            ({"makespan": 1.0}, "makespan: expected at least the last finish"),
                            ({"tasks": None}, "tasks: expected a list")):
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps(d | change))
        for cmd in (["bound"], ["render", "--out", str(tmp_path / "b.png"), "--no-progress"]):
            assert main([cmd[0], str(EXAMPLE), str(bad), *cmd[1:]]) == 2, (cmd, change)
            line = _one_error_line(capsys)
            assert f"{bad}: {message}" in line, (cmd, line)
        assert not (tmp_path / "b.png").exists()


# ---------------------------------------------------------------------------------------------
# missing optional dependencies
# ---------------------------------------------------------------------------------------------
def test_missing_torch_is_a_one_line_error_naming_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "torch", None)  # as if torch were not installed
    for argv in (["solve", str(EXAMPLE), "--method", "rl"],
                 ["solve", str(EXAMPLE), "--method", "rl-s4"],
                 ["bench", str(EXAMPLE), "--methods", "greedy,rl-lookahead", "--no-progress"],
                 ["train", "--run-dir", str(tmp_path / "run")]):
        assert main(argv) == 2, argv
        line = _one_error_line(capsys)
        assert "torch" in line and "pip install 'hmrta[rl]'" in line, line


def test_missing_ortools_is_a_one_line_error_naming_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ortools", None)
    for argv in (["solve", str(CTAS), "--method", "cpsat"], ["bound", str(CTAS), "--time-limit", "1"]):
        assert main(argv) == 2, argv
        line = _one_error_line(capsys)
        assert "ortools" in line and "pip install 'hmrta[cpsat]'" in line, line


def test_missing_matplotlib_is_a_one_line_error_naming_the_extra(tmp_path, monkeypatch, capsys):
    sol = tmp_path / "sol.json"
    assert main(["solve", str(EXAMPLE), "--method", "greedy", "--out", str(sol)]) == 0
    capsys.readouterr()
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["render", str(EXAMPLE), str(sol), "--out", str(tmp_path / "fig.png")]) == 2
    line = _one_error_line(capsys)
    assert "matplotlib" in line and "pip install 'hmrta[plot]'" in line, line
    assert not (tmp_path / "fig.png").exists()


# ---------------------------------------------------------------------------------------------
# progress
# ---------------------------------------------------------------------------------------------
def test_solve_progress_bar(monkeypatch, capsys):
    monkeypatch.setattr(SolveProgress, "DELAY", 0.0)
    with SolveProgress("rl-lookahead x") as prog:
        for k in range(4):
            prog(k, 3, "task", f"{2 * k} decisions")
        assert prog.bar.n == 3  # never past the total
        shown = str(prog.bar)
    assert "rl-lookahead x" in shown and "3/3" in shown and "6 decisions" in shown
    assert "rl-lookahead x" in capsys.readouterr().err  # on stderr
    with SolveProgress("cpsat x") as prog:  # time bars advance between the solver's calls
        prog(0.0, 30.0, "s", "heuristic")
        deadline = time.monotonic() + 20.0  # (its ticker thread: 0.5 s a tick, later on a busy machine)
        while prog.bar.n < 0.5 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert 0.5 <= prog.bar.n < 30
    capsys.readouterr()
    monkeypatch.setattr(SolveProgress, "DELAY", 0.5)
    with SolveProgress("lookahead y") as prog:  # a slow first decision: the bar shows after DELAY all the same
        prog(0, 50, "task", "0 decisions")
        time.sleep(1.5)
    assert "lookahead y" in capsys.readouterr().err and prog.bar.n == 0
    with SolveProgress("off", enabled=False) as prog:
        prog(1, 2, "task")
        assert prog.bar is None
    capsys.readouterr()


def test_solvers_report_progress():
    from hmrta.methods import solve

    inst = load_instance(CTAS)
    calls = []
    sol = solve(inst, "rl-lookahead", progress=lambda *a: calls.append(a))
    assert sol.success and calls
    assert all(unit == "task" and total == inst.n_tasks for _, total, unit, _ in calls)
    assert [c[0] for c in calls] == sorted(c[0] for c in calls) and calls[-1][0] == inst.n_tasks
    assert calls[0][0] == 0  # called before the first decision (the slowest): a bar shows at once
    calls.clear()
    sol = solve(inst, "cpsat", time_limit=1.0, progress=lambda *a: calls.append(a))
    assert sol.success and calls[0][3].startswith("heuristic") and "makespan" in calls[-1][3]
    assert all(unit == "s" and total == 1.0 for _, total, unit, _ in calls)
    assert [c[0] for c in calls] == sorted(c[0] for c in calls)


def test_progress_per_instance_whenever_there_are_several(tmp_path, monkeypatch, capsys):
    import hmrta.cli

    monkeypatch.setattr(SolveProgress, "DELAY", 0.0)
    folder = _missions(tmp_path)
    capsys.readouterr()
    assert main(["solve", str(folder), "--method", "greedy"]) == 0  # stderr is no terminal here: no bar
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(hmrta.cli.progress, "_terminal", lambda: True)
    assert main(["solve", str(folder), "--method", "greedy"]) == 0
    err = capsys.readouterr().err
    assert "solve" in err and "2/2" in err and "instance" in err
    assert main(["solve", str(folder), "--method", "greedy", "--no-progress"]) == 0
    assert capsys.readouterr().err == ""


# ---------------------------------------------------------------------------------------------
# bad user input: exit 2, one line naming the option, nothing left behind
# ---------------------------------------------------------------------------------------------
def test_bench_suite_default_out_is_not_the_committed_tables(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "--suite", "paper", "--tables", "SA-BT", "--max-tasks", "20", "--count", "1",
                 "--methods", "greedy", "--no-progress"]) == 0
    assert "wrote bench-paper/results.json" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bench-paper"]
    assert (tmp_path / "bench-paper" / "results.md").is_file()
    assert "--out docs/results/families, and for the paper's tables docs/results/sa, ma and large" in " ".join(build_parser()._subparsers._group_actions[0]
                                                   .choices["bench"].format_help().split())


@pytest.mark.parametrize("argv, msg", [
    (["--method", "rl-sample", "--temperature", "inf"], "option temperature: expected a finite number >= 0.01"),
    (["--method", "rl-sample", "--temperature", "nan"], "option temperature: expected a finite number >= 0.01"),
    (["--method", "rl-sample", "--temperature", "0"], "option temperature: expected a number >= 0.01"),
    (["--method", "rl-sample", "--samples", "10001"], "option samples: expected an integer in [1, 10000]"),
    (["--method", "cpsat", "--time-limit", "inf"], "option time_limit (--time-limit): expected a finite number >= 0.01"),
    (["--method", "cpsat", "--time-limit", "nan"], "option time_limit (--time-limit): expected a finite number >= 0.01"),
    # the heuristic phase is a part of the time limit
    (["--method", "cpsat", "--heuristic-seconds", "5", "--time-limit", "2"],
     "cpsat: option heuristic_seconds (--heuristic-seconds) 5 is more than option time_limit (--time-limit) 2: "
     "it is a part of that time (expected at most 2)"),
    (["--method", "cpsat", "--heuristic-seconds", "61"],
     "option heuristic_seconds (--heuristic-seconds) 61 is more than option time_limit (--time-limit) 60, its default"),
])
def test_method_options_out_of_range(argv, msg, capsys):
    assert main(["solve", str(EXAMPLE), "--no-progress", *argv]) == 2
    assert msg in _one_error_line(capsys)


def _exit2(argv, capsys, *needles) -> str:
    """``main(argv)`` exits 2 with one line (no traceback) holding every needle."""
    assert main(argv) == 2, argv
    out, err = capsys.readouterr()
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for n in needles:
        assert n in err, (n, err)
    return err.strip()


ROW = ["--scenario", "MA-AT", "--agents", "6", "--species", "2", "--tasks", "6", "--skills", "3", "--count", "1"]
HOPELESS = ["--scenario", "MA-AT", "--agents", "1", "--species", "1", "--tasks", "50", "--skills", "3"]


@pytest.mark.parametrize("argv, needles", [
    (["generate", *ROW, "--seed", "-1"], ["--seed: expected an integer in 0..2^63-1, got -1"]),
    (["generate", *ROW, "--agents", "0"], ["--agents: expected a positive integer, got 0"]),
    (["generate", *ROW, "--agents", "7"], ["--agents 7: expected a multiple of --species (2)"]),
    (["generate", *ROW, "--agents", "1"], ["--agents 1: expected at least --species (2)"]),
    (["generate", *HOPELESS], ["no feasible instance", "more agents"]),
    (["generate", *ROW, "--count", "0"], ["--count: expected a positive integer, got 0"]),
    # a mission may have no tasks, but a generated set of them measures nothing
    (["generate", *ROW, "--tasks", "0"], ["--tasks: expected a positive integer, got 0"]),
    (["generate", *ROW, "--species", "-1"], ["--species: expected a positive integer, got -1"]),
    (["generate", *ROW, "--skills", "0"], ["--skills: expected a positive integer, got 0"]),
    (["bench", *ROW, "--tasks", "0"], ["--tasks: expected a positive integer, got 0"]),
    # a generated row's sizes beside a suite (or your missions) would be ignored
    (["bench", "--suite", "paper", "--skills", "0"], ["--skills: only applies with --scenario (a generated row), not "
                                                      "with --suite"]),
    (["bench", str(EXAMPLE), "--tasks", "5"], ["--tasks: only applies with --scenario (a generated row), not with "
                                               "INSTANCE"]),
    (["bench", str(EXAMPLE), "--count", "3"], ["--count: only applies to generated rows"]),
    (["bench", str(EXAMPLE), "--seed", "5"], ["--seed: only applies to generated rows"]),
    # option values are checked before the cache is written
    (["bench", *ROW, "--methods", "greedy,cpsat", "--heuristic-seconds", "3", "--time-limit", "1"],
     ["option heuristic_seconds (--heuristic-seconds) 3 is more than option time_limit (--time-limit) 1"]),
    (["bench", *ROW, "--methods", "greedy,cpsat", "--time-limit", "nan"], ["option time_limit (--time-limit): expected a finite"]),
    (["bench", *ROW, "--seed", "-1"], ["--seed: expected an integer in 0..2^63-1"]),
    (["bench", *ROW, "--agents", "0"], ["--agents: expected a positive integer, got 0"]),
    (["bench", *ROW, "--agents", "7"], ["--agents 7: expected a multiple of --species (2)"]),
    (["bench", *ROW, "--methods", "portfolio", "--candidates", "greedy,foo"],
     ["portfolio: option candidates: unknown method 'foo'"]),
    (["bench", *HOPELESS], ["no feasible instance", "more agents"]),
    (["bench", *ROW, "--count", "0"], ["--count: expected a positive integer, got 0"]),
    (["bench", *ROW, "--count", "-2"], ["--count: expected a positive integer, got -2"]),
    (["bench", "--suite", "paper", "--max-tasks", "0"], ["--max-tasks: expected a positive integer, got 0"]),
    (["bench", "--suite", "paper", "--max-tasks", "5"], ["--max-tasks 5: every row of --suite paper has more"]),
    (["bench", "--suite", "families", "--tables", "homog", "--max-tasks", "1"], ["--max-tasks 1: every row"]),
    (["bench", *ROW, "--max-tasks", "3"], ["--max-tasks: only applies with --suite"]),
    (["schedules", "--count", "1", "--seed", "-1"], ["--seed: expected an integer in 0..2^63-1"]),
    (["solve", str(EXAMPLE), "--method", "rl-s3", "--seed", str(2**64)], ["--seed: expected an integer in 0..2^63-1"]),
    (["demo", "--seed", "-1"], ["--seed: expected an integer in 0..2^63-1"]),
])
def test_bad_counts_seeds_and_teams_leave_nothing(argv, needles, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / ("s.jsonl" if argv[0] == "schedules" else "out")
    _exit2([*argv, "--out", str(out), *(["--no-progress"] if argv[0] != "generate" else [])], capsys, *needles)
    assert list(tmp_path.iterdir()) == []  # no folder, no schedules header, no cache


def test_solve_json_and_schedule_are_exclusive(capsys):
    with pytest.raises(SystemExit) as e:
        main(["solve", str(EXAMPLE), "--json", "--schedule"])
    assert e.value.code == 2 and "--schedule: not allowed with argument --json" in capsys.readouterr().err


def test_jobs_above_the_local_cores_are_refused_unless_on_a_cluster(tmp_path, monkeypatch, capsys):
    """A local Ray with more workers than cores oversubscribes them; a cluster (--ray-address) may have more."""
    pytest.importorskip("torch")
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    monkeypatch.chdir(tmp_path)
    for argv in (["train", "--check"], ["bench", *ROW, "--methods", "greedy", "--no-progress", "--out", "res"],
                 ["schedules", "--count", "1", "--no-progress", "--out", "s.jsonl"]):
        _exit2([*argv, "--jobs", "3"], capsys, "--jobs 3: expected at most 2, the cores of this machine",
               "--ray-address HOST:PORT for a cluster")
    assert list(tmp_path.iterdir()) == []
    assert main(["train", "--check", "--jobs", "3", "--ray-address", "127.0.0.1:6379"]) == 0
    helps = build_parser()._subparsers._group_actions[0].choices
    for cmd in ("bench", "train", "schedules"):
        assert "N at most this machine's cores unless --ray-address" in " ".join(helps[cmd].format_help().split())


@pytest.mark.parametrize("opt, value", [("--frames", "0"), ("--frames", "-5"), ("--fps", "0"), ("--fps", "-1"),
                                        ("--frames", "100000000"), ("--fps", "51")])
def test_render_frames_and_fps(opt, value, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    sol = tmp_path / "sol.json"
    assert main(["solve", str(EXAMPLE), "--method", "greedy", "--out", str(sol)]) == 0
    capsys.readouterr()
    for out in ("r.png", "r.gif"):
        _exit2(["render", str(EXAMPLE), str(sol), "--out", str(tmp_path / out), "--gif", opt, value], capsys,
               f"{opt}: expected an integer in 1..{1000 if opt == '--frames' else 50}, got {value}")
    assert [p.name for p in tmp_path.iterdir()] == ["sol.json"]  # no png written before failing


CONFIG = Path(__file__).resolve().parents[2] / "policy" / "configs" / "default.yaml"


def test_train_check_reads_the_checkpoint_it_would_start_from(tmp_path, capsys):
    """``train --check --resume`` reads the checkpoint the run would start from (``--init``: a
    file or a shipped name) as the run would, and writes nothing: a checkpoint cut short, or one
    that does not fit the config's network, is an error before any training."""
    pytest.importorskip("torch")
    from hmrta.rl.checkpoint_info import SHIPPED_DIR

    team = CONFIG.with_name("coalition-team.yaml")
    run = tmp_path / "run"
    train = ["train", "--config", str(team), "--run-dir", str(run), "--check", "--resume"]
    assert main([*train, "--init", "coalition-team", "--reseed"]) == 0
    out = capsys.readouterr().out
    assert f"{SHIPPED_DIR / 'coalition-team.pt'}: a checkpoint this run can start from" in out, out
    cut = tmp_path / "cut.pt"
    cut.write_bytes((SHIPPED_DIR / "coalition-team.pt").read_bytes()[:5000])
    _exit2([*train, "--init", str(cut)], capsys, f"{cut}: not a readable hmrta checkpoint (a zip archive cut short")
    _exit2([*train, "--init", "default", "--reseed"], capsys, "weights do not match the network")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.pt"]  # no run folder
    # ... nor when it runs: the run folder made for it is not left behind, and the message names
    # the network's settings that differ (coalition-team.yaml's network against compact.pt's)
    deep = [str(tmp_path / "runs" / "a" / "b") if t == str(run) else t for t in train if t != "--check"]
    _exit2(deep + ["--init", "compact", "--reseed"], capsys,
           "compact.pt: a network of d_model 64, heads 4, ff_hidden 64, this config has model.d_model 128, "
           "model.heads 8, model.ff_hidden 128")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.pt"]


def test_train_device_and_missing_checkpoints(tmp_path, monkeypatch, capsys):
    torch = pytest.importorskip("torch")
    run = tmp_path / "run"
    train = ["train", "--config", str(CONFIG), "--run-dir", str(run), "--no-progress"]
    _exit2([*train, "--device", "tpu"], capsys, "--device tpu: expected cpu, cuda or cuda:N")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    _exit2([*train, "--device", "cuda"], capsys, "--device cuda: CUDA is not available", "--device cpu")
    for device, needle in (("tpu", "expected cpu, cuda or cuda:N"), ("cuda", "CUDA is not available")):
        _exit2([*train, "--check", "--device", device], capsys, f"--device {device}: {needle}")  # --check too
    missing = tmp_path / "nosuch.pt"
    _exit2([*train, "--resume", "--init", str(missing)], capsys, f"--init {missing}: no such checkpoint file")
    _exit2([*train, "--resume", "--init", str(tmp_path)], capsys, f"--init {tmp_path}: is a folder")
    _exit2([*train, "--resume", "--init", "nosuch"], capsys, "no shipped checkpoint of that name (shipped: broad,")
    _exit2([*train, "--resume"], capsys, f"--resume: no checkpoint {run / 'last.pt'} to continue")
    assert list(tmp_path.iterdir()) == []  # no run folder
    run.write_text("a file")
    _exit2(train, capsys, f"--run-dir {run}: exists and is not a folder")
    _exit2(["train", "--config", str(CONFIG), "--run-dir", str(tmp_path / "r2"), "--export", str(tmp_path)], capsys,
           f"--export {tmp_path}: is a folder, expected a file name")
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


@pytest.mark.parametrize("value", ["0", "-1", "inf", "nan"])
def test_time_limits_must_be_positive_and_finite(value, tmp_path, capsys):
    _exit2(["bound", str(EXAMPLE), "--time-limit", value], capsys, f"--time-limit: expected a positive number of "
                                                                    f"seconds, got {float(value)}")
    out = tmp_path / "s.jsonl"
    _exit2(["schedules", "--count", "1", "--time-limit", value, "--out", str(out), "--no-progress"], capsys,
           "--time-limit: expected a positive number of seconds")
    assert not out.exists()


def _unwritable_cases(tmp_path):
    sol = tmp_path / "in" / "sol.json"
    assert main(["solve", str(EXAMPLE), "--method", "greedy", "--out", str(sol)]) == 0
    return [
        ["solve", str(EXAMPLE), "--method", "greedy", "--out", "/proc/x.json"],
        ["render", str(EXAMPLE), str(sol), "--out", "/proc/x.png"],
        ["convert", str(EXAMPLE), "--out", "/proc/x.yaml"],
        ["bench", *ROW, "--methods", "greedy", "--no-progress", "--out", "/proc/x"],
        ["generate", *ROW, "--out", "/proc/x"],
        ["schedules", "--count", "1", "--no-progress", "--out", "/proc/x.jsonl"],
        ["demo", "--method", "greedy", "--out", "/proc/x.json"],
    ]


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc")
def test_unwritable_out_paths(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    for argv in _unwritable_cases(tmp_path):
        capsys.readouterr()
        out = argv[argv.index("--out") + 1]
        _exit2(argv, capsys, f"--out {out}: cannot write in /proc")
    _exit2(["keys", "create", "--robots", "a,b", "--out", "/proc/x"], capsys, "/proc/x: cannot write in /proc")
    assert [p.name for p in tmp_path.iterdir()] == ["in"]


def test_out_paths_of_the_wrong_kind_leave_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("keep")
    (tmp_path / "folder").mkdir()
    for argv, msg in (
        (["solve", str(EXAMPLE), str(CTAS), "--method", "greedy", "--out", "afile"], "--out afile: exists and is not a folder"),
        (["solve", str(EXAMPLE), "--method", "greedy", "--out", "afile/x.json"], "--out afile/x.json: afile is not a folder"),
        (["bench", *ROW, "--methods", "greedy", "--no-progress", "--out", "afile"], "--out afile: exists and is not a folder"),
        (["generate", *ROW, "--out", "afile"], "--out afile: exists and is not a folder"),
        (["convert", str(EXAMPLE), "--out", "folder"], "--out folder: is a folder, expected a file name"),
        (["convert", str(CTAS), "--out", "folder"], "--out folder: is a folder, expected a file name"),
        (["schedules", "--count", "1", "--out", "folder"], "--out folder: is a folder, expected a file name"),
        (["convert", str(EXAMPLE), "--out", "new/"], "--out new/: names a folder (a trailing /), expected a file name"),
        (["demo", "--method", "greedy", "--out", "new/"], "--out new/: names a folder (a trailing /)"),
        (["keys", "create", "--robots", "a", "--out", "afile"], "afile: exists and is not a folder"),
    ):
        _exit2(argv, capsys, msg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "folder"]
    assert afile.read_text() == "keep" and list((tmp_path / "folder").iterdir()) == []


def test_keys_create_refuses_the_current_folder(tmp_path, monkeypatch, capsys):
    here = tmp_path / "here"
    here.mkdir()
    (here / "notes.txt").write_text("mine")
    monkeypatch.chdir(here)
    for out in (".", str(here), ".."):
        _exit2(["keys", "create", "--robots", "a,b", "--out", out, "--force"], capsys,
               f"{out}: is the current folder or holds it")
    assert [p.name for p in tmp_path.iterdir()] == ["here"] and [p.name for p in here.iterdir()] == ["notes.txt"]


def test_solve_refuses_inputs_that_share_an_output_name(tmp_path, capsys):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "m.yaml").write_text(EXAMPLE.read_text())
    out = tmp_path / "out"
    a, b = tmp_path / "a" / "m.yaml", tmp_path / "b" / "m.yaml"
    _exit2(["solve", str(a), str(b), "--method", "greedy", "--out", str(out)], capsys,
           f"--out {out}: {a} and {b} would both be written to {out / 'm.json'}")
    assert not out.exists()


@pytest.mark.parametrize("cmd", ["solve", "bound"])
def test_a_bad_file_in_a_folder_stops_before_anything_is_done(cmd, tmp_path, capsys):
    folder = _missions(tmp_path, 2)
    bad = folder / "zz_bad.yaml"  # sorted last: the others would be done first
    bad.write_text("garbage: [\n")
    capsys.readouterr()
    argv = [cmd, str(folder), "--no-progress"] + (["--method", "greedy", "--out", str(tmp_path / "sols")]
                                                  if cmd == "solve" else [])
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and f"{bad}:2: invalid YAML" in err and "Traceback" not in err  # nothing printed ...
    assert not (tmp_path / "sols").exists()  # ... nor written


@pytest.mark.parametrize("text", ["", "\n", "# only a comment\n"])
def test_an_empty_instance_file_says_so(text, tmp_path, capsys):
    f = tmp_path / "empty.yaml"
    f.write_text(text)
    for argv in (["solve", str(f)], ["bound", str(f)], ["convert", str(f), "--out", str(tmp_path / "x.yaml")]):
        line = _exit2(argv, capsys, f"{f}: the file is empty (expected an hmrta-instance/1 mission")
        assert "NoneType" not in line
    assert [p.name for p in tmp_path.iterdir()] == ["empty.yaml"]
    f.write_text(re.sub(r"^species:.*\n", "species:\n  -\n", EXAMPLE.read_text(), count=1, flags=re.M))
    assert "NoneType" not in _exit2(["solve", str(f)], capsys, "species[0]: expected a mapping", "got nothing")


def test_solve_out_is_a_file_for_one_mission_with_a_suffixed_name(tmp_path, capsys):
    """One mission: --out NAME.SUFFIX is the solution file whatever the suffix; a name without a
    suffix, a trailing slash or an existing folder is a folder of <stem>.json. Several missions
    need a folder."""
    for name, want in (("sol.json", "sol.json"), ("out.txt", "out.txt"), ("sols", "sols/example.json"),
                       ("dir.d/", "dir.d/example.json")):
        assert main(["solve", str(EXAMPLE), "--method", "greedy", "--out", f"{tmp_path}/{name}"]) == 0, name
        capsys.readouterr()
        assert json.loads((tmp_path / want).read_text())["method"] == "greedy", name
    (tmp_path / "old.v2").mkdir()
    assert main(["solve", str(EXAMPLE), "--method", "greedy", "--out", str(tmp_path / "old.v2")]) == 0
    capsys.readouterr()
    assert (tmp_path / "old.v2" / "example.json").is_file()
    _exit2(["solve", str(EXAMPLE), str(CTAS), "--method", "greedy", "--out", str(tmp_path / "two.txt")], capsys,
           "with several instances, --out must be a folder")


def test_generate_caps_the_mission_and_the_set(tmp_path, capsys):
    """A set is drawn in memory before it is written: at most 100,000 tasks a mission and
    1,000,000 in the set, refused before anything is drawn."""
    row = ["generate", "--scenario", "MA-AT", "--agents", "4", "--species", "2", "--skills", "2"]
    _exit2([*row, "--tasks", "100001", "--count", "1", "--out", str(tmp_path / "a")], capsys,
           "tasks (100001): a mission holds at most 100000")
    _exit2([*row, "--tasks", "2000", "--count", "100000000", "--out", str(tmp_path / "b")], capsys,
           "at most 1,000,000 tasks in one set")
    _exit2([*row[:-1], "100000000", "--tasks", "3", "--count", "1", "--out", str(tmp_path / "c")], capsys,
           "skills (100000000): a mission has at most 1000")  # (2 ** skills, drawn at once, would not end)
    assert list(tmp_path.iterdir()) == []


def test_schedule_names_cancelled_tasks_and_lost_robots(tmp_path, capsys):
    """--schedule of a mission with events: a task not done says why (cancelled by the operator,
    or no longer satisfiable after a loss), a lost robot shows when, and a failed mission prints
    no 'nan' return times."""
    (tmp_path / "m.yaml").write_text(
        "format: hmrta-instance/1\nrequirement_type: additive\nvelocity: 0.2\nskills: 1\n"
        "species: [{traits: [1], count: 2, depot: [0.0, 0.0]}]\n"
        "tasks:\n  - {location: [0.2, 0.0], requirements: [1], duration: 2}\n"
        "  - {location: [0.0, 0.4], requirements: [2], duration: 2}\n"
        "  - {location: [0.6, 0.0], requirements: [1], duration: 1}\n")
    (tmp_path / "s.yaml").write_text("format: hmrta-scenario/1\ninstance: m.yaml\n"
                                     "events: [{t: 3.0, type: lose_robot, robot: 0}]\n")
    assert main(["solve", str(tmp_path / "s.yaml"), "--method", "greedy", "--schedule"]) == 3  # task 1 lost
    out = capsys.readouterr().out
    assert "(cancelled at 3.00: no longer satisfiable)" in out and "lost 3.00" in out and "nan" not in out
    (tmp_path / "c.yaml").write_text("format: hmrta-scenario/1\ninstance: m.yaml\n"
                                     "events: [{t: 2.0, type: cancel_task, id: 2}]\n")
    assert main(["solve", str(tmp_path / "c.yaml"), "--method", "greedy", "--schedule"]) == 0
    assert "(cancelled at 2.00)" in capsys.readouterr().out


def test_a_mission_beyond_the_learned_policy_is_refused_naming_the_file_before_any_work(tmp_path, capsys):
    """More skills than the policy takes: the rl methods refuse the file (one line, exit 2, nothing
    written); the default method leaves them out and says so."""
    from hmrta.generators import ScenarioGenerator

    mission = tmp_path / "seven.yaml"
    ScenarioGenerator("MA-AT", 6, 3, 5, 7).instance(0, 0).save(mission)
    for method in ("rl", "rl-s10", "rl@broad"):
        assert main(["solve", str(mission), "--method", method, "--out", str(tmp_path / "out.json")]) == 2
        line = _one_error_line(capsys)
        assert line.startswith(f"hmrta: error: {mission}: method rl") and "at most 5 skills, the mission has 7" in line
        assert not (tmp_path / "out.json").exists()
    assert main(["solve", str(mission), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "chose greedy" in out and "left out: rl, rl@broad, rl@coalition-team (method rl: the learned policy " \
                                     "handles at most 5 skills, the mission has 7" in out


def test_a_reader_that_goes_early_loses_no_output_file(tmp_path):
    """``hmrta solve ... | head -1``: the pipe closes after the first summary line; every mission
    is still solved and written, with no traceback and exit 0 (``demo --out`` too)."""
    import subprocess

    folder = _missions(tmp_path, 3)
    out = tmp_path / "sols"
    cmd = [sys.executable, "-m", "hmrta.cli"]
    for args, written in (
            (["solve", str(folder), "--method", "greedy", "--out", str(out), "--schedule"],
             [out / f"{f.stem}.json" for f in sorted(folder.glob("*.yaml"))]),
            (["demo", "--method", "greedy", "--out", str(tmp_path / "demo.json")], [tmp_path / "demo.json"])):
        proc = subprocess.Popen(cmd + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        proc.stdout.readline()
        proc.stdout.close()  # the reader goes
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=120) == 0, err
        assert "Traceback" not in err, err
        assert all(f.exists() for f in written), (args, list(out.glob("*")) if out.exists() else [])


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_standard_output_that_cannot_be_written_is_one_line_and_no_output_file_is_lost(tmp_path):
    """``hmrta solve ... > /dev/full``: the solution file is still written whole; the lost summary
    is said in one line, exit 1, no traceback."""
    import subprocess

    out = tmp_path / "sol.json"
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "hmrta.cli", "solve", str(EXAMPLE), "--method", "greedy",
                               "--out", str(out), "--no-progress"], stdout=full, stderr=subprocess.PIPE, timeout=120)
    err = proc.stderr.decode()
    assert proc.returncode == 1 and "Traceback" not in err, err
    assert err.strip() == "hmrta: error: cannot write to standard output (No space left on device)"
    assert json.loads(out.read_text())["success"]


def test_an_output_is_never_one_of_the_inputs(tmp_path, capsys):
    """``--out`` naming a file the command reads is refused before any work (exit 2, one line),
    and the file is left as it was: solve (a file, or a folder holding the input's .json name),
    convert, render."""
    mission = tmp_path / "m.yaml"
    mission.write_text(EXAMPLE.read_text())
    sol = tmp_path / "m.json"
    assert main(["solve", str(mission), "--method", "greedy", "--out", str(sol)]) == 0
    before = {p: p.read_bytes() for p in (mission, sol)}
    capsys.readouterr()
    for argv, culprit in ((["solve", str(mission), "--method", "greedy", "--out", str(mission)], mission),
                          (["solve", str(sol.with_suffix(".yaml")), "--method", "greedy", "--out", str(tmp_path / "x.json")], None),
                          (["convert", str(mission), "--out", str(mission)], mission),
                          (["render", str(mission), str(sol), "--out", str(sol)], sol)):
        if culprit is None:  # (a control: a different output is fine)
            assert main(argv) == 0
            capsys.readouterr()
            continue
        assert main(argv) == 2, argv
        assert "is an input of this command" in _one_error_line(capsys)
    assert {p: p.read_bytes() for p in (mission, sol)} == before
    # a folder output whose <stem>.json would be an input (a solution named like its mission)
    ctas = tmp_path / "c"
    ctas.mkdir()
    (ctas / "config.json").write_text((CTAS / "config.json").read_text())
    assert main(["solve", str(ctas / "config.json"), "--method", "greedy", "--out", str(ctas)]) == 2
    assert "is an input of this command" in _one_error_line(capsys)


def test_an_output_is_never_the_mission_a_scenario_names(tmp_path, capsys):
    mission = tmp_path / "m.yaml"
    mission.write_text(EXAMPLE.read_text())
    scen = tmp_path / "s.yaml"
    scen.write_text("format: hmrta-scenario/1\ninstance: m.yaml\nevents:\n  - {t: 1.0, type: cancel_task, id: 0}\n")
    before = mission.read_bytes()
    capsys.readouterr()
    assert main(["solve", str(scen), "--method", "greedy", "--out", str(mission)]) == 2
    assert "is an input of this command" in _one_error_line(capsys) and mission.read_bytes() == before


def test_bench_refuses_a_mission_given_twice(tmp_path, capsys):
    """Its results would count twice in the row's means: the same file, or a folder given twice."""
    folder = tmp_path / "mine"
    folder.mkdir()
    shutil.copyfile(EXAMPLE, folder / "a.yaml")
    out = tmp_path / "out"
    _exit2(["bench", str(EXAMPLE), str(EXAMPLE), "--methods", "greedy", "--out", str(out)], capsys,
           f"{EXAMPLE}: given twice: its results would count twice")
    _exit2(["bench", str(folder), str(folder / "a.yaml"), "--methods", "greedy", "--out", str(out)], capsys,
           f"{folder / 'a.yaml'}: given twice")
    assert not out.exists()


def test_a_ctas_folder_that_also_holds_missions_says_they_are_not_read(tmp_path, capsys):
    folder = tmp_path / "both"
    shutil.copytree(CTAS, folder)
    shutil.copyfile(EXAMPLE, folder / "mine.yaml")
    assert main(["solve", str(folder), "--method", "greedy", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert f"warning: {folder}: read as one CTAS-D mission (its config.json); the *.yaml files in it are not read" in err
    assert main(["solve", str(CTAS), "--method", "greedy", "--no-progress"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_an_unknown_option_points_to_its_commands_help(capsys):
    for argv, said in ((["solve", str(EXAMPLE), "--bogus"],
                        "hmrta solve: error: unrecognized arguments: --bogus (see hmrta solve --help)"),
                       (["checkpoint", "average", "a.pt", "--out", "b.pt", "--bogus"],
                        "hmrta checkpoint average: error: unrecognized arguments: --bogus (see hmrta checkpoint "
                        "average --help)")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2 and capsys.readouterr().err.strip() == said


def test_a_resumed_bench_says_how_many_of_its_results_the_cache_holds(tmp_path, capsys):
    mission = tmp_path / "m.yaml"
    mission.write_text(EXAMPLE.read_text())
    argv = ["bench", str(mission), "--methods", "greedy,greedy-coalition", "--out", str(tmp_path / "res"),
            "--no-progress"]
    assert main(argv) == 0
    assert "resuming" not in capsys.readouterr().err
    assert main(argv) == 0
    assert f"resuming: 2 of 2 results cached in {tmp_path / 'res' / 'cache.jsonl'}" in capsys.readouterr().err
    mission.write_text(EXAMPLE.read_text().replace("velocity: 0.2", "velocity: 0.3"))  # another mission
    assert main(argv) == 0
    assert "resuming: 0 of 2 results cached" in capsys.readouterr().err
