"""CP-SAT solver: optimality against an independent brute force on tiny instances, anytime
behaviour (never worse than its warm start), consistent re-evaluation, hint feasibility."""
from __future__ import annotations

import dataclasses
import importlib.util
import itertools
import json
import math

import pytest

from hmrta import methods
from hmrta.generators import ScenarioGenerator
from hmrta.instance import Instance, Species, Task
from hmrta.methods import MethodError, solve
from hmrta.solution import RouteError, evaluate_routes, satisfies

# (a module-level skip, not importorskip: test_bounds imports the brute force from here)
pytestmark = pytest.mark.skipif(importlib.util.find_spec("ortools") is None, reason="ortools not installed")


# ---------------------------------------------------------------------------------------------
# independent brute force
# ---------------------------------------------------------------------------------------------
def _fast_makespan(inst: Instance, routes, T, S):
    """Route evaluation (SPEC §3) in plain Python; None on cyclic waiting. Same float operations
    as hmrta.solution.evaluate_routes, so equal results."""
    A, M = inst.n_agents, inst.n_tasks
    coal = [[] for _ in range(M)]
    for a, r in enumerate(routes):
        for m in r:
            coal[m].append(a)
    ptr = [0] * A
    ready = [0.0] * A
    where = [int(inst.agent_species[a]) for a in range(A)]
    dur = inst.durations
    started = [False] * M
    left = M
    while left:
        prog = False
        for m in range(M):
            if started[m]:
                continue
            if all(ptr[a] < len(routes[a]) and routes[a][ptr[a]] == m for a in coal[m]):
                st = max(ready[a] + T[where[a]][S + m] for a in coal[m])
                fin = st + dur[m]
                for a in coal[m]:
                    ready[a], where[a] = fin, S + m
                    ptr[a] += 1
                started[m] = True
                left -= 1
                prog = True
        if not prog:
            return None
    return max(ready[a] + T[where[a]][int(inst.agent_species[a])] for a in range(A))


def brute_force(inst: Instance, minimal: bool = True) -> tuple[float, list[list[int]]]:
    """Optimal makespan by enumerating a coalition per task and a visiting order per agent.
    ``minimal``: only coalitions from which no member can be removed (removing an unneeded
    member never delays anything: travel obeys the triangle inequality); else every satisfying
    coalition."""
    from hmrta.solvers.listsched import travel_matrix

    A, M, S = inst.n_agents, inst.n_tasks, inst.n_species
    T = travel_matrix(inst).tolist()
    coals = []
    for m in range(M):
        ok = [c for r in range(1, A + 1) for c in itertools.combinations(range(A), r)
              if not satisfies(inst, list(c), m)]
        if minimal:
            ok = [c for c in ok if all(satisfies(inst, [b for b in c if b != a], m) for a in c)]
        coals.append(ok)
    best, best_routes = math.inf, None
    for choice in itertools.product(*coals):
        sets = [[m for m in range(M) if a in choice[m]] for a in range(A)]
        for perms in itertools.product(*[itertools.permutations(s) for s in sets]):
            v = _fast_makespan(inst, perms, T, S)
            if v is not None and v < best:
                best, best_routes = v, [list(p) for p in perms]
    assert best_routes is not None
    assert evaluate_routes(inst, best_routes).makespan == best
    return best, best_routes


# (scenario, agents, species, tasks, skills, index); in each of these the list-scheduler hint is
# not optimal, so the model itself has to find and prove the optimum
TINY = [
    ("MA-AT", 3, 3, 4, 3, 1),  # one agent per species
    ("SA-AT", 4, 2, 4, 2, 1),  # two agents per species: integer flows / coalitions of 2
    ("MA-BT", 3, 3, 4, 3, 1),
    ("MA-AT", 4, 2, 4, 3, 3),
    ("SA-AT", 4, 2, 5, 2, 2),
    ("MA-AT", 3, 3, 5, 3, 2),
]


