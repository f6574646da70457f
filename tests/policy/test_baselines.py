"""Greedy, coalition-aware greedy and random baselines (issue 2, point 7) and simulator invariants on
the paper rows (point 5)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hmrta.baselines import GREEDY_RULES, CoalitionGreedy, Greedy, RandomPolicy
from hmrta.core import IN_PROGRESS, LOST, OPEN, TASK, MissionState, Rules
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


def _reference_coalition_choice(s: MissionState) -> int:
    """Loop-by-loop restatement of CoalitionGreedy's documented rule (checks the vectorised one)."""
    mask = s.mask()[1:]
    if not mask.any():
        return 0
    a, t, v, loc = s.agent, s.clock, s.inst.velocity, s.inst.task_locations
    me = s.position(a)
    best = None
    for j in np.flatnonzero(mask):
        mine = t + np.hypot(*(loc[j] - me)) / v
        start = max([mine] + [s.arrive[m] for m in s.members[j]])
        rem = np.maximum(s.rem[j] - s.cap[a], 0)
        arrivals = []
        for b in range(s.A):
            if b == a or s.mode[b] == LOST:
                continue
            free_at, pos = t, s.position(b)
            if s.mode[b] == TASK and s.target[b] >= 0:
                k = s.target[b]
                if s.status[k] == OPEN:
                    continue  # held at an open task
                if s.status[k] == IN_PROGRESS:
                    free_at, pos = s.finish[k], loc[k]
            arrivals.append((free_at + np.hypot(*(loc[j] - pos)) / v, b))
        for arr, b in sorted(arrivals):
            if not (rem > 1e-9).any():
                break
            if (np.minimum(rem, s.cap[b]) > 0).any():
                rem = np.maximum(rem - s.cap[b], 0)
                start = max(start, arr)
        if (rem > 1e-9).any():
            start = np.inf
        key = (start, mine, j)
        best = key if best is None or key < best else best
    return 1 + int(best[2])


@pytest.mark.parametrize("scenario,row", [("MA-AT", (9, 3, 20, 3)), ("MA-AT", (15, 5, 20, 5)), ("SA-BT", (9, 3, 20, 3))])
def test_coalition_greedy_follows_its_documented_rule(scenario, row):
    cg = CoalitionGreedy()
    for i, inst in enumerate(ScenarioGenerator(scenario, *row).generate(2, seed=31)):
        state = MissionState(inst, seed=i, rules=GREEDY_RULES)
        while not state.done:
            node = cg(state)
            assert node == _reference_coalition_choice(state)
            state.step(node)
        assert state.success


def test_coalition_greedy_prefers_the_task_that_can_start_first():
    """The nearest task needs a partner who is far away; a slightly farther solo task starts first."""
    from hmrta.instance import instance_from_dict

    inst = instance_from_dict({
        "format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2, "skills": 1,
        "species": [{"traits": [1], "count": 1, "depot": [0.5, 0.5]},
                    {"traits": [1], "count": 1, "depot": [0.0, 0.0]}],
        "tasks": [{"location": [0.55, 0.5], "requirements": [2], "duration": 1},
                  {"location": [0.5, 0.65], "requirements": [1], "duration": 1}]})
    state = MissionState(inst, 0, GREEDY_RULES)
    while state.agent != 0:  # the agent at the centre decides
        state.step(Greedy()(state))
    assert Greedy()(state) == 1  # nearest: the two-robot task
    assert CoalitionGreedy()(state) == 2  # its partner needs 3.7 time units; the solo task starts at 0.75


@pytest.mark.parametrize("scenario,row", SMALL[::2], ids=[row_name(s, *r) for s, r in SMALL[::2]])
def test_coalition_greedy_solves_paper_rows(scenario, row, traced_run, check_rollout):
    for inst in ScenarioGenerator(scenario, *row).generate(4, seed=2024):
        state, trace = traced_run(inst, CoalitionGreedy(), 0, GREEDY_RULES)
        sol = solution_from_state(state, "greedy-coalition", 0, 0.0)
        assert sol.success, (inst.name, sol.extra)
        check_rollout(inst, state, trace, sol)


def test_coalition_greedy_method_and_decider():
    from hmrta.methods import decider
    from hmrta.sim import run

    inst = ScenarioGenerator("MA-AT", 9, 3, 20, 3).instance(seed=8, index=0)
    sol = solve(inst, "greedy-coalition", seed=2)
    decide, rules = decider("greedy-coalition")
    live = run(inst, decide, 2, rules)
    assert sol.success and sol.method == "greedy-coalition"
    assert live.routes == sol.routes and live.makespan == sol.makespan


def test_coalition_greedy_with_no_partner_left():
    """Every other robot lost: tasks that need a partner get an infinite estimate, no crash."""
    inst = ScenarioGenerator("MA-AT", 9, 3, 20, 3).instance(seed=8, index=1)
    state = MissionState(inst, seed=0, rules=GREEDY_RULES)
    a = state.agent
    for b in range(state.A):
        if b != a:
            state.drop_agent(b)
    if state.done or state.agent != a:
        pytest.skip("the mission ended when the others were dropped")
    cand, start, mine = CoalitionGreedy().estimates(state)
    solo = ~(np.maximum(state.rem[cand] - state.cap[a], 0) > 1e-9).any(1)
    assert np.isinf(start[~solo]).all() and np.isfinite(start[solo]).all()
    assert CoalitionGreedy()(state) == _reference_coalition_choice(state)
