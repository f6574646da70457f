"""Route evaluation (SPEC §3) on hand-made routes, SPEC §4 metrics and the hmrta-solution/1 format."""
from __future__ import annotations

import json
import math

import pytest

from hmrta.instance import instance_from_dict
from hmrta.solution import (ETA, RouteError, Solution, evaluate_routes, parse_routes, redundancy,
                            satisfies)

U = 0.125  # coordinates in units of U and velocity U: travel time = distance in units (exact)


def make(rt, skills, species, tasks):
    return instance_from_dict({
        "format": "hmrta-instance/1", "name": "hand", "requirement_type": rt, "velocity": U, "skills": skills,
        "species": [{"traits": list(t), "count": c, "depot": [x * U, y * U]} for t, c, (x, y) in species],
        "tasks": [{"location": [x * U, y * U], "requirements": list(q), "duration": d} for (x, y), q, d in tasks],
    })


# agent 0 [1,0] at D0 (0,0); agent 1 [0,2] at D1 (3,1)
# T0 (3,4) q [1,1] dur 2; T1 (7,1) q [0,2] dur 1.  |D0 T0| 5, |D1 T0| 3, |D1 T1| 4, |T0 T1| 5
INST = make("additive", 2, [([1, 0], 1, (0, 0)), ([0, 2], 1, (3, 1))],
            [((3, 4), [1, 1], 2), ((7, 1), [0, 2], 1)])


def test_evaluate_greedy_order():
    # a0: D0 -> T0 (arr 5); a1: D1 -> T0 (arr 3, waits 2); T0 5..7; a1 -> T1 arr 12, 12..13 -> home 17
    sol = evaluate_routes(INST, [[0], [0, 1]])
    assert sol.success and sol.makespan == 17.0 and sol.awt == 1.0 and sol.redundancy == 0.25
    assert sol.tasks == [{"start": 5.0, "finish": 7.0, "members": [0, 1]},
                         {"start": 12.0, "finish": 13.0, "members": [1]}]
    assert [a["return_time"] for a in sol.agents] == [12.0, 17.0]


def test_evaluate_partner_arrives_late():
    # a1 does T1 first: arr 4, 4..5, -> T0 arr 10; a0 arrives T0 at 5 and waits 5.
    # T0 10..12; a0 home 12 + 5 = 17, a1 home 12 + 3 = 15. AWT (5 + 0) / 2 = 2.5
    sol = evaluate_routes(INST, [[0], [1, 0]])
    assert sol.tasks == [{"start": 10.0, "finish": 12.0, "members": [0, 1]},
                         {"start": 4.0, "finish": 5.0, "members": [1]}]
    assert [a["return_time"] for a in sol.agents] == [17.0, 15.0]
    assert (sol.makespan, sol.awt) == (17.0, 2.5)


def test_evaluate_binary_coverage_and_idle_agents():
    # BT: agent 0 [1,1] alone covers T0 (q [1,1]); agents 1, 2 idle (return 0) count in AWT.
    inst = make("binary", 2, [([1, 1], 1, (0, 0)), ([1, 0], 2, (0, 0))], [((3, 4), [1, 1], 1.5)])
    sol = evaluate_routes(inst, [[0], [], []])
    assert sol.makespan == 11.5 and sol.awt == 0.0 and sol.redundancy == 0.0
    assert [a["return_time"] for a in sol.agents] == [11.5, 0.0, 0.0]
    # agent 1 adds nothing needed but is in the coalition: over-provision c = [2,1] vs q = [1,1]
    sol = evaluate_routes(inst, [[0], [0], []])
    assert sol.redundancy == 0.5 and sol.awt == 0.0


# ---- deadlock (cyclic waiting) -----------------------------------------------------------------
CROSS = make("additive", 2, [([1, 0], 1, (0, 0)), ([0, 1], 1, (0, 0))],
             [((3, 4), [1, 1], 1), ((4, 3), [1, 1], 1)])


def test_cyclic_waiting_is_a_deadlock():
    with pytest.raises(RouteError) as ei:
        evaluate_routes(CROSS, [[0, 1], [1, 0]])
    assert str(ei.value) == "deadlock: cyclic waiting among tasks [0, 1]"
    # the same tasks in the same order for both is fine: T0 5..6, T1 (|T0 T1| = sqrt 2 u) ...
    sol = evaluate_routes(CROSS, [[0, 1], [0, 1]])
    assert sol.tasks[0]["start"] == 5.0 and sol.tasks[1]["start"] == pytest.approx(6.0 + math.sqrt(2), rel=1e-15)