def _tiny(row) -> Instance:
    scen, a, s, m, k, i = row
    return ScenarioGenerator(scen, a, s, m, k).instance(11, i)


def test_minimal_coalitions_dominate():
    """The brute force over minimal coalitions equals the one over all satisfying coalitions."""
    inst = _tiny(("MA-AT", 3, 3, 4, 3, 1))
    assert brute_force(inst, minimal=True)[0] == brute_force(inst, minimal=False)[0]


@pytest.mark.parametrize("row", TINY, ids=lambda r: f"{r[0]}-{r[1]}-{r[2]}-{r[3]}-{r[4]}#{r[5]}")
def test_optimal_against_brute_force(row):
    inst = _tiny(row)
    opt, _ = brute_force(inst)
    sol = solve(inst, "cpsat", seed=0, time_limit=20, heuristic_seconds=0.0)
    e = sol.extra
    assert e["status"] == "optimal"
    assert e["hint_makespan"] > opt + 1e-6  # the model improved on its hint
    # optimal for the x1000 rounded-up model: within the rounding slack of the float optimum
    assert opt - 1e-9 <= sol.makespan <= opt + e["rounding_slack"] + 1e-9
    assert e["lower_bound"] <= opt + 1e-9
    assert sol.makespan <= e["objective"] + 1e-9  # model times are rounded up
    assert evaluate_routes(inst, sol.routes).makespan == sol.makespan


def test_never_worse_than_warm_start_and_consistent():
    inst = ScenarioGenerator("MA-AT", 9, 3, 12, 3).instance(5, 0)
    greedy = solve(inst, "greedy", seed=0)
    sol = solve(inst, "cpsat", seed=0, time_limit=3, warm_start="greedy", heuristic_seconds=0.5)
    assert sol.success and sol.method == "cpsat"
    assert sol.makespan <= greedy.makespan + 1e-9
    assert sol.extra["warm_start"] == "greedy"
    assert sol.extra["status"] in ("optimal", "feasible")
    assert 0 < sol.extra["lower_bound"] <= sol.makespan + 1e-9
    # the reported metrics are the core's exact re-evaluation of the routes
    again = evaluate_routes(inst, sol.routes)
    assert again.makespan == sol.makespan and again.awt == sol.awt and again.redundancy == sol.redundancy
    d = sol.to_dict()
    assert {"status", "lower_bound", "objective"} <= set(d)


def test_warm_start_kept_when_model_has_no_time(monkeypatch):
    """With a warm start better than anything found, the warm start's routes come back."""
    inst = ScenarioGenerator("MA-AT", 9, 3, 10, 3).instance(5, 1)
    good = solve(inst, "cpsat", seed=0, time_limit=4, heuristic_seconds=0.5)

    def fake_rl(inst_, seed=0, **_):
        return evaluate_routes(inst_, good.routes, "rl", seed)

    monkeypatch.setitem(methods.METHODS, "rl", dataclasses.replace(methods.METHODS["rl"], solve=fake_rl))
    sol = solve(inst, "cpsat", seed=1, time_limit=0.3, warm_start="rl", heuristic_seconds=0.0)
    assert sol.makespan <= good.makespan + 1e-9
    assert sol.extra["warm_start_makespan"] == pytest.approx(good.makespan)


def test_rl_warm_start_failure_is_a_method_error(monkeypatch):
    def broken(inst_, seed=0, **_):
        raise FileNotFoundError("no checkpoint")

    monkeypatch.setitem(methods.METHODS, "rl", dataclasses.replace(methods.METHODS["rl"], solve=broken))
    inst = _tiny(TINY[0])
    with pytest.raises(MethodError, match="warm-start rl"):
        solve(inst, "cpsat", seed=0, time_limit=1, warm_start="rl")
    with pytest.raises(MethodError, match=r"warm_start \(--warm-start\): expected one of none, greedy, rl"):
        solve(inst, "cpsat", seed=0, time_limit=1, warm_start="bogus")


