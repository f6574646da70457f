"""Property tests (hypothesis, derandomized): any feasible small instance x {greedy, random policy}
-> every task satisfied, all agents home, start >= every member's arrival, AWT >= 0, and route
evaluation reproduces the makespan (exactly without depot stops or delayed departures, else lower).
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from hmrta.baselines import GREEDY_RULES, Greedy, RandomPolicy
from hmrta.core import MissionState, Rules
from hmrta.generators import SCENARIOS, ScenarioGenerator
from hmrta.instance import instance_from_dict
from hmrta.solution import solution_from_state

SETTINGS = settings(max_examples=150, derandomize=True, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

GRID = [0.0, 0.25, 0.5, 0.75, 1.0]  # coarse grid: shared locations and equal distances (ties)


@st.composite
def generated(draw):
    """An instance of a scenario generator with drawn small sizes and seed."""
    scenario = draw(st.sampled_from(SCENARIOS))
    skills = draw(st.integers(1, 4))
    if scenario.startswith("MA"):
        species = draw(st.integers(1, min(3, 2 ** skills - 1)))
    else:  # SA: at least as many species as skills
        species = draw(st.integers(skills, 4))
    # AT needs >= 2 agents per species for requirements of 2 to be coverable quickly
    per = draw(st.integers(2 if scenario.endswith("AT") else 1, 3))
    tasks = draw(st.integers(1, 10))
    seed = draw(st.integers(0, 2**32 - 1))
    return ScenarioGenerator(scenario, species * per, species, tasks, skills).instance(seed, 0)


@st.composite
def arbitrary(draw):
    """A hand-rolled feasible instance: integer traits 0..2, amounts up to 3, grid locations,
    durations including 0, both requirement types, several velocities."""
    rt = draw(st.sampled_from(["additive", "binary"]))
    K = draw(st.integers(1, 3))
    n_species = draw(st.integers(1, 3))
    species = []
    for _ in range(n_species):
        traits = draw(st.lists(st.integers(0, 2), min_size=K, max_size=K))
        traits[0] = traits[0] or (0 if any(traits) else 1)
        species.append({"traits": traits, "count": draw(st.integers(1, 3)),
                        "depot": [draw(st.sampled_from(GRID)), draw(st.sampled_from(GRID))]})
    team = np.sum([np.array(s["traits"]) * s["count"] for s in species], axis=0)  # [K]
    tasks = []
    for _ in range(draw(st.integers(0, 8))):
        q = np.array(draw(st.lists(st.integers(0, 3), min_size=K, max_size=K)))
        q = np.minimum(q, team) if rt == "additive" else q * (team > 0)
        if not q.any():
            q[int(np.flatnonzero(team)[0])] = 1
        tasks.append({"location": [draw(st.sampled_from(GRID)), draw(st.sampled_from(GRID))],
                      "requirements": q.tolist(),
                      "duration": draw(st.sampled_from([0, 0.5, 1, 2.5, 3.7]))})
    return instance_from_dict({
        "format": "hmrta-instance/1", "requirement_type": rt,
        "velocity": draw(st.sampled_from([0.2, 0.125, 1.0])), "skills": K, "species": species, "tasks": tasks})


DECIMALS = [0.1, 0.2, 0.3, 0.7, 0.05, 1.1, 0.35]  # capabilities whose sums round (0.1 x 8 < 0.8)


@st.composite
def decimal(draw):
    """A feasible instance with decimal capabilities, whose requirements are what some robots of
    the team add up to, written to 6 decimals as a user would (0.8 for eight robots of 0.1, whose
    sum one by one is 0.7999999999999999): the coalitions that meet them exactly on paper must
    meet them in floating point too (hmrta.instance.cover_tolerance)."""
    K = draw(st.integers(1, 3))
    species = []
    for _ in range(draw(st.integers(1, 3))):
        traits = [draw(st.sampled_from([0.0, *DECIMALS])) for _ in range(K)]
        traits[0] = traits[0] or (0.0 if any(traits) else 0.1)
        species.append({"traits": traits, "count": draw(st.integers(1, 8)),
                        "depot": [draw(st.sampled_from(GRID)), draw(st.sampled_from(GRID))]})
    tasks = []
    for _ in range(draw(st.integers(1, 6))):
        q = np.zeros(K)
        for sp in species:  # some of each species' robots, added one by one
            for _ in range(draw(st.integers(0, sp["count"]))):
                q = q + np.array(sp["traits"])
        if not q.any():
            q = np.array(species[0]["traits"])
        tasks.append({"location": [draw(st.sampled_from(GRID)), draw(st.sampled_from(GRID))],
                      "requirements": [round(float(x), 6) for x in q],
                      "duration": draw(st.sampled_from([0, 0.5, 2.5]))})
    return instance_from_dict({"format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2,
                               "skills": K, "species": species, "tasks": tasks})


# greedy under its documented rules and under real-time rules (no back-dated departures);
# the random policy under several rule sets
policies = st.one_of(
    st.tuples(st.just("greedy"), st.none(),
              st.sampled_from([GREEDY_RULES, dataclasses.replace(GREEDY_RULES, backdate=False)])),
    st.tuples(st.just("random"), st.integers(0, 1000),
              st.sampled_from([Rules(), Rules(max_open=1), Rules(max_open=2, backdate=True),
                               Rules(max_open=2, backdate=False), Rules(backdate=False),
                               Rules(max_open="team")])),
)


def _policy(spec):
    name, pseed, rules = spec
    if name == "greedy":
        return Greedy(), rules
    return RandomPolicy(pseed, depot_weight=0.5), rules


def _run_and_check(inst, spec, seed, traced_run, check_rollout):
    """Roll out, check every invariant (check_rollout), and label the example for statistics."""
    pol, rules = _policy(spec)
    state, trace = traced_run(inst, pol, seed, rules)
    sol = solution_from_state(state, spec[0], seed, 0.0)
    ev = check_rollout(inst, state, trace, sol)
    event(f"{spec[0]} backdate={rules.backdate}: evaluate {'==' if ev.makespan == sol.makespan else '<'} simulate")
    event(f"tasks {'0' if inst.n_tasks == 0 else '1-4' if inst.n_tasks < 5 else '5+'}")
    event(f"depot stops: {'depot_stops' in sol.extra}")


@SETTINGS
@given(inst=generated(), spec=policies, seed=st.integers(0, 1000))
def test_generated_instances(inst, spec, seed, traced_run, check_rollout):
    _run_and_check(inst, spec, seed, traced_run, check_rollout)


@SETTINGS
@given(inst=arbitrary(), spec=policies, seed=st.integers(0, 1000))
def test_arbitrary_instances(inst, spec, seed, traced_run, check_rollout):
    _run_and_check(inst, spec, seed, traced_run, check_rollout)


@SETTINGS
@given(inst=decimal(), spec=policies, seed=st.integers(0, 1000))
def test_decimal_capabilities_meet_the_requirements_they_add_up_to(inst, spec, seed, traced_run, check_rollout):
    _run_and_check(inst, spec, seed, traced_run, check_rollout)


@settings(max_examples=40, derandomize=True, deadline=None, database=None)
@given(inst=arbitrary(), pseed=st.integers(0, 1000), seed=st.integers(0, 1000), cut=st.floats(0, 1))
def test_snapshot_anywhere_continues_identically(inst, pseed, seed, cut):
    rules = Rules(max_open=2)
    state = MissionState(inst, seed, rules)
    pol = RandomPolicy(pseed)
    steps = 0
    while not state.done and steps < 40 * cut:
        state.step(pol(state))
        steps += 1
    restored = MissionState.from_snapshot(inst, json.loads(json.dumps(state.snapshot())))
    pol2 = RandomPolicy(pseed)
    pol2.rng.setstate(pol.rng.getstate())
    for s, p in ((state, pol), (restored, pol2)):
        while not s.done:
            s.step(p(s))
    a, b = solution_from_state(state, "r", seed, 0).to_dict(), solution_from_state(restored, "r", seed, 0).to_dict()
    a.pop("moves")  # (the movement history, a drawing aid, is not in snapshots)
    assert json.dumps(a) == json.dumps(b)


# ---- random event streams (docs/semantics.md, "Events during a mission") ----------------------
@st.composite
def event_streams(draw):
    """(decision index, kind, draw of the event's details) for up to 6 events."""
    kinds = st.sampled_from(["add_task", "cancel_task", "add_agent", "drop_agent", "timed_add"])
    return draw(st.lists(st.tuples(st.integers(0, 30), kinds, st.integers(0, 2**16),
                                   st.sampled_from(GRID), st.sampled_from(GRID)), max_size=6))


def _apply_random_event(state, kind, r, x, y):
    """Apply one random event; rejected events (EventRejected) are part of what is tested."""
    from hmrta.core import EventRejected, LOST
    from hmrta.instance import Task

    K = state.K
    try:
        if kind in ("add_task", "timed_add"):
            q = [float((r >> (2 * k)) % 3) for k in range(K)]
            q[r % K] = q[r % K] or 1.0
            task = Task((x, y), tuple(q), float(r % 4) / 2)
            state.add_task(task, state.clock + (r % 7 if kind == "timed_add" else 0.0))
        elif kind == "cancel_task":
            state.cancel_task(r % state.M if state.M else 0)
        elif kind == "add_agent":
            if r % 3 == 0:
                state.add_agent(traits=[float((r >> k) % 2 + (k == 0)) for k in range(K)], position=(x, y))
            else:
                state.add_agent(species=r % state.inst.n_species)
        else:
            alive = [a for a in range(state.A) if state.mode[a] != LOST]
            if len(alive) > 1:
                state.drop_agent(alive[r % len(alive)])
    except EventRejected:
        return False
    return True


@settings(max_examples=120, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(inst=arbitrary(), spec=policies, seed=st.integers(0, 1000), stream=event_streams())
def test_random_event_streams(inst, spec, seed, stream):
    """Adds, cancellations, robot additions and losses at random decision points: the mission
    always ends (never a deadlock), succeeds unless a task became unsatisfiable, every done task
    was satisfied by its coalition after everyone arrived, and the state snapshot round trip after
    the events is bit-exact and continues identically."""
    from hmrta.core import CANCELLED, DONE, LOST

    pol, rules = _policy(spec)
    state = MissionState(inst, seed, rules)
    stream = sorted(stream)
    k = 0
    restored = None
    while not state.done:
        while stream and stream[0][0] <= k and not state.done:
            _, kind, r, x, y = stream.pop(0)
            _apply_random_event(state, kind, r, x, y)
        if state.done:
            break
        if restored is None and k >= 3:  # snapshot once, after some events
            d = json.loads(json.dumps(state.snapshot()))
            restored = MissionState.from_snapshot(inst, d)
            assert json.dumps(restored.snapshot()) == json.dumps(d)
            twin = _policy(spec)[0]
            if hasattr(pol, "rng"):
                twin.rng.setstate(pol.rng.getstate())
            saved_stream = list(stream)
            restored_k = k
        state.step(pol(state))
        k += 1
    assert state.done
    assert state.failure is None or "cancelled" in state.failure, state.failure
    unsat = (state.status == CANCELLED) & ~state.by_operator
    assert state.success == (not unsat.any())
    assert ((state.status == DONE) | (state.status == CANCELLED)).all()
    assert not state.pending and state.n_hidden == 0
    for m in np.flatnonzero(state.status == DONE):
        mem = state.members[m]
        assert mem and all(state.mode[a] != LOST or True for a in mem)
        c = state.cap[mem].sum(0)
        assert (c >= state.req[m] - 1e-9).all()
    for a in range(state.A):
        if state.mode[a] != LOST:
            assert np.allclose(state.to_pos[a], state.inst.depots[a]), (a, state.to_pos[a])
    if restored is not None:  # the restored twin, fed the same events, ends identically
        k = restored_k
        stream = saved_stream
        while not restored.done:
            while stream and stream[0][0] <= k and not restored.done:
                _, kind, r, x, y = stream.pop(0)
                _apply_random_event(restored, kind, r, x, y)
            if restored.done:
                break
            restored.step(twin(restored))
            k += 1
        assert json.dumps(restored.snapshot()) == json.dumps(state.snapshot())
