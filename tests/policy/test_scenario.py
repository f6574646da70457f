"""Dynamic scenarios (`hmrta-scenario/1`): loading, one-line errors, every method running them,
dynamic metrics, and the learned policy seeing a released task exactly like an added one."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hmrta import methods
from hmrta.core import MissionState
from hmrta.formats import load_instance
from hmrta.generators import ScenarioGenerator
from hmrta.instance import InstanceError
from hmrta.scenario import ScenarioError, scenario_from_dict

MISSION = (Path(__file__).parent / "data" / "two_species.yaml").read_text()  # shared with test_bench
EVENTS = """  - {t: 3.0, type: add_task, id: inspect-7, location: [0.3, 0.6], requirements: [1, 1], duration: 2}
  - {t: 4.0, type: add_task, id: extra, location: [0.6, 0.6], requirements: [2, 0], duration: 1}
  - {t: 5.0, type: cancel_task, id: extra}
  - {t: 6.0, type: add_robot, species: 1}
  - {t: 7.0, type: add_robot, traits: [1, 1], position: [0.5, 0.5]}
  - {t: 8.0, type: lose_robot, robot: 0}
"""


@pytest.fixture
def scenario(tmp_path):
    (tmp_path / "mission.yaml").write_text(MISSION)
    p = tmp_path / "scen.yaml"
    p.write_text("format: hmrta-scenario/1\nname: demo\ninstance: mission.yaml\nevents:\n" + EVENTS)
    return p


def test_load_scenario_events_in_time_order(scenario):
    inst = load_instance(scenario)
    assert inst.name == "demo" and inst.dynamic and inst.n_tasks == 3
    assert [e["type"] for e in inst.events] == ["add_task", "add_task", "cancel_task", "add_agent", "add_agent",
                                                "drop_agent"]
    assert inst.events[2] == {"t": 5.0, "type": "cancel_task", "name": "extra"}


@pytest.mark.parametrize("method", ["greedy", "greedy-coalition", "rl", "rl-s3"])
def test_every_method_runs_a_scenario(scenario, method):
    sol = methods.solve(load_instance(scenario), method, seed=0)
    assert sol.success and len(sol.routes) == 6 and len(sol.tasks) == 5
    dyn = sol.extra["dynamic"]
    assert dyn["release"] == [0.0, 0.0, 0.0, 3.0, 4.0]
    assert dyn["tasks_lost"] == {"cancelled": 1, "unsatisfiable": 0, "rejected": 0}
    assert dyn["response"][4] is None and dyn["response"][3] == pytest.approx(sol.tasks[3]["finish"] - 3.0)
    assert sol.routes[0] == [] or 0 not in sol.routes[0][1:]  # robot 0 lost at t = 8
    assert sol.makespan >= max(t["finish"] for t in sol.tasks if t["finish"] == t["finish"])


def test_the_solution_of_a_grown_mission_carries_the_mission_as_it_ended(scenario, tmp_path):
    """Routes and tasks of a scenario's solution index the tasks and robots it added: the solution
    carries that instance (``final_instance``), which reads back and draws; a plain mission's does not."""
    from hmrta.solution import Solution, SolutionError, check_solution, final_instance

    inst = load_instance(scenario)
    sol = Solution.from_dict(json.loads(json.dumps(methods.solve(inst, "greedy", seed=0).to_dict())))
    grown = final_instance(inst, sol)
    assert (grown.n_tasks, grown.n_agents, grown.n_species) == (5, 6, 3) and grown.name == inst.name
    check_solution(grown, sol)
    assert final_instance(grown, sol) is grown
    assert "response time (finish - release) mean" in sol.summary() and "1 cancelled" in sol.summary()
    # the task the operator cancelled needs no coalition: it is not scored as unsatisfied (ETA = 10, of 5 tasks)
    from hmrta.solution import redundancy

    kept = [t["finish"] == t["finish"] for t in sol.tasks]  # (not NaN)
    assert sol.redundancy == pytest.approx(redundancy(grown, [t["members"] for t in sol.tasks], kept, kept))
    assert sol.redundancy < 10 / 5
    plain = load_instance(scenario.parent / "mission.yaml")
    assert "final_instance" not in methods.solve(plain, "greedy", seed=0).extra
    assert "\n" not in methods.solve(plain, "greedy", seed=0).summary()
    with pytest.raises(SolutionError, match="does not match"):
        final_instance(dataclasses.replace(plain, name="other", _cache={}), sol)
    pytest.importorskip("matplotlib")
    from hmrta.render import render

    assert render(grown, sol, tmp_path / "grown.png")[0].stat().st_size > 10000
    # hmrta render SCENARIO SOLUTION draws it the same way
    from hmrta.cli import main

    (tmp_path / "sol.json").write_text(json.dumps(sol.to_dict()))
    assert main(["render", str(scenario), str(tmp_path / "sol.json"), "--out", str(tmp_path / "cli.png")]) == 0
    assert (tmp_path / "cli.png").stat().st_size > 10000


