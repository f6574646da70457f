"""Mission events in the core state machine (add_task, cancel_task, add_agent, drop_agent, timed
external events): hand-built cases for each rule of docs/semantics.md, "Events during a mission"."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.core import (CANCELLED, DONE, EMPTY, FREE, HOME, IN_PROGRESS, OPEN, UNRELEASED, EventRejected,
                        MissionState, Rules, apply_event, team_cap)
from hmrta.instance import Task, instance_from_dict
from hmrta.solution import solution_from_state

NO_SAFETY = Rules(safety=False)


def _inst(tasks, species=None, rt="additive", skills=2):
    species = species or [{"traits": [1, 0], "count": 2, "depot": [0.0, 0.0]},
                          {"traits": [0, 1], "count": 1, "depot": [1.0, 1.0]}]
    return instance_from_dict({"format": "hmrta-instance/1", "requirement_type": rt, "velocity": 0.2,
                               "skills": skills, "species": species, "tasks": tasks})


def _t(x, y, req, dur=1.0, **kw):
    return {"location": [x, y], "requirements": req, "duration": dur, **kw}


def _run(state, policy=None):
    policy = policy or Greedy()
    while not state.done:
        state.step(policy(state))
    return state


def test_add_task_is_empty_offered_at_once_and_completed():
    inst = _inst([_t(0.5, 0.0, [1, 0])])
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    assert s.agent is not None and len(s.mask()) == 2
    m = s.add_task(Task((0.0, 0.5), (0.0, 1.0), 2.0), name="inspect-7")
    assert m == 1 and s.M == 2 and s.status[1] == EMPTY and s.release[1] == s.clock == 0.0
    assert s.inst.n_tasks == 2 and s.names == [None, "inspect-7"]
    assert len(s.mask()) == 3  # the pending decision sees the new task
    _run(s)
    assert s.success and (s.status == DONE).all()
    assert s.log[0]["type"] == "add_task" and s.log[0]["id"] == 1


def test_add_task_infeasible_is_rejected_and_state_unchanged():
    inst = _inst([_t(0.5, 0.0, [1, 0])])
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    s.drop_agent(2)  # the only robot with skill 1
    before = json.dumps(s.snapshot())
    with pytest.raises(EventRejected, match="no robot left with skill 1"):
        s.add_task(Task((0.0, 0.5), (0.0, 1.0), 2.0), name="inspect-7")
    with pytest.raises(EventRejected, match="needs 3 of skill 0, the remaining team has 2"):
        s.add_task(Task((0.0, 0.5), (3.0, 0.0), 2.0))
    with pytest.raises(EventRejected, match="location"):
        s.add_task(Task((2.0, 0.5), (1.0, 0.0), 2.0))
    with pytest.raises(EventRejected, match="before the mission clock"):
        s.add_task(Task((0.0, 0.5), (1.0, 0.0), 2.0), now=-1.0)
    assert json.dumps(s.snapshot()) == before


def test_cancel_open_task_frees_en_route_robot_where_it_is():
    # one robot of skill 0 commits to a task needing 2: the task is open; it is cancelled mid-way
    inst = _inst([_t(1.0, 0.0, [2, 0], 1.0), _t(0.0, 1.0, [0, 1], 30.0)])
    s = MissionState(inst, seed=0, rules=NO_SAFETY)
    # step until a robot of species 0 committed to task 0 and the clock moved past 0
    while s.status[0] != OPEN:
        a = s.agent
        s.step(1 if s.mask()[1] and a < 2 else (2 if s.mask()[2] else 0))
    a = s.members[0][0]
    t = 2.0  # half-way from (0, 0) to (1, 0) at speed 0.2 takes 2.5 time units
    s.schedule({"type": "cancel_task", "t": t, "task": 0})
    while s.clock < t and not s.done:
        s.step(int(np.flatnonzero(s.mask())[0]))
    assert s.status[0] == CANCELLED and s.by_operator[0]
    rec = s.log[0]
    assert rec["type"] == "cancel_task" and a in rec["freed"]
    # the freed robot re-planned from where it was at t = 2: 0.4 along the leg
    assert s.from_pos[a, 0] == pytest.approx(0.4) and s.depart[a] >= t - 1e-12
    _run(s)
    assert s.success and s.status[1] == DONE
    sol = solution_from_state(s, "greedy", 0, 0.0)
    assert sol.extra["dynamic"]["tasks_lost"] == {"cancelled": 1, "unsatisfiable": 0, "rejected": 0}


def test_cancel_in_progress_task_stops_its_coalition():
    inst = _inst([_t(0.5, 0.0, [1, 0], 50.0)], species=[{"traits": [1, 0], "count": 1, "depot": [0.0, 0.0]}])
    s = _run(MissionState(inst, seed=0, rules=GREEDY_RULES))
    assert s.finish[0] == pytest.approx(52.5)  # starts at 2.5 without the cancellation
    s2 = MissionState(inst, seed=0, rules=GREEDY_RULES)
    s2.schedule({"type": "cancel_task", "t": 10.0, "task": 0})
    s2.step(1)
    assert s2.done and s2.success
    assert s2.status[0] == CANCELLED and np.isnan(s2.finish[0])
    # stopped at the task at t = 10 and went home: back at 10 + 2.5
    assert s2.makespan == pytest.approx(12.5)
    assert s2.wait_total[0] == 0.0 and s2.routes[0] == []


def test_cancel_rejects_unknown_done_and_cancelled():
    inst = _inst([_t(0.5, 0.0, [1, 0]), _t(0.5, 0.5, [1, 0])])
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    with pytest.raises(EventRejected, match="no such task"):
        s.cancel_task(7)
    with pytest.raises(EventRejected, match="'x': no such task"):
        s.cancel_task("x")
    s.cancel_task(1)
    with pytest.raises(EventRejected, match="already cancelled"):
        s.cancel_task(1)
    _run(s)
    assert s.success and s.status[0] == DONE
    s2 = MissionState(inst, seed=0, rules=GREEDY_RULES)
    _run(s2)
    with pytest.raises(EventRejected, match="mission is over"):
        s2.cancel_task(0)


def test_add_agent_free_at_position_and_deciding():
    inst = _inst([_t(0.9, 0.9, [0, 1], 1.0)])
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    a = s.add_agent(species=1, position=(0.9, 0.8))
    assert a == 3 and s.A == 4 and s.inst.n_agents == 4 and s.mode[a] == FREE
    assert tuple(s.position(a)) == (0.9, 0.8) and tuple(s.inst.depots[a]) == (1.0, 1.0)
    b = s.add_agent(traits=[0.0, 3.0], position=(0.2, 0.2))
    assert b == 4 and tuple(s.inst.depots[b]) == (0.2, 0.2) and s.inst.n_species == 3
    assert s.pool[1] == 1 + 1 + 3
    # team cap fixed at mission start
    assert s.open_cap == GREEDY_RULES.open_cap(inst)
    with pytest.raises(EventRejected, match="exactly one of species and traits"):
        s.add_agent()
    with pytest.raises(EventRejected, match="needs a position"):
        s.add_agent(traits=[1, 1])
    with pytest.raises(EventRejected, match="no such species"):
        s.add_agent(species=9)
    _run(s)
    assert s.success
    assert s.arrive[b] >= 0 and tuple(s.to_pos[b]) == (0.2, 0.2)  # ends at its own depot


def test_added_robot_makes_task_feasible_again_for_additions():
    inst = _inst([_t(0.5, 0.0, [1, 0])])
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    s.drop_agent(2)
    with pytest.raises(EventRejected):
        s.add_task(Task((0.0, 0.5), (0.0, 1.0), 2.0))
    s.add_agent(species=1)
    assert s.add_task(Task((0.0, 0.5), (0.0, 1.0), 2.0)) == 1
    _run(s)
    assert s.success


def test_team_cap_counts_only_tasks_known_at_start():
    tasks = [_t(0.1 * i, 0.5, [2, 1]) for i in range(6)]
    inst = _inst(tasks)
    late = _inst(tasks + [_t(0.5, 0.5, [2, 1], release=5.0)] * 4)
    assert team_cap(inst) == team_cap(late)


def test_release_and_add_are_the_same_mission():
    base = [_t(0.2, 0.3, [1, 0], 2.0), _t(0.8, 0.1, [1, 1], 1.0), _t(0.4, 0.9, [0, 1], 3.0)]
    late = _t(0.6, 0.6, [2, 1], 1.5)
    released = MissionState(_inst(base + [{**late, "release": 4.0}]), seed=3, rules=GREEDY_RULES)
    assert released.status[3] == UNRELEASED and not released.mask()[4] and released.n_hidden == 1
    added = MissionState(_inst(base), seed=3, rules=GREEDY_RULES)
    added.schedule({"type": "add_task", "t": 4.0, "task": {k: late[k] for k in ("location", "requirements", "duration")}})
    _run(released)
    _run(added)
    assert released.success and added.success
    assert released.routes == added.routes and released.makespan == added.makespan
    assert np.array_equal(released.finish, added.finish) and np.array_equal(released.release, added.release)


def test_events_after_everything_done_keep_the_mission_going():
    inst = _inst([_t(0.5, 0.0, [1, 0], 1.0)])
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    s.schedule({"type": "add_task", "t": 100.0, "task": _t(0.0, 0.5, [0, 1], 1.0), "name": "late"})
    _run(s)
    assert s.success and s.status[1] == DONE and s.start[1] >= 100.0
    sol = solution_from_state(s, "greedy", 0, 0.0)
    dyn = sol.extra["dynamic"]
    assert dyn["release"] == [0.0, 100.0]
    assert dyn["response"][1] == pytest.approx(s.finish[1] - 100.0)
    assert dyn["max_response"] == max(dyn["response"])


@pytest.mark.parametrize("seed", range(12))
def test_a_task_added_after_the_mission_ended_reopens_it_as_if_it_had_been_known(seed):
    """Every task done, the robots on their way home (or home): a task added then (a live
    operator's) reopens the mission, which then runs exactly as the same mission with the task
    scheduled from the start (which stays open for it): same routes, finish times, makespan and
    log, for greedy and greedy-coalition, added while robots drive home or once they are home."""
    from hmrta.baselines import COALITION_RULES, CoalitionGreedy
    from hmrta.generators import ScenarioGenerator

    rng = np.random.default_rng(seed)
    inst = ScenarioGenerator(["SA-AT", "MA-AT", "MA-BT"][seed % 3], 6, 3, 5, 2).instance(seed, 0)
    policy, rules = (Greedy(), GREEDY_RULES) if seed % 2 else (CoalitionGreedy(), COALITION_RULES)
    ended = _run(MissionState(inst, seed=seed, rules=rules), policy)
    assert ended.success
    home = float(ended.arrive.max())
    t = float(ended.clock + rng.random() * (home - ended.clock + 2.0))  # driving home, or home
    if seed % 4 == 0:  # the instant the mission ended: the task comes one ulp later
        t = float(np.nextafter(ended.clock, np.inf))
    task = {"location": rng.random(2).round(3).tolist(), "requirements": list(inst.tasks[0].requirements),
            "duration": 1.5}
    known = MissionState(inst, seed=seed, rules=rules)
    known.schedule({"type": "add_task", "t": t, "task": task, "name": "late"})
    _run(known, policy)
    m = ended.add_task(Task(tuple(task["location"]), tuple(task["requirements"]), task["duration"]), t, "late")
    assert m == inst.n_tasks and not ended.done and ended.clock == t and ended.release[m] == t
    _run(ended, policy)
    assert ended.success and known.success and ended.status[m] == DONE
    assert ended.routes == known.routes and ended.makespan == known.makespan
    assert np.array_equal(ended.finish, known.finish) and np.array_equal(ended.arrive, known.arrive)
    assert ended.log == known.log and ended.moves == known.moves


def test_a_task_added_after_the_end_brings_back_the_robots_events_dropped_at_the_end():
    """Robot events scheduled after a mission's end are dropped (logged as rejected); a task added
    later reopens the mission, and those before it apply at their own times again, as in the
    mission that knew the task would come; a task added at the instant the mission ended (the
    default time) comes one ulp later, as that mission would have it."""
    inst = _inst([_t(0.5, 0.0, [1, 0], 1.0)])
    late = [{"type": "drop_agent", "t": 50.0, "agent": 2},
            {"type": "add_agent", "t": 55.0, "species": 1}]
    task = {"location": [0.6, 0.0], "requirements": [0.0, 1.0], "duration": 1.0}
    ended = MissionState(inst, seed=0, rules=GREEDY_RULES)
    known = MissionState(inst, seed=0, rules=GREEDY_RULES)
    for rec in late:
        ended.schedule(dict(rec))
        known.schedule(dict(rec))
    known.schedule({"type": "add_task", "t": 60.0, "task": task})
    _run(ended)
    assert ended.success and [e["type"] for e in ended.log if "rejected" in e] == ["drop_agent", "add_agent"]
    ended.add_task(Task(tuple(task["location"]), tuple(task["requirements"]), task["duration"]), 60.0)
    _run(ended)
    _run(known)
    assert ended.success and known.success and ended.A == known.A == 4
    assert ended.routes == known.routes and ended.makespan == known.makespan and ended.log == known.log
    assert json.dumps(ended.snapshot()) == json.dumps(known.snapshot())

    now = _run(MissionState(inst, seed=1, rules=GREEDY_RULES))
    end = now.clock
    m = now.add_task(Task((0.5, 0.5), (1.0, 0.0), 1.0))  # default: the mission clock
    assert now.release[m] == np.nextafter(end, np.inf)
    ref = MissionState(inst, seed=1, rules=GREEDY_RULES)
    ref.schedule({"type": "add_task", "t": float(np.nextafter(end, np.inf)),
                  "task": {"location": [0.5, 0.5], "requirements": [1.0, 0.0], "duration": 1.0}})
    assert _run(now).routes == _run(ref).routes and now.makespan == ref.makespan


def test_a_task_refused_after_the_mission_ended_leaves_it_ended():
    inst = _inst([_t(0.5, 0.0, [1, 0], 1.0)])
    s = _run(MissionState(inst, seed=0, rules=GREEDY_RULES))
    before = json.dumps(s.snapshot())
    with pytest.raises(EventRejected, match="needs 5 of skill 0"):
        s.add_task(Task((0.0, 0.5), (5.0, 0.0), 1.0), s.clock + 1.0)
    with pytest.raises(EventRejected, match="before the mission clock"):
        s.add_task(Task((0.0, 0.5), (1.0, 0.0), 1.0), s.clock - 1.0)
    capped = _run(MissionState(inst, seed=0, rules=dataclasses.replace(GREEDY_RULES, t_max=50.0)))
    with pytest.raises(EventRejected, match="after the mission's time limit 50"):
        capped.add_task(Task((0.0, 0.5), (1.0, 0.0), 1.0), 60.0)
    assert capped.done and capped.success
    with pytest.raises(ValueError):  # not a task at all: an error, the mission still as it was
        s.add_task(Task((0.0, 0.5), (1.0, "x"), 1.0), s.clock + 2.0)
    assert s.done and s.success and json.dumps(s.snapshot()) == before
    failed = _run(MissionState(inst, seed=0, rules=GREEDY_RULES))
    failed.done, failed.success, failed.failure = True, False, "deadlock"
    with pytest.raises(EventRejected, match="the mission is over"):
        failed.add_task(Task((0.0, 0.5), (1.0, 0.0), 1.0))


def test_scheduled_rejections_are_logged_not_raised():
    inst = _inst([_t(0.5, 0.0, [1, 0], 1.0)])
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    s.schedule({"type": "drop_agent", "t": 0.5, "agent": 2})
    s.schedule({"type": "add_task", "t": 1.0, "task": _t(0.0, 0.5, [0, 1]), "name": "x"})
    s.schedule({"type": "cancel_task", "t": 2.0, "name": "x"})
    _run(s)
    assert s.success and s.M == 1
    assert [e["type"] for e in s.log] == ["drop_agent", "add_task", "cancel_task"]
    assert "no robot left with skill 1" in s.log[1]["rejected"] and "no such task" in s.log[2]["rejected"]
    dyn = solution_from_state(s, "g", 0, 0.0).extra["dynamic"]
    assert dyn["tasks_lost"]["rejected"] == 1


def test_deadlock_mask_covers_added_tasks():
    # two robots of skill 0; an added task needing both: the safety mask must not let one robot
    # open it while the other is committed to a task needing two
    species = [{"traits": [1, 0], "count": 2, "depot": [0.0, 0.0]}]
    inst = _inst([_t(0.5, 0.5, [2, 0], 1.0)], species=species)
    s = MissionState(inst, seed=0, rules=Rules(max_open=None, safety=True))
    s.add_task(Task((0.9, 0.9), (2.0, 0.0), 1.0))
    a = s.agent
    s.step(1)  # opens task 0
    assert not s.mask()[2]  # opening task 1 as well would deadlock
    _run(s)
    assert s.success


def test_snapshot_round_trip_after_events_is_exact():
    inst = _inst([_t(0.5, 0.0, [1, 0], 1.0), _t(0.2, 0.7, [1, 1], 2.0, release=3.0)])
    s = MissionState(inst, seed=5, rules=GREEDY_RULES)
    s.add_task(Task((0.3, 0.3), (1.0, 1.0), 2.0), name="a")
    s.add_agent(traits=[2.0, 2.0], position=(0.5, 0.5))
    s.schedule({"type": "cancel_task", "t": 4.0, "name": "a"})
    s.schedule({"type": "add_agent", "t": 6.0, "species": 0})
    pol = Greedy()
    while not s.done:
        d = json.loads(json.dumps(s.snapshot()))
        r = MissionState.from_snapshot(inst, d)
        assert json.dumps(r.snapshot()) == json.dumps(d)
        node = pol(s)
        s.step(node)
        r.step(node)
        assert json.dumps(r.snapshot()) == json.dumps(s.snapshot())
    assert s.success


def test_apply_event_replays_a_journal():
    inst = _inst([_t(0.5, 0.0, [1, 0], 1.0), _t(0.2, 0.7, [1, 1], 2.0)])
    s = MissionState(inst, seed=1, rules=GREEDY_RULES)
    journal = []
    pol = Greedy()
    k = 0
    while not s.done:
        if k == 1:
            s.add_task(Task((0.3, 0.3), (1.0, 0.0), 2.0), name="a")
            journal.append(s.log[-1])
            s.add_agent(species=1)
            journal.append(s.log[-1])
        if k == 2:
            s.cancel_task("a")
            journal.append(s.log[-1])
        if k == 3:
            s.drop_agent(0)
            journal.append(s.log[-1])
        if s.done:
            break
        a, node = s.agent, pol(s)
        journal.append({"type": "choice", "agent": a, "node": node})
        s.step(node)
        k += 1
    r = MissionState(inst, seed=1, rules=GREEDY_RULES)
    for rec in json.loads(json.dumps(journal)):
        apply_event(r, rec)
    assert json.dumps(r.snapshot()) == json.dumps(s.snapshot())
    with pytest.raises(EventRejected, match="unknown type"):
        apply_event(r, {"type": "explode", "t": 0})


def _one_skill(tasks, count=2):
    return _inst(tasks, species=[{"traits": [1], "count": count, "depot": [0.0, 0.0]}], skills=1)


def _decided_after(state, policy, t_lost, robot):
    """Run the mission; the decisions robot ``robot`` is handed at or after ``t_lost``."""
    seen = []
    while not state.done:
        if state.agent == robot and state.clock >= t_lost - 1e-12:
            seen.append(state.clock)
        state.step(policy(state))
    return seen


@pytest.mark.parametrize("case", ["completion", "cancellation", "join"])
def test_a_robot_lost_when_an_event_of_the_same_instant_frees_it_never_decides_again(case):
    """A loss at the instant another event frees the robot (its task completes, its task is
    cancelled, it has just joined): the robot stays lost. It is never offered a decision, never
    joins a task, and never drives home."""
    tasks = [_t(0.2, 0.0, [1], 2.0), _t(0.0, 0.4, [2], 2.0), _t(0.6, 0.0, [1], 1.0)]
    s = MissionState(_one_skill(tasks), seed=0, rules=GREEDY_RULES)
    robot, t = 0, 3.0  # robot 0 reaches task 0 at 1.0 and finishes it at 3.0 (greedy, seed 0)
    if case == "cancellation":
        s.schedule({"type": "cancel_task", "t": t, "task": 0})
    if case == "join":
        s.schedule({"type": "add_agent", "t": t, "species": 0})
        robot = 2
    s.schedule({"type": "drop_agent", "t": t, "agent": robot})
    assert _decided_after(s, Greedy(), t, robot) == []
    assert s.mode[robot] == 4 and s.arrive[robot] <= t + 1e-9  # LOST, stopped at its loss
    assert all(not (robot in s.members[m] and s.start[m] >= t) for m in range(s.M))
    sol = solution_from_state(s, "greedy", 0, 0.0)
    assert all(robot not in task["members"] or task["finish"] <= t + 1e-9 for task in sol.tasks if task["members"])


def test_robot_events_after_the_mission_ended_do_not_push_its_end():
    """Every task done and every robot home: a robot joining or lost later changes nothing, and
    the makespan stays the mission's; the events are logged as rejected. Before the end they
    apply (a loss on the way home stops the robot there); a task added later is still done."""
    tasks = [_t(0.5, 0.0, [1, 0]), _t(0.0, 0.5, [0, 1])]
    plain = _run(MissionState(_inst(tasks), seed=0, rules=GREEDY_RULES))
    end = plain.makespan
    s = MissionState(_inst(tasks), seed=0, rules=GREEDY_RULES)
    s.schedule({"type": "add_agent", "t": 1000.0, "species": 0})
    s.schedule({"type": "drop_agent", "t": 500.0, "agent": 0})
    _run(s)
    assert s.success and s.makespan == end and s.A == 3 and s.mode[0] != 4
    assert [(r["type"], r["t"]) for r in s.log] == [("drop_agent", 500.0), ("add_agent", 1000.0)]
    assert all("after the mission's end" in r["rejected"] for r in s.log)
    # a loss before the end applies; a task added after it still extends the mission
    s = MissionState(_inst(tasks), seed=0, rules=GREEDY_RULES)
    s.schedule({"type": "add_task", "t": 100.0, "task": _t(0.5, 0.5, [1, 0])})
    s.schedule({"type": "drop_agent", "t": 50.0, "agent": 0})
    _run(s)
    assert s.success and s.mode[0] == 4 and s.makespan > 100.0 and s.M == 3