def test_three_agent_cycle_after_a_valid_prefix():
    # T0 needs a0+a1, T1 a1+a2, T2 a2+a0; T3 a0 alone (done first). Then a0 waits at T0 for a1,
    # a1 waits at T1 for a2, a2 waits at T2 for a0: a cycle of three.
    inst = make("additive", 3, [([1, 0, 0], 1, (0, 0)), ([0, 1, 0], 1, (0, 0)), ([0, 0, 1], 1, (0, 0))],
                [((1, 1), [1, 1, 0], 1), ((2, 2), [0, 1, 1], 1), ((3, 3), [1, 0, 1], 1), ((4, 4), [1, 0, 0], 1)])
    with pytest.raises(RouteError, match=r"deadlock: cyclic waiting among tasks \[0, 1, 2\]"):
        evaluate_routes(inst, [[3, 0, 2], [1, 0], [2, 1]])
    assert evaluate_routes(inst, [[3, 0, 2], [0, 1], [1, 2]]).success


# ---- other route errors ----------------------------------------------------------------------
def test_uncovered_and_unsatisfied_tasks():
    with pytest.raises(RouteError, match="task 1 is not covered by any route"):
        evaluate_routes(INST, [[0], [0]])
    with pytest.raises(RouteError) as ei:
        evaluate_routes(INST, [[0, 1], []])
    assert str(ei.value) == "task 0: its coalition (agents [0]) lacks skill(s) [1]"


@pytest.mark.parametrize("data,match", [
    ([[0], [0, 1]], "expected a JSON object with a 'routes' key"),
    ({"route": []}, "expected a JSON object with a 'routes' key"),
    ({"routes": [[0]]}, r"expected a list of 2 routes .* got 1"),
    ({"routes": {"0": [0]}}, r"expected a list of 2 routes .* got dict"),
    ({"routes": [[0], 1]}, r"routes\[1\]: expected a list of task ids"),
    ({"routes": [[0], [0, 2]]}, r"routes\[1\]\[1\]: unknown task id 2 \(expected 0..1\)"),
    ({"routes": [[-1], [0, 1]]}, r"routes\[0\]\[0\]: unknown task id -1"),
    ({"routes": [["0"], [0, 1]]}, r"routes\[0\]\[0\]: unknown task id '0'"),
    ({"routes": [[True], [0, 1]]}, r"routes\[0\]\[0\]: unknown task id True"),
    ({"routes": [[0.0], [0, 1]]}, r"routes\[0\]\[0\]: unknown task id 0.0"),
    ({"routes": [[0], [0, 1, 0]]}, r"routes\[1\]: agent 1 visits task 0 twice"),
])
def test_parse_routes_errors(data, match):
    with pytest.raises(RouteError, match=match) as ei:
        parse_routes(INST, data, source="r.json")
    assert str(ei.value).startswith("r.json: ") and "\n" not in str(ei.value)


def test_parse_routes_accepts_extra_keys():
    """ROUTES.json is any object with a 'routes' key (e.g. a whole hmrta-solution/1 file)."""
    sol = evaluate_routes(INST, [[0], [0, 1]])
    assert parse_routes(INST, json.loads(json.dumps(sol.to_dict()))) == [[0], [0, 1]]


# ---- metrics -----------------------------------------------------------------------------------
def test_redundancy_and_satisfies():
    # exact: T0 coalition {0,1}: c [1,2] vs [1,1] -> 1/2; T1 unsatisfied -> eta = 10
    assert redundancy(INST, [[0, 1], [0]], [True, False]) == (0.5 + ETA) / 2
    assert ETA == 10.0
    assert satisfies(INST, [0, 1], 0) == [] and satisfies(INST, [0], 0) == [1] and satisfies(INST, [], 1) == [1]
    assert satisfies(INST, [0], 1) == [1]


# ---- hmrta-solution/1 ----------------------------------------------------------------------------
def test_solution_format_round_trip(tmp_path):
    sol = evaluate_routes(INST, [[0], [0, 1]], method="m", seed=3)
    d = sol.to_dict()
    assert list(d) == ["format", "instance", "method", "seed", "success", "makespan", "awt", "redundancy",
                       "compute_seconds", "routes", "tasks", "agents"]
    assert d["format"] == "hmrta-solution/1" and d["instance"] == "hand" and d["seed"] == 3
    assert d["agents"] == [{"species": 0, "return_time": 12.0}, {"species": 1, "return_time": 17.0}]
    p = tmp_path / "s.json"
    sol.save(p)
    back = Solution.from_dict(json.loads(p.read_text()))
    assert back.to_dict() == d
    assert "makespan 17.000" in back.summary()


def test_failed_solution_serialises_nan_as_null():
    sol = Solution("x", "m", 0, False, math.nan, 0.0, 10.0, 0.1, [[]], [
        {"start": math.nan, "finish": math.nan, "members": []}], [{"species": 0, "return_time": math.nan}],
        {"failure": "deadlock: no agent can move"})
    text = json.dumps(sol.to_dict())
    assert "NaN" not in text  # strict JSON
    d = json.loads(text)
    assert d["makespan"] is None and d["tasks"][0]["start"] is None and d["failure"].startswith("deadlock")
    back = Solution.from_dict(d)
    assert math.isnan(back.makespan) and back.extra == {"failure": "deadlock: no agent can move"}
    assert "FAILED (deadlock" in back.summary()


