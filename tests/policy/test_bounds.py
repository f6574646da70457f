"""Cheap lower bounds: valid (never above an optimum or any solution), exact where they should be."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hmrta.bounds import BOUND_DOCS, lower_bounds
from hmrta.generators import ScenarioGenerator
from hmrta.instance import Instance, Species, Task
from hmrta.methods import solve

sys.path.insert(0, str(Path(__file__).parent))


def test_keys_and_best():
    inst = ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(1, 0)
    b = lower_bounds(inst)
    assert set(BOUND_DOCS) <= set(b)
    assert b["best"] == max(b[k] for k in BOUND_DOCS)
    assert b[b["best_name"]] == b["best"]
    assert all(v >= 0 for k, v in b.items() if k != "best_name")


def test_single_task_round_trip_is_exact():
    # one agent: out 5, work 2, back 5
    inst = Instance("additive", 0.2, 1, (Species((1.0,), 1, (0.0, 0.0)),), (Task((0.6, 0.8), (1.0,), 2.0),))
    b = lower_bounds(inst)
    assert b["task_round_trip"] == pytest.approx(12.0)
    assert b["best"] == pytest.approx(solve(inst, "greedy").makespan)


def test_round_trip_needs_enough_of_a_skill():
    # skill 0 needs 2: the near species has only 1 agent, so the far species must come too
    near = Species((1.0,), 1, (0.5, 0.5))
    far = Species((1.0,), 1, (0.5, 0.0))
    inst = Instance("additive", 0.2, 1, (near, far), (Task((0.5, 0.6), (2.0,), 1.0),))
    b = lower_bounds(inst)
    far_trip = 2 * inst.travel_time((0.5, 0.0), (0.5, 0.6))
    assert b["task_round_trip"] == pytest.approx(far_trip + 1.0)
    assert b["best"] <= solve(inst, "greedy").makespan + 1e-9


def test_empty_instance():
    inst = Instance("binary", 0.2, 1, (Species((1.0,), 1, (0.0, 0.0)),), ())
    assert lower_bounds(inst)["best"] == 0.0


@pytest.mark.parametrize("scen,row", [("MA-AT", (3, 3, 4, 3)), ("SA-AT", (4, 2, 4, 2)), ("MA-BT", (3, 3, 4, 3)),
                                      ("SA-BT", (4, 2, 5, 2))])
def test_below_brute_force_optimum(scen, row):
    from test_cpsat import brute_force

    for i in range(3):
        inst = ScenarioGenerator(scen, *row).instance(11, i)
        opt, _ = brute_force(inst)
        b = lower_bounds(inst)
        for k in BOUND_DOCS:
            assert b[k] <= opt + 1e-9, (k, b[k], opt)


@pytest.mark.parametrize("scen,row", [("MA-AT", (15, 5, 20, 5)), ("SA-AT", (9, 3, 20, 3)), ("SA-BT", (25, 5, 20, 5)),
                                      ("MA-AT", (50, 5, 50, 5))])
def test_below_heuristic_solutions(scen, row):
    from hmrta.solvers.listsched import best_list_schedule

    for i in range(3):
        inst = ScenarioGenerator(scen, *row).instance(2, i)
        b = lower_bounds(inst)["best"]
        assert 0 < b <= solve(inst, "greedy").makespan + 1e-9
        assert b <= best_list_schedule(inst, 0, 0.0).makespan + 1e-9


def test_report_with_solutions():
    from hmrta.bounds import bound_report, format_report

    inst = ScenarioGenerator("MA-AT", 9, 3, 8, 3).instance(1, 0)
    g = solve(inst, "greedy")
    g.extra["lower_bound"] = 1e-3  # a weak solver bound does not replace the cheap ones
    rep = bound_report(inst, [g])
    assert rep["best"] == lower_bounds(inst)["best"]
    assert rep["solutions"][0]["gap"] == pytest.approx((g.makespan - rep["best"]) / g.makespan)
    g.extra.update(lower_bound=g.makespan - 1.0, status="feasible")
    rep = bound_report(inst, [g])
    assert rep["best"] == g.makespan - 1.0 and rep["best_name"] == "greedy (solver)"
    text = format_report(rep)
    assert "task_round_trip" in text and "gap to best bound" in text


def test_release_times_bound_the_makespan():
    """A task released at 30 starts no sooner, is worked 2 and its members go 4 home: 36. Every
    method's makespan on missions with release times is above the bound."""
    import dataclasses

    import numpy as np

    inst = Instance("additive", 0.2, 1, (Species((1.0,), 2, (0.1, 0.1)),),
                    (Task((0.5, 0.5), (1.0,), 1.0), Task((0.9, 0.1), (2.0,), 2.0, release=30.0)))
    b = lower_bounds(inst)
    assert b["release"] == pytest.approx(36.0) and b["best_name"] == "release"
    assert solve(inst, "greedy").makespan >= b["release"]
    assert lower_bounds(dataclasses.replace(inst, tasks=(inst.tasks[0], dataclasses.replace(inst.tasks[1], release=0.0)),
                                            _cache={}))["release"] == 0.0
    for i, base in enumerate(ScenarioGenerator("MA-AT", 9, 3, 20, 3).generate(5, 9)):
        rng = np.random.default_rng(i)
        inst = dataclasses.replace(base, tasks=tuple(dataclasses.replace(t, release=float(rng.random() * 40))
                                                     for t in base.tasks), _cache={})
        best = lower_bounds(inst)["best"]
        for method in ("greedy", "greedy-coalition"):
            assert solve(inst, method).makespan >= best - 1e-9, (i, method)


def test_bound_reads_a_routes_file_as_evaluate_does(tmp_path, capsys):
    import json

    from hmrta.cli import main

    example = Path(__file__).parent / "data" / "example.yaml"
    sol = tmp_path / "s.json"
    assert main(["solve", str(example), "--method", "greedy", "--out", str(sol)]) == 0
    routes = tmp_path / "r.json"
    routes.write_text(json.dumps({"routes": json.loads(sol.read_text())["routes"]}))
    capsys.readouterr()
    assert main(["bound", str(example), str(routes), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["solutions"][0]["makespan"] == pytest.approx(json.loads(sol.read_text())["makespan"])


def test_a_routes_file_of_a_mission_with_release_times_is_refused(tmp_path, capsys):
    """Routes are re-simulated without release times (hmrta evaluate refuses them too): bound asks
    for the solution file instead of reporting a makespan below its own bound."""
    import json

    from hmrta.cli import main

    mission = tmp_path / "rel.yaml"
    mission.write_text(json.dumps({"format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2,
                                   "skills": 1, "species": [{"traits": [1], "count": 2, "depot": [0.1, 0.1]}],
                                   "tasks": [{"location": [0.5, 0.5], "requirements": [1], "duration": 1},
                                             {"location": [0.9, 0.1], "requirements": [2], "duration": 2,
                                              "release": 20}]}))
    sol = tmp_path / "s.json"
    assert main(["solve", str(mission), "--method", "greedy", "--out", str(sol)]) == 0
    routes = tmp_path / "r.json"
    routes.write_text(json.dumps({"routes": json.loads(sol.read_text())["routes"]}))
    capsys.readouterr()
    assert main(["bound", str(mission), str(routes)]) == 2
    assert "re-simulated without release times" in capsys.readouterr().err
    assert main(["bound", str(mission), str(sol)]) == 0