def test_a_task_only_a_robot_that_joined_can_do_reads_back_and_draws(tmp_path, capsys):
    """A scenario adds a robot of a new kind, then a task only it can do: the solution's mission as
    it ended is feasible (the team counts the robot that joined), so render and the reader take it."""
    from hmrta.cli import main
    from hmrta.solution import Solution, final_instance

    (tmp_path / "base.yaml").write_text(
        "format: hmrta-instance/1\nrequirement_type: additive\nvelocity: 0.2\nskills: 2\nspecies:\n"
        "  - {traits: [1, 0], count: 2, depot: [0.1, 0.1]}\ntasks:\n"
        "  - {location: [0.5, 0.5], requirements: [1, 0], duration: 3}\n"
        "  - {location: [0.9, 0.5], requirements: [2, 0], duration: 3}\n")
    scen = tmp_path / "scen.yaml"
    scen.write_text(
        "format: hmrta-scenario/1\ninstance: base.yaml\nevents:\n"
        "  - {t: 1.0, type: add_robot, traits: [0, 1], position: [0.3, 0.3]}\n"
        "  - {t: 2.0, type: add_task, id: weld-1, location: [0.3, 0.6], requirements: [0, 1], duration: 2}\n")
    inst = load_instance(scen)
    sol = Solution.from_dict(json.loads(json.dumps(methods.solve(inst, "greedy", seed=0).to_dict())))
    assert sol.success and len(sol.tasks) == 3 and 2 in sol.routes[2]  # the robot that joined did it
    grown = final_instance(inst, sol)
    assert (grown.n_agents, grown.n_tasks, grown.added_agents) == (3, 3, (1,))
    (tmp_path / "sol.json").write_text(json.dumps(sol.to_dict()))
    assert main(["evaluate", str(tmp_path / "base.yaml"), str(tmp_path / "sol.json")]) == 2  # another mission
    assert "final_instance" not in capsys.readouterr().err
    pytest.importorskip("matplotlib")
    assert main(["render", str(scen), str(tmp_path / "sol.json"), "--out", str(tmp_path / "r.png")]) == 0


def test_cpsat_refuses_a_scenario(scenario, tmp_path, capsys):
    from hmrta.cli import main

    with pytest.raises(methods.MethodError, match="offline solver"):
        methods.solve(load_instance(scenario), "cpsat", seed=0)
    # before any work: nothing solved or written for the missions given before it
    mission = scenario.parent / "mission.yaml"
    assert main(["solve", str(mission), str(scenario), "--method", "cpsat", "--out", str(tmp_path / "o")]) == 2
    assert "offline solver" in capsys.readouterr().err and not (tmp_path / "o").exists()
    assert main(["bench", str(scenario), "--methods", "greedy,cpsat", "--out", str(tmp_path / "b"),
                 "--no-progress"]) == 2
    assert "offline solver" in capsys.readouterr().err and not (tmp_path / "b").exists()