def test_hint_is_complete_and_feasible():
    from ortools.sat.python import cp_model

    from hmrta.solvers import cpsat as C
    from hmrta.solvers.listsched import best_list_schedule, prune_routes

    for inst in (ScenarioGenerator("MA-AT", 15, 5, 10, 5).instance(3, 0),
                 ScenarioGenerator("SA-AT", 9, 3, 8, 3).instance(3, 1),
                 ScenarioGenerator("SA-BT", 9, 3, 8, 3).instance(3, 2)):
        D = C._Data(inst)
        routes = prune_routes(inst, best_list_schedule(inst, 0, 0.0).routes)
        assert C._hint_valid(D, routes)
        _, hc = C._int_schedule(D, routes)
        md, *_ = C._build(D, hc, 0, routes)
        s = cp_model.CpSolver()
        s.parameters.fix_variables_to_their_hinted_value = True
        s.parameters.num_workers = 1
        s.parameters.max_time_in_seconds = 10
        assert s.Solve(md) in (cp_model.OPTIMAL, cp_model.FEASIBLE)
        assert s.ObjectiveValue() == hc


def test_zero_tasks_and_bt():
    inst = Instance("additive", 0.2, 2, (Species((1.0, 0.0), 2, (0.1, 0.1)),), (), "empty")
    sol = solve(inst, "cpsat", time_limit=1)
    assert sol.makespan == 0 and sol.extra["status"] == "optimal"
    # one task, one agent: makespan is the round trip plus the duration
    inst = Instance("binary", 0.2, 1, (Species((1.0,), 1, (0.0, 0.0)),),
                    (Task((0.6, 0.8), (1.0,), 2.0),), "one")
    sol = solve(inst, "cpsat", time_limit=2, heuristic_seconds=0.0)
    assert sol.makespan == pytest.approx(5.0 + 2.0 + 5.0)
    assert sol.extra["status"] == "optimal"


def test_bad_options():
    inst = _tiny(TINY[0])
    with pytest.raises(MethodError):
        solve(inst, "cpsat", time_limit=0)
    with pytest.raises(MethodError):
        solve(inst, "cpsat", time_limit=1, workers=0)


def test_routes_are_valid_for_evaluate():
    """Model routes never deadlock and never leave a task uncovered (raises RouteError otherwise)."""
    inst = ScenarioGenerator("SA-AT", 6, 2, 6, 2).instance(2, 0)
    sol = solve(inst, "cpsat", seed=3, time_limit=3, heuristic_seconds=0.2)
    try:
        evaluate_routes(inst, sol.routes)
    except RouteError as e:  # pragma: no cover - reported with the message
        pytest.fail(str(e))


