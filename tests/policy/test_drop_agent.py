"""MissionState.drop_agent (robot loss, used by the ROS task board): no ROS graph needed."""
from __future__ import annotations

import json
import random

import numpy as np
import pytest

from hmrta.baselines import GREEDY_RULES, Greedy, RandomPolicy
from hmrta.core import CANCELLED, DONE, LOST, MissionState, Rules
from hmrta.generators import ScenarioGenerator
from hmrta.solution import satisfies, solution_from_state


def _rollout_with_losses(inst, policy, rules, seed, drops):
    """Roll out, dropping agent a just before decision number k for each (k, a) in drops."""
    state = MissionState(inst, seed=seed, rules=rules)
    drops = sorted(drops)
    cancelled: list[int] = []
    dropped: list[int] = []
    k = 0
    while not state.done:
        while drops and drops[0][0] <= k and not state.done:
            a = drops.pop(0)[1]
            cancelled += state.drop_agent(a)
            dropped.append(a)
        if not state.done:
            state.step(policy(state))
            k += 1
    return state, dropped, cancelled


def _check(inst, state, lost, cancelled):
    assert state.done
    assert state.failure is None or "cancelled" in state.failure, state.failure
    assert state.success == (not cancelled)
    team = inst.traits[[a for a in range(inst.n_agents) if a not in lost]].sum(0)
    for m in range(inst.n_tasks):
        if m in cancelled:
            assert state.status[m] == CANCELLED
            assert satisfies(inst, list(range(inst.n_agents)), m) == []  # it was satisfiable before
            lacks = [k for k in range(inst.skills)
                     if (inst.requirements[m, k] > team[k] if inst.additive else inst.requirements[m, k] > 0 >= team[k])]
            assert lacks  # ... and is not any more
        else:
            assert state.status[m] == DONE
            assert satisfies(inst, state.members[m], m) == []
            assert state.finish[m] == state.start[m] + inst.durations[m]
    for a in lost:
        assert state.mode[a] == LOST
    for a in range(inst.n_agents):
        for m in state.routes[a]:
            assert a in state.members[m]
    # the state still survives a JSON snapshot round trip
    snap = json.loads(json.dumps(state.snapshot()))
    assert json.dumps(MissionState.from_snapshot(inst, snap).snapshot()) == json.dumps(snap)


@pytest.mark.parametrize("scenario,row", [("MA-AT", (9, 3, 20, 3)), ("SA-BT", (9, 3, 20, 3)),
                                          ("SA-AT", (15, 5, 20, 5)), ("MA-AT", (25, 5, 50, 5))])
def test_random_losses_never_deadlock(scenario, row):
    gen = ScenarioGenerator(scenario, *row)
    rng = random.Random(7)
    for i in range(12):
        inst = gen.instance(3, i)
        lost = rng.sample(range(inst.n_agents), rng.choice([1, 1, 2, 3]))
        drops = [(rng.randrange(0, 2 * inst.n_tasks), a) for a in lost]
        for policy, rules in ((Greedy(), GREEDY_RULES), (RandomPolicy(i), Rules())):
            state, lost, cancelled = _rollout_with_losses(inst, policy, rules, i, drops)
            _check(inst, state, lost, cancelled)
            sol = solution_from_state(state, "x", i, 0.0)
            assert sol.success == (not cancelled)


def test_drop_releases_open_task_and_cancels_unsatisfiable():
    from hmrta.instance import instance_from_dict

    inst = instance_from_dict({
        "format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2, "skills": 2,
        "species": [{"traits": [1, 0], "count": 2, "depot": [0.0, 0.0]},
                    {"traits": [0, 1], "count": 1, "depot": [1.0, 1.0]}],
        "tasks": [{"location": [0.5, 0.0], "requirements": [1, 1], "duration": 1.0},
                  {"location": [0.0, 0.5], "requirements": [2, 0], "duration": 1.0}],
    })
    state = MissionState(inst, seed=0, rules=Rules())
    # the first decider commits to task 0 (opens it); then drop the only skill-1 robot
    a = state.agent
    state.step(1 if state.mask()[1] else 2)
    before = [list(r) for r in state.routes]
    cancelled = state.drop_agent(2)
    assert state.mode[2] == LOST
    if inst.traits[a][0] > 0 and before[a] == [0]:
        assert 0 in cancelled and state.routes[a] == []
    while not state.done:
        state.step(Greedy()(state))
    assert cancelled == [0]
    assert state.status[1] == DONE and not state.success
    assert "cancelled" in state.failure