# ---- reading solution files ------------------------------------------------------------------
def _sol_dict():
    return json.loads(json.dumps(evaluate_routes(INST, [[0], [0, 1]], method="m", seed=3).to_dict()))


def _edit(**kv):
    def f(d):
        for k, v in kv.items():
            obj, *rest = k.split("__")
            target = d
            keys = [obj] + rest
            for key in keys[:-1]:
                target = target[int(key) if key.isdigit() else key]
            last = keys[-1]
            target[int(last) if last.isdigit() else last] = v
        return d
    return f


@pytest.mark.parametrize("edit,expect", [
    (_edit(format="hmrta-solution/2"), "format: expected 'hmrta-solution/1'"),
    (_edit(makespan="17"), "makespan: expected a number in [0, 1e+15] or null, got '17'"),
    (_edit(makespan=-1), "makespan: expected a number in [0, 1e+15] or null"),
    (_edit(makespan=3.0), "makespan: expected at least the last finish or return time (17)"),
    (_edit(success="yes"), "success: expected true or false"),
    (_edit(seed=1.5), "seed: expected an integer"),
    (_edit(method=["x"]), "method: expected a string"),
    (_edit(routes=[[0]]), "routes: expected one route per agent (2 agents listed), got 1"),
    (_edit(routes__1__1=2), "routes[1][1]: unknown task id 2 (expected 0..1: the file lists 2 tasks)"),
    (_edit(tasks__0__members=[0, 5]), "tasks[0].members[1]: unknown agent id 5"),
    (_edit(tasks__0__start=None), "tasks[0].finish: expected a finish >= the start"),
    (_edit(tasks__1__finish=0.5), "tasks[1].finish: expected a finish >= the start"),
    (_edit(tasks__0__extra=1), "tasks[0]: unknown key 'extra'"),
    (_edit(agents__1__species=-1), "agents[1].species: expected an integer >= 0"),
    (_edit(lower_bound="3"), "lower_bound: expected a number in [0, 1e+15] or null"),
    (_edit(status=7), "status: expected a string"),
    (lambda d: [d], "expected an object with keys"),
    (lambda d: {k: v for k, v in d.items() if k != "agents"}, "missing key 'agents'"),
])
def test_solution_files_are_validated(tmp_path, edit, expect):
    from hmrta.solution import SolutionError, read_solution

    p = tmp_path / "s.json"
    p.write_text(json.dumps(edit(_sol_dict())))
    with pytest.raises(SolutionError) as ei:
        read_solution(p)
    msg = str(ei.value)
    assert msg.startswith(f"{p}: ") and "\n" not in msg and expect in msg, msg


def test_solution_file_extra_keys_are_kept(tmp_path):
    from hmrta.solution import read_solution

    d = _sol_dict()
    d.update(lower_bound=12.5, status="OPTIMAL", note={"anything": [1, 2]})
    p = tmp_path / "s.json"
    p.write_text(json.dumps(d))
    sol = read_solution(p)
    assert sol.extra == {"lower_bound": 12.5, "status": "OPTIMAL", "note": {"anything": [1, 2]}}
    assert sol.to_dict() == d


def test_routes_file_reader(tmp_path):
    from hmrta.solution import read_routes

    p = tmp_path / "r.json"
    p.write_bytes(b'{"routes": [[0], [0, 1]]}')
    assert read_routes(INST, p) == [[0], [0, 1]]
    p.write_bytes(b'{"routes": [[0], [0, \xff1]]}')
    with pytest.raises(RouteError, match=r"r.json: not UTF-8 text \(byte offset 21\)"):
        read_routes(INST, p)
    with pytest.raises(RouteError, match="is a folder, expected a file"):
        read_routes(INST, tmp_path)


def test_a_solution_whose_routes_miss_the_tasks_its_robots_did_is_refused():
    """Routes edited apart from the tasks (every route emptied, success and makespan kept): render
    and bound would draw and score a schedule that does not exist."""
    from hmrta.generators import ScenarioGenerator
    from hmrta.methods import solve
    from hmrta.solution import SolutionError, check_solution

    inst = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(0, 0)
    d = solve(inst, "greedy", seed=0).to_dict()
    check_solution(inst, Solution.from_dict(d))
    d["routes"] = [[] for _ in d["routes"]]
    with pytest.raises(SolutionError, match=r"tasks\[0\]\.members: robot \d+ did task 0, but task 0 is not on its route"):
        check_solution(inst, Solution.from_dict(d))