def test_ctrl_c_during_the_cp_sat_search_stops_the_command(tmp_path):
    """CP-SAT's own SIGINT handler would end the search and hand back the incumbent as a normal
    result (the command went on and exited 0; bench cached it). A Ctrl-C in the CP-SAT phase
    stops `hmrta solve` at once with the best schedule so far, written and marked interrupted,
    and exit 130."""
    import signal
    import subprocess
    import sys
    import time

    import os
    import pty
    import select

    path = tmp_path / "m.yaml"
    ScenarioGenerator("MA-AT", 25, 5, 50, 5).instance(3, 0).save(path)
    out = tmp_path / "out.json"
    import fcntl
    import struct
    import termios

    master, slave = pty.openpty()  # stderr a terminal (24 x 160): the progress bar names the phase
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 160, 0, 0))
    p = subprocess.Popen([sys.executable, "-m", "hmrta.cli", "solve", "--method", "cpsat", "--time-limit", "120",
                          "--heuristic-seconds", "0.5", "--out", str(out), str(path)],
                         stdout=subprocess.PIPE, stderr=slave, text=True)
    os.close(slave)
    seen = []

    def read(wait: float) -> str:  # what the child wrote to its terminal so far
        end = time.monotonic() + wait
        while time.monotonic() < end and select.select([master], [], [], 0.1)[0]:
            try:
                seen.append(os.read(master, 65536).decode(errors="replace"))
            except OSError:  # the child closed its end
                break
        return "".join(seen)

    try:
        deadline = time.monotonic() + 60
        while "CP-SAT" not in read(0.2) and time.monotonic() < deadline:
            assert p.poll() is None, read(0.5)
        assert "CP-SAT" in read(0.1), "the CP-SAT phase never started"
        read(1.0)  # inside the search
        t0 = time.monotonic()
        p.send_signal(signal.SIGINT)
        stdout, _ = p.communicate(timeout=20)
        stopped = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    text = read(1.0).replace("\r", "\n")
    os.close(master)
    assert p.returncode == 130, text
    assert text.rstrip().endswith(f"written to {out}") and "interrupted: " in text and "Traceback" not in text
    assert "cpsat makespan" in stdout and json.loads(out.read_text())["interrupted"] is True
    assert stopped < 10.0  # not the 120 s time limit


def _interrupt_after(seconds: float):
    """A Ctrl-C to the main thread after ``seconds`` (as SIGINT raises KeyboardInterrupt there;
    tests/conftest.py makes sure Python handles SIGINT, also in a runner started in the background)."""
    import _thread
    import threading

    t = threading.Timer(seconds, _thread.interrupt_main)
    t.start()
    return t


def test_a_ctrl_c_while_the_model_is_built_keeps_the_heuristics_best(monkeypatch):
    from hmrta.solvers import cpsat
    from hmrta.methods import keep_best_on_interrupt
    from hmrta.solvers.cpsat import solve_cpsat

    def interrupted(*a, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(cpsat, "_build", interrupted)
    inst = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(3, 0)
    with keep_best_on_interrupt():
        sol = solve_cpsat(inst, 0, time_limit=5.0, heuristic_seconds=0.2)
    assert sol.extra["interrupted"] and sol.success and sol.extra["note"].startswith("interrupted before the CP-SAT")
    assert sol.makespan <= solve(inst, "greedy", 0).makespan
    with pytest.raises(KeyboardInterrupt):
        solve_cpsat(inst, 0, time_limit=5.0, heuristic_seconds=0.2)


def test_a_ctrl_c_keeps_the_best_solution_only_where_asked():
    """Within keep_best_on_interrupt (``hmrta solve``), a Ctrl-C in the CP-SAT phase or in the
    heuristic phase ends the solve with the best so far, marked interrupted; elsewhere (bench, a
    library call) it is raised."""
    import time

    from hmrta.methods import keep_best_on_interrupt
    from hmrta.solvers.cpsat import solve_cpsat

    inst = ScenarioGenerator("MA-AT", 25, 5, 50, 5).instance(3, 0)
    greedy = solve(inst, "greedy", 0).makespan
    for heuristic, at in ((0.3, 2.0), (15.0, 1.5)):  # Ctrl-C in CP-SAT, then in the annealing
        timer = _interrupt_after(at)
        t0 = time.perf_counter()
        try:
            with keep_best_on_interrupt():
                sol = solve_cpsat(inst, 0, time_limit=30.0, heuristic_seconds=heuristic)
        finally:
            timer.cancel()
        assert time.perf_counter() - t0 < at + 5.0
        assert sol.extra["interrupted"] and sol.success and sol.makespan <= greedy
        assert sol.extra["lower_bound"] <= sol.makespan
        assert evaluate_routes(inst, sol.routes).makespan == sol.makespan
    timer = _interrupt_after(1.5)
    try:
        with pytest.raises(KeyboardInterrupt):
            solve_cpsat(inst, 0, time_limit=30.0, heuristic_seconds=0.3)
    finally:
        timer.cancel()
