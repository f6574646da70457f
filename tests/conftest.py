"""Shared fixtures for the hmrta test suite (kept minimal)."""
from __future__ import annotations

import copy
import signal
from pathlib import Path

import pytest
import yaml

DATA = Path(__file__).parent / "policy" / "data"

# A test run started in the background (``cmd &`` in a script, as a CI runner may) inherits SIGINT
# ignored, and so would every process it starts: the tests of what a Ctrl-C does would then test
# nothing. The suite runs as from a terminal: Python's own SIGINT handler (children start with the
# default disposition).
if signal.getsignal(signal.SIGINT) in (signal.SIG_IGN, signal.SIG_DFL, None):
    signal.signal(signal.SIGINT, signal.default_int_handler)

# A small valid `hmrta-instance/1` mapping: 3 skills, team traits [2, 1, 2].
VALID = {
    "format": "hmrta-instance/1",
    "name": "valid",
    "requirement_type": "additive",
    "velocity": 0.2,
    "skills": 3,
    "species": [
        {"traits": [1, 0, 1], "count": 2, "depot": [0.1, 0.8]},
        {"traits": [0, 1, 0], "count": 1, "depot": [0.5, 0.5]},
    ],
    "tasks": [
        {"location": [0.5, 0.9], "requirements": [0, 1, 1], "duration": 3.5},
        {"location": [0.2, 0.2], "requirements": [2, 1, 0], "duration": 0},
    ],
}


@pytest.fixture
def valid_dict():
    """A fresh deep copy of a valid instance mapping (mutate freely)."""
    return copy.deepcopy(VALID)


@pytest.fixture
def data_dir() -> Path:
    return DATA


@pytest.fixture
def write_yaml(tmp_path):
    """write_yaml(obj_or_text, name='inst.yaml') -> Path of a file under tmp_path."""

    def _write(obj, name: str = "inst.yaml") -> Path:
        p = tmp_path / name
        p.write_text(obj if isinstance(obj, str) else yaml.safe_dump(obj, sort_keys=False))
        return p

    return _write


class Trace:
    """What a traced rollout observed besides the final state."""

    def __init__(self):
        self.arrivals: dict[tuple[int, int], float] = {}  # (agent, task) -> arrival time
        self.idle_commits = 0  # departures (to a task or home) later than the agent became free, not back-dated
        self.home_commits = 0  # task commitments by agents parked at / heading to their depot


def _traced_run(inst, policy, seed=0, rules=None):
    """Roll out like hmrta.sim.run, recording every arrival and every delayed departure."""
    from hmrta.core import FREE, HOME, WAIT, MissionState, Rules

    state = MissionState(inst, seed=seed, rules=rules or Rules())
    trace = Trace()
    orig = state.commit

    def commit(a, node):
        mode = state.mode[a]
        if node > 0 and mode == HOME:
            trace.home_commits += 1
        elif mode in (FREE, WAIT) and state.clock > state.free_since[a] and not state.rules.backdate:
            trace.idle_commits += 1  # to a task or (late) home
        orig(a, node)
        if node > 0:
            trace.arrivals[(a, node - 1)] = float(state.arrive[a])

    state.commit = commit  # step() looks the method up on the instance
    while not state.done:
        state.step(policy(state))
    return state, trace


@pytest.fixture
def traced_run():
    """traced_run(inst, policy, seed, rules) -> (finished MissionState, Trace)."""
    return _traced_run


def _check_rollout(inst, state, trace, sol):
    """The invariants every successful simulated solution must satisfy (issue 2, points 5, 6, 9).

    Returns the route-evaluation Solution. Exact makespan reproduction is required when no agent
    went home mid-mission and no departure was delayed; otherwise route evaluation (which leaves
    at once, straight to the next task) may only be lower.
    """
    import numpy as np

    from hmrta.core import HOME
    from hmrta.solution import evaluate_routes

    assert sol.success, sol.extra.get("failure")
    A, M = inst.n_agents, inst.n_tasks
    traits, req = inst.traits, inst.requirements
    # every task is done by a coalition that satisfies it (computed from the raw instance)
    for m, t in enumerate(sol.tasks):
        members = t["members"]
        assert members == sorted(a for a in range(A) if m in sol.routes[a])
        c = traits[members].sum(0) if members else np.zeros(inst.skills)
        if inst.additive:
            assert (c >= req[m] - inst.cover_tol).all(), (m, c, req[m])  # (0 unless decimals: rounding)
        else:
            assert ((c > 0) | (req[m] == 0)).all(), (m, c, req[m])
        # SPEC §3, rule 3: start = latest arrival of the members; finish = start + duration
        arr = [trace.arrivals[(a, m)] for a in members]
        assert all(t["start"] >= x for x in arr)
        assert t["start"] == max(arr)
        assert t["finish"] == t["start"] + inst.durations[m]
    # routes are consistent in time: leave after the previous finish, travel at least straight
    wait = np.zeros(A)
    for a, r in enumerate(sol.routes):
        assert len(set(r)) == len(r)
        pos, free = inst.depots[a], 0.0
        for m in r:
            arr = trace.arrivals[(a, m)]
            assert arr >= free + inst.travel_time(pos, inst.task_locations[m]) - 1e-9
            wait[a] += sol.tasks[m]["start"] - arr
            pos, free = inst.task_locations[m], sol.tasks[m]["finish"]
        ret = sol.agents[a]["return_time"]
        assert ret >= free + inst.travel_time(pos, inst.depots[a]) - 1e-9
    # all agents home, makespan = last return, after every finish
    assert (state.mode == HOME).all()
    assert np.array_equal(state.to_pos, inst.depots)
    assert sol.makespan == max([a["return_time"] for a in sol.agents], default=0.0)
    assert all(sol.makespan >= t["finish"] for t in sol.tasks)
    # AWT (SPEC §4): per agent waiting at tasks, averaged over all agents (idle ones included)
    assert (wait >= 0).all() and sol.awt >= 0
    assert sol.awt == pytest.approx(float(wait.mean()), rel=1e-12, abs=1e-12)
    # route evaluation
    ev = evaluate_routes(inst, sol.routes)
    assert ev.redundancy == sol.redundancy
    delayed = "depot_stops" in sol.extra or trace.idle_commits or trace.home_commits
    if not delayed:
        assert ev.makespan == sol.makespan
        assert ev.tasks == sol.tasks and ev.agents == sol.agents
    assert ev.makespan <= sol.makespan + 1e-9
    if trace.home_commits:
        assert "depot_stops" in sol.extra
    return ev


@pytest.fixture
def check_rollout():
    """check_rollout(inst, state, trace, sol) -> evaluate_routes Solution (asserts the invariants)."""
    return _check_rollout