def test_cli_solve_and_bad_file(scenario, tmp_path):
    out = tmp_path / "sol.json"
    r = subprocess.run([sys.executable, "-m", "hmrta.cli", "solve", str(scenario), "--method", "greedy",
                        "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(out.read_text())["dynamic"]["tasks_lost"]["cancelled"] == 1
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: hmrta-scenario/1\ninstance: mission.yaml\nevents:\n"
                   "  - {t: 1, type: add_task, id: a, location: [0.3, 0.6], requirements: [1, 1], duration: 2}\n"
                   "  - {t: 2, type: add_robot, species: 7}\n")
    r = subprocess.run([sys.executable, "-m", "hmrta.cli", "solve", str(bad), "--method", "greedy"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0
    assert "bad.yaml (line 5): events[1].species: expected a species index in 0..1, got 7" in r.stderr


@pytest.mark.parametrize("event, message", [
    ({"t": -1, "type": "lose_robot", "robot": 0}, "events[0].t: expected a finite time in [0, 1e+09]"),
    ({"t": 1, "type": "explode"}, "events[0].type: expected one of add_task"),
    ({"t": 1, "type": "lose_robot", "robot": 9}, "events[0].robot: expected a robot index in 0..3"),
    ({"t": 1, "type": "cancel_task", "id": "nope"}, "events[0].id: no add_task event has id 'nope'"),
    ({"t": 1, "type": "cancel_task", "id": 3}, "task index in 0..2"),
    ({"t": 1, "type": "add_robot", "traits": [1, 0]}, "missing field 'position'"),
    ({"t": 1, "type": "add_task", "id": "a", "location": [2, 0], "requirements": [1, 0], "duration": 1},
     "events[0].location: expected a point in the unit square"),
    ({"t": 1, "type": "add_task", "id": "a", "location": [0, 0], "requirements": [1, 0]}, "missing field 'duration'"),
    ({"t": 1, "type": "lose_robot", "robot": 0, "why": "x"}, "events[0].why: unknown field"),
    # integers too large for a float are refused like any number out of range (no OverflowError)
    ({"t": 10 ** 400, "type": "lose_robot", "robot": 0}, "events[0].t: expected a finite time in [0, 1e+09]"),
    ({"t": 1, "type": "add_task", "id": "a", "location": [0, 0], "requirements": [10 ** 400, 0], "duration": 1},
     "events[0].requirements"),
    ({"t": 1, "type": "add_task", "id": "a", "location": [0, 0], "requirements": [1, 0], "duration": 10 ** 400},
     "events[0].duration"),
    # and values a mission file could not hold (they were rejected only when the event came)
    ({"t": 1, "type": "add_task", "id": "a", "location": [0, 0], "requirements": [1e300, 1], "duration": 1},
     "events[0].requirements: expected a list of 2 numbers in [0, 1e+09]"),
    ({"t": 1, "type": "add_robot", "traits": [10 ** 29, 1], "position": [0, 0]},
     "events[0].traits: expected a list of 2 numbers in [0, 1e+09]"),
    # an id an operator could not give (it names a task of the mission by its index)
    ({"t": 1, "type": "add_task", "id": "7", "location": [0, 0], "requirements": [1, 0], "duration": 1},
     "events[0].id: an id of decimal digits names a task of the mission by its index"),
])
def test_scenario_errors_name_the_field(event, message):
    import yaml

    d = {"format": "hmrta-scenario/1", "instance": yaml.safe_load(MISSION), "events": [event]}
    with pytest.raises(ScenarioError, match=None) as e:
        scenario_from_dict(d, "s.yaml")
    assert message in str(e.value) and str(e.value).startswith("s.yaml")
    assert isinstance(e.value, InstanceError)


@pytest.mark.parametrize("events, message", [
    # the file lists the robot's arrival first, but it joins after the time of its loss
    ([{"t": 1, "type": "add_robot", "species": 0}, {"t": 0.5, "type": "lose_robot", "robot": 4}],
     "events[1].robot: expected a robot of the mission at t=0.5 (0..3), got 4: it is added later"),
    ([{"t": 1, "type": "lose_robot", "robot": 0}, {"t": 2, "type": "lose_robot", "robot": 0}],
     "events[1].robot: robot 0 is lost twice"),
    ([{"t": 2, "type": "cancel_task", "id": "x"},
      {"t": 5, "type": "add_task", "id": "x", "location": [0.3, 0.3], "requirements": [1, 0], "duration": 1}],
     "events[0].id: task 'x' is cancelled at t=2, before its add_task event"),
    ([{"t": 1, "type": "cancel_task", "id": 1}, {"t": 2, "type": "cancel_task", "id": 1}],
     "events[1].id: task 1 is cancelled twice"),
    ([{"t": 1, "type": "add_task", "id": "x", "location": [0.3, 0.3], "requirements": [1, 0], "duration": 1},
      {"t": 3, "type": "cancel_task", "id": "x"}, {"t": 2, "type": "cancel_task", "id": "x"}],
     "events[1].id: task 'x' is cancelled twice"),
])
def test_robot_losses_and_cancellations_are_checked_in_time_order(events, message):
    """Events apply in time order, whatever their order in the file: a robot can be lost only once
    it is in the mission, and only once; a task cancelled only after it is added, and only once
    (each was accepted and then logged as rejected)."""
    import yaml

    d = {"format": "hmrta-scenario/1", "instance": yaml.safe_load(MISSION), "events": events}
    with pytest.raises(ScenarioError) as e:
        scenario_from_dict(d, "s.yaml")
    assert str(e.value).startswith("s.yaml") and message in str(e.value), str(e.value)


def test_release_field_on_instance_tasks(tmp_path):
    p = tmp_path / "m.yaml"
    p.write_text(MISSION.replace("duration: 1}", "duration: 1, release: 2.5}"))
    inst = load_instance(p)
    assert inst.tasks[2].release == 2.5 and inst.dynamic
    assert "release: 2.5" in inst.to_yaml()
    p.write_text(MISSION.replace("duration: 1}", "duration: 1, release: -1}"))
    with pytest.raises(InstanceError, match=r"tasks\[2\].release: expected a time >= 0"):
        load_instance(p)


def test_learned_policy_released_equals_added():
    """A task known from the start with release t (masked, not observed until t) and the same task
    added at t by an event: the learned policy takes the same decisions, the missions are equal."""
    pytest.importorskip("torch")
    from hmrta.rl.features import observe

    base = ScenarioGenerator("MA-AT", 9, 3, 12, 3).instance(11, 0)
    late = [dataclasses.replace(t, release=0.0) for t in base.tasks[-3:]]
    early = dataclasses.replace(base, tasks=base.tasks[:-3], _cache={})
    times = [3.0, 7.5, 12.0]
    released = dataclasses.replace(
        base, tasks=early.tasks + tuple(dataclasses.replace(t, release=r) for t, r in zip(late, times)), _cache={})
    added = dataclasses.replace(early, events=tuple(
        {"t": r, "type": "add_task", "task": {"location": list(t.location), "requirements": list(t.requirements),
                                               "duration": t.duration}} for t, r in zip(late, times)), _cache={})
    decide, rules = methods.decider("rl")
    a, b = MissionState(released, 4, rules), MissionState(added, 4, rules)
    seen_hidden = False
    while not a.done:
        assert not b.done
        oa, ob = observe(a), observe(b)
        seen_hidden |= a.n_hidden > 0
        for x, y in zip(oa[:3], ob[:3]):
            assert np.array_equal(x, y)
        assert np.array_equal(oa[3], ob[3])
        na, nb = decide(a), decide(b)
        assert na == nb
        a.step(na)
        b.step(nb)
    assert b.done and seen_hidden
    assert a.routes == b.routes and a.makespan == b.makespan and a.success
    sa, sb = (methods.solve(x, "rl", seed=4) for x in (released, added))
    assert sa.routes == sb.routes and sa.extra["dynamic"]["response"] == sb.extra["dynamic"]["response"]


def test_scenario_naming_a_scenario_is_refused(scenario, tmp_path):
    """The mission a scenario names is a mission: another scenario, or the file itself, is an error
    (no recursion), and a parsed mapping without a loader takes only an inline mission."""
    own = tmp_path / "self.yaml"
    own.write_text("format: hmrta-scenario/1\ninstance: self.yaml\nevents: []\n")
    nested = tmp_path / "nested.yaml"
    nested.write_text(f"format: hmrta-scenario/1\ninstance: {scenario.name}\nevents: []\n")
    for p in (own, nested):
        with pytest.raises(ScenarioError, match=r"\(line 2\): instance: .*: expected a mission \(hmrta-instance/1\), "
                                                r"got a scenario"):
            load_instance(p)
    with pytest.raises(ScenarioError, match="instance: expected an inline hmrta-instance/1 mapping"):
        scenario_from_dict({"format": "hmrta-scenario/1", "instance": "mission.yaml", "events": []}, "s.yaml")


def test_small_rollouts_run_their_forwards_on_one_thread(scenario):
    """The forwards of a single mission (and of a few samples) run on one intra-op thread, so that
    their cost does not depend on a busy machine's thread pool and live agents (one thread) take
    the same decisions; the process setting is restored afterwards, and large batches keep it."""
    torch = pytest.importorskip("torch")
    from hmrta.rl import rollout as R
    from hmrta.rl.inference import load_policy

    pol = load_policy(None)
    seen: list[int] = []
    hook = pol.model.register_forward_pre_hook(lambda *_: seen.append(torch.get_num_threads()))
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        methods.solve(load_instance(scenario), "rl", seed=0)
        assert seen and set(seen) == {1} and torch.get_num_threads() == 2
        seen.clear()
        states = [MissionState(load_instance(scenario), k, pol.rules) for k in range(R.SINGLE_THREAD_STATES + 1)]
        R.rollout(pol.model, states, sample=False)
        assert seen[0] == 2 and torch.get_num_threads() == 2 and all(s.done for s in states)
    finally:
        hook.remove()
        torch.set_num_threads(old)


@pytest.mark.parametrize("argv", [["evaluate", "{scen}", "{routes}"], ["bound", "{scen}"],
                                  ["convert", "{scen}", "--out", "{tmp}/conv.yaml"]])
def test_commands_that_would_drop_a_scenarios_events_refuse_it(scenario, tmp_path, argv, capsys):
    from hmrta.cli import main

    (tmp_path / "routes.json").write_text("[[], [], [], []]")
    args = [a.format(scen=scenario, routes=tmp_path / "routes.json", tmp=tmp_path) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a scenario (a mission with timed events)" in err[0] and "events would be lost" in err[0]
    assert not (tmp_path / "conv.yaml").exists()


def test_events_not_applied_are_named_in_the_summary(tmp_path):
    """An event the mission could not take (a task already done when its cancellation comes, a
    robot joining after the end) is listed in the solution and named in its summary line."""
    (tmp_path / "mission.yaml").write_text(MISSION)
    (tmp_path / "s.yaml").write_text("format: hmrta-scenario/1\ninstance: mission.yaml\nevents:\n"
                                     "  - {t: 100.0, type: cancel_task, id: 0}\n"
                                     "  - {t: 1000.0, type: add_robot, species: 0}\n")
    sol = methods.solve(load_instance(tmp_path / "s.yaml"), "greedy", seed=0)
    plain = methods.solve(load_instance(tmp_path / "mission.yaml"), "greedy", seed=0)
    assert sol.success and sol.makespan == plain.makespan
    rejected = [e for e in sol.extra["dynamic"]["events"] if "rejected" in e]
    assert [e["type"] for e in rejected] == ["cancel_task", "add_agent"]
    assert "2 other event(s) not applied (first: cancel_task at t=100.0: after the mission's end" in sol.summary()


def test_release_times_are_kept_by_convert_and_bound_and_refused_by_evaluate(tmp_path, capsys):
    """A mission whose tasks have release times is a mission file (hmrta-instance/1 holds them):
    convert keeps them, bound bounds it (a release only delays a task), evaluate (which takes
    every task as known at time 0) refuses it naming the release times; and evaluate refuses the
    routes of a mission with events instead of miscounting them."""
    import yaml

    from hmrta.cli import main

    d = yaml.safe_load(MISSION)
    d["tasks"][1]["release"] = 5.0
    (tmp_path / "rel.yaml").write_text(yaml.safe_dump(d))
    assert main(["convert", str(tmp_path / "rel.yaml"), "--out", str(tmp_path / "out.yaml")]) == 0
    assert load_instance(tmp_path / "out.yaml").tasks[1].release == 5.0
    assert main(["bound", str(tmp_path / "rel.yaml")]) == 0
    capsys.readouterr()
    (tmp_path / "routes.json").write_text(json.dumps({"routes": [[], [], [], []]}))
    assert main(["evaluate", str(tmp_path / "rel.yaml"), str(tmp_path / "routes.json")]) == 2
    assert "1 task(s) with a release time" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "rel.yaml"), "--out", str(tmp_path / "out.json")]) == 2
    assert "give a .yaml file name" in capsys.readouterr().err and not (tmp_path / "out.json").exists()
    # the solution of a scenario where a robot joined: named as such, not "expected 4 routes, got 5"
    (tmp_path / "mission.yaml").write_text(MISSION)
    (tmp_path / "s.yaml").write_text("format: hmrta-scenario/1\ninstance: mission.yaml\nevents:\n"
                                     "  - {t: 1.0, type: add_robot, species: 0}\n")
    assert main(["solve", str(tmp_path / "s.yaml"), "--method", "greedy", "--out", str(tmp_path / "sol.json")]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "mission.yaml"), str(tmp_path / "sol.json")]) == 2
    assert "the solution of a mission with events" in capsys.readouterr().err