def test_a_solution_whose_routes_run_against_its_task_times_is_refused():
    """A route reversed (the same tasks, the timings kept): a robot would start a task before it
    finished the one before it on its route."""
    from hmrta.generators import ScenarioGenerator
    from hmrta.methods import solve
    from hmrta.solution import SolutionError, check_solution

    inst = ScenarioGenerator("MA-AT", 4, 2, 8, 2).instance(0, 0)
    d = solve(inst, "greedy", seed=0).to_dict()
    a = next(i for i, r in enumerate(d["routes"]) if len(r) > 1)
    d["routes"][a] = d["routes"][a][::-1]
    with pytest.raises(SolutionError, match=rf"routes\[{a}\]\[1\]: task \d+ starts at .* before task \d+ \(earlier "
                                            rf"on robot {a}'s route\) finishes"):
        check_solution(inst, Solution.from_dict(d))


# ---- partial results: the coalitions under way when a run stopped -----------------------------
def _stopped():
    """A greedy run of an MA-AT mission stopped by its time limit with tasks in progress."""
    from hmrta.baselines import Greedy
    from hmrta.core import Rules
    from hmrta.generators import ScenarioGenerator
    from hmrta.sim import simulate

    inst = ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(1, 0)
    return inst, simulate(inst, Greedy(), 0, Rules(t_max=12.0, safety=True), "greedy")


def test_a_stopped_run_lists_the_tasks_in_progress_and_reads_back():
    from hmrta.baselines import Greedy
    from hmrta.core import IN_PROGRESS, MissionState, Rules

    inst, sol = _stopped()
    # the same run by hand: the state where it stopped
    st = MissionState(inst, seed=0, rules=Rules(t_max=12.0, safety=True))
    while not st.done:
        st.step(Greedy()(st))
    running = [m for m in range(inst.n_tasks) if st.status[m] == IN_PROGRESS]
    assert not sol.success and running
    assert sol.extra["in_progress"] == [{"task": m, "start": float(st.start[m]), "finish": float(st.finish[m]),
                                         "members": sorted(st.members[m])} for m in running]
    assert all(math.isnan(sol.tasks[m]["finish"]) for m in running)  # not done: no times in tasks
    d = json.loads(json.dumps(sol.to_dict()))
    back = Solution.from_dict(d)
    assert back.extra["in_progress"] == sol.extra["in_progress"] and back.to_dict() == d
    line = back.summary().splitlines()[1]
    assert line.startswith("  coalitions complete when it stopped: ") and f"task {running[0]} (start " in line


def test_a_finished_run_has_no_tasks_in_progress():
    from hmrta.methods import solve

    assert "in_progress" not in solve(INST, "greedy", 0).extra


@pytest.mark.parametrize("edit,expect", [
    (lambda d, r: r.update(task=r["task"] + 100), "in_progress[0].task: expected a task not done"),
    (lambda d, r: d["in_progress"].append(dict(r)), "in_progress[1].task: expected a task not done and listed once"),
    (lambda d, r: r.update(finish=r["start"] / 2), "in_progress[0].finish: expected a planned finish >= the start"),
    (lambda d, r: r.update(start=None), "in_progress[0].finish: expected a planned finish >= the start"),
    (lambda d, r: r.update(members=[99]), "in_progress[0].members[0]: unknown agent id 99"),
    (lambda d, r: r.update(members=[]), "in_progress[0].members: expected the distinct agents of a coalition"),
    (lambda d, r: r.update(members=r["members"][:1] * 2), "in_progress[0].members: expected the distinct agents"),
    (lambda d, r: r.update(members=r["members"] + [next(a for a, rt in enumerate(d["routes"]) if r["task"] not in rt)]),
     "does not have task 4 on its route"),
    (lambda d, r: r.pop("members"), "in_progress[0]: missing key 'members'"),
    (lambda d, r: d.update(in_progress={}), "in_progress: expected a list"),
])
def test_tasks_in_progress_are_validated(tmp_path, edit, expect):
    from hmrta.solution import SolutionError, read_solution

    _, sol = _stopped()
    d = json.loads(json.dumps(sol.to_dict()))
    edit(d, d["in_progress"][0])
    p = tmp_path / "s.json"
    p.write_text(json.dumps(d))
    with pytest.raises(SolutionError) as ei:
        read_solution(p)
    msg = str(ei.value)
    assert msg.startswith(f"{p}: ") and "\n" not in msg and expect in msg, msg


def test_a_successful_solution_with_tasks_in_progress_is_refused():
    from hmrta.solution import SolutionError

    d = _sol_dict()
    d["in_progress"] = [{"task": 0, "start": 1.0, "finish": 2.0, "members": [0]}]
    with pytest.raises(SolutionError, match="in_progress: expected no tasks in progress: the solution succeeded"):
        Solution.from_dict(d)