def test_drop_current_decider_and_no_cancel_keeps_success():
    inst = ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(1, 0)
    state = MissionState(inst, seed=1, rules=GREEDY_RULES)
    for _ in range(5):
        state.step(Greedy()(state))
    d = state.agent
    assert d is not None
    state.drop_agent(d)
    assert state.agent != d and state.mode[d] == LOST
    assert state.drop_agent(d) == []  # idempotent
    while not state.done:
        state.step(Greedy()(state))
    assert state.success
    assert all(d not in state.members[m] for m in range(inst.n_tasks) if m not in state.routes[d])
    assert np.isfinite(state.arrive).all()


def test_the_loss_record_says_where_the_robot_stopped():
    """A robot lost part-way along a leg stops where it is then: the log's drop_agent record carries
    that point (``at``), the position the state machine holds for it from then on."""
    inst = ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(1, 0)
    state = MissionState(inst, seed=1, rules=GREEDY_RULES)
    moving: list[int] = []
    while not moving:  # the first decision with a robot on its way somewhere
        state.step(Greedy()(state))
        moving = [a for a in range(inst.n_agents) if state.depart[a] < state.clock < state.arrive[a]]
    a = moving[0]
    here = state.position(a)
    assert not np.allclose(here, state.to_pos[a]) and not np.allclose(here, state.from_pos[a])
    state.drop_agent(a)
    rec = state.log[-1]
    assert rec["type"] == "drop_agent" and rec["agent"] == a and rec["at"] == [float(x) for x in here]
    assert rec["since"] == state.clock  # on its way: there only from the loss
    assert np.array_equal(state.position(a), here)
    json.dumps(rec)  # JSON-able like every record
    # a robot that arrived earlier (waiting at its task, or back at its depot): there since its arrival
    while True:
        arrived = [b for b in range(inst.n_agents) if state.mode[b] != LOST and state.arrive[b] < state.clock
                   and state.depart[b] < state.arrive[b]]
        if arrived:
            break
        state.step(Greedy()(state))
    b = arrived[0]
    there, since = state.to_pos[b].copy(), float(state.arrive[b])
    state.drop_agent(b)
    assert (state.log[-1]["at"], state.log[-1]["since"]) == ([float(x) for x in there], since)


@pytest.mark.parametrize("method", ["greedy", "greedy-coalition", "random"])
def test_a_robot_lost_at_time_0_never_decides(method):
    """A scenario losing a robot at t = 0: the robot is gone before the first decision (it was
    queued with the others and took decisions and work), as a loss an instant later would be."""
    from hmrta.methods import solve
    from hmrta.scenario import scenario_from_dict

    inst = ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(1, 0)
    for t in (0.0, 1e-6):
        scen = scenario_from_dict({"format": "hmrta-scenario/1", "instance": inst.to_dict(),
                                   "events": [{"t": t, "type": "lose_robot", "robot": 3}]}, "s.yaml")
        sol = solve(scen, method, seed=0)
        assert sol.routes[3] == [] and all(3 not in tk["members"] for tk in sol.tasks), (t, sol.routes[3])


def test_a_task_released_when_nobody_can_do_it_is_cancelled_and_logged():
    """The robots with skill 1 are lost before a task needing it is released: at its release the
    task is cancelled as unsatisfiable, and the log says so (a release record with the task
    ``cancelled``), so that a solution tells it; the render draws it as cancelled."""
    import json

    from hmrta.instance import instance_from_dict
    from hmrta.methods import solve
    from hmrta.render import mission_changes
    from hmrta.scenario import scenario_from_dict
    from hmrta.solution import Solution

    mission = {"format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2, "skills": 2,
               "species": [{"traits": [1, 0], "count": 2, "depot": [0.0, 0.0]},
                           {"traits": [0, 1], "count": 2, "depot": [1.0, 1.0]}],
               "tasks": [{"location": [0.5, 0.1], "requirements": [1, 0], "duration": 20},
                         {"location": [0.2, 0.8], "requirements": [0, 1], "duration": 1, "release": 5.0}]}
    scen = scenario_from_dict({"format": "hmrta-scenario/1", "instance": mission,
                               "events": [{"t": 1.0, "type": "lose_robot", "robot": 2},
                                          {"t": 2.0, "type": "lose_robot", "robot": 3}]}, "s.yaml")
    sol = Solution.from_dict(json.loads(json.dumps(solve(scen, "greedy", seed=0).to_dict())))
    assert not sol.success and sol.extra["dynamic"]["tasks_lost"]["unsatisfiable"] == 1
    rel = [e for e in sol.extra["dynamic"]["events"] if e["type"] == "release"]
    assert rel == [{"t": 5.0, "type": "release", "task": 1, "cancelled": [1]}]
    assert mission_changes(instance_from_dict(mission), sol).cancelled == {1: (5.0, False)}
