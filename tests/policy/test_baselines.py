"""Greedy and random baselines (issue 2, point 7) and simulator invariants on the paper rows (point 5)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hmrta.baselines import GREEDY_RULES, Greedy, RandomPolicy
from hmrta.core import MissionState, Rules
from hmrta.generators import PAPER_ROWS, ScenarioGenerator, row_name
from hmrta.methods import solve
from hmrta.solution import solution_from_state

ROWS = [("MA-AT" if sc == "MA-AT-large" else sc, r) for sc, rows in PAPER_ROWS.items() for r in rows]
SMALL = [(sc, r) for sc, r in ROWS if r[2] < 500]
LARGE = [(sc, r) for sc, r in ROWS if r[2] >= 500]


@pytest.mark.parametrize("backdate", [True, False], ids=["backdate", "realtime"])
@pytest.mark.parametrize("scenario,row", SMALL, ids=[row_name(s, *r) for s, r in SMALL])
def test_greedy_solves_every_paper_row(scenario, row, backdate, traced_run, check_rollout):
    """Like the paper's greedy: 100% success; every solution satisfies the invariants. Also under
    real-time rules (no back-dated departures), as the live task board runs it."""
    rules = dataclasses.replace(GREEDY_RULES, backdate=backdate)
    for inst in ScenarioGenerator(scenario, *row).generate(10, seed=2024):
        state, trace = traced_run(inst, Greedy(), 0, rules)
        sol = solution_from_state(state, "greedy", 0, 0.0)
        assert sol.success, (inst.name, sol.extra)
        check_rollout(inst, state, trace, sol)


@pytest.mark.parametrize("scenario,row", LARGE, ids=[row_name(s, *r) for s, r in LARGE])
def test_greedy_solves_large_rows(scenario, row):
    inst = ScenarioGenerator(scenario, *row).instance(seed=2024, index=0)
    sol = solve(inst, "greedy", seed=1)
    assert sol.success and sol.method == "greedy" and sol.makespan > 0


def test_greedy_takes_the_nearest_admissible_task():
    """Exact rule: nearest admissible task from the decider's position (lowest id on ties), never
    the depot while a task is admissible."""
    inst = ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(seed=3, index=1)
    state = MissionState(inst, seed=0, rules=GREEDY_RULES)
    g = Greedy()
    n = 0
    while not state.done:
        mask = state.mask()
        here = state.position(state.agent)
        d = np.hypot(*(inst.task_locations - here).T)
        best = min((d[m], m) for m in np.flatnonzero(mask[1:]))[1]
        node = g(state)
        assert node == 1 + best
        state.step(node)
        n += 1
    assert state.success and n == state.decisions > 0


def test_greedy_tie_breaks_by_lowest_id():
    from hmrta.instance import instance_from_dict

    inst = instance_from_dict({
        "format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2, "skills": 1,
        "species": [{"traits": [1], "count": 1, "depot": [0.5, 0.5]}],
        "tasks": [{"location": [0.5, 0.9], "requirements": [1], "duration": 1},
                  {"location": [0.5, 0.1], "requirements": [1], "duration": 1},
                  {"location": [0.1, 0.5], "requirements": [1], "duration": 1}]})
    state = MissionState(inst, 0, GREEDY_RULES)
    assert Greedy()(state) == 1


def test_greedy_rules_are_documented():
    assert GREEDY_RULES.max_open == 2 and GREEDY_RULES.safety and GREEDY_RULES.backdate
    import hmrta.baselines as b

    assert "nearest" in b.__doc__ and "max-open" in b.__doc__ and "deadlock" in b.__doc__


def test_random_policy_is_seeded():
    inst = ScenarioGenerator("SA-AT", 15, 5, 20, 5).instance(seed=5, index=0)
    a = solve(inst, "random", seed=4).to_dict()
    b = solve(inst, "random", seed=4).to_dict()
    a.pop("compute_seconds"), b.pop("compute_seconds")
    assert a == b and a["success"]
    others = set()
    for s in range(5):
        d = solve(inst, "random", seed=s).to_dict()
        others.add(str(d["routes"]))
    assert len(others) > 1


@pytest.mark.parametrize("scenario,row", SMALL[:: 3], ids=[row_name(s, *r) for s, r in SMALL[:: 3]])
def test_random_policy_always_completes_with_safety(scenario, row, traced_run, check_rollout):
    """The deadlock-avoidance mask completes every feasible instance whatever the policy picks."""
    for i, inst in enumerate(ScenarioGenerator(scenario, *row).generate(3, seed=99)):
        for rules in (Rules(), Rules(max_open=1), Rules(max_open=3)):
            state, trace = traced_run(inst, RandomPolicy(i, depot_weight=0.5), i, rules)
            sol = solution_from_state(state, "random", i, 0.0)
            check_rollout(inst, state, trace, sol)
