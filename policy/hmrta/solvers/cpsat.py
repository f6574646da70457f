"""Exact / anytime CP-SAT solver for the full problem (SPEC §1, route semantics of §3).

Method ``cpsat`` of :data:`hmrta.methods.METHODS`: ``solve(inst, 'cpsat', seed, time_limit=60, warm_start=None,
workers=2)``. The returned :class:`~hmrta.solution.Solution` is always the core's re-evaluation
(:func:`hmrta.solution.evaluate_routes`, exact float arithmetic) of per-agent routes; ``extra``
carries ``status`` (optimal / feasible / none), ``lower_bound``, ``objective`` and solver details.

Model (times scaled by ``SCALE = 1000`` and rounded *up*):

* coalition choice ``x[s,m] in 0..ub[s,m]`` (members of species s at task m); only species that
  contribute a needed skill are allowed, and ``ub`` is the number of members after which species s
  alone saturates every skill it contributes (more members can always be removed without making
  anything later: minimal coalitions dominate). AT: ``sum_s x[s,m] c_s >= q_m``; BT: every
  required skill is covered by some allowed species with ``x >= 1``.
* one routing structure per *species* (agents of a species are identical): integer arc flows
  ``f[s,i,j]`` over {depot, tasks}; in-flow = out-flow = ``x[s,m]`` at task m; depot out-flow
  <= count of the species.
* one start time per task, shared by its coalition. An arc used by any species (``y[i,j]``)
  implies ``start_j >= start_i + max(1, dur_i + travel_ij)`` (strict: the flow is acyclic, so it
  decomposes into depot-to-depot paths, one per agent); ``x[s,m] >= 1`` implies
  ``start_m >= travel(depot_s, m)`` and ``C >= start_m + dur_m + travel(m, depot_s)``.
* objective: minimise the makespan ``C``.
* redundant constraints that lift the bound: per-species workload (sum of flow x (duration +
  travel) <= count x C), a per-species cumulative (task intervals extended backwards by the
  shortest possible in-travel, demand ``x[s,m]``, capacity = count), and a per-skill cumulative
  with constant demand ``q_m,k`` (BT: 1) and capacity = the team's total of that skill.
* forced sharing: when ``x[s,i] + x[s,j] > count_s`` some agent serves both tasks, so one precedes
  the other by its duration + the travel between them (a disjunction on the start times).
* a complete hint (and the incumbent upper bound on C) from the best of the warm start, the greedy
  baseline and the heuristic phase.

Phases (all within ``time_limit`` seconds of wall time):

1. heuristic (``heuristic_seconds``, default 25% of the limit): a randomised list scheduler
   (:mod:`hmrta.solvers.listsched`, <= 1 s), then simulated annealing over task orders with a
   serial schedule decoder, one independent run per worker (forked processes), stopping early when
   it stalls or meets the cheap lower bound;
2. CP-SAT (``workers`` threads) on the model above, hinted with the best solution so far, for the
   rest of the time.
The result is the best of all of them, re-evaluated, so never worse than the warm start. Inside
:func:`hmrta.methods.keep_best_on_interrupt` (``hmrta solve``), a Ctrl-C in either phase ends
the solve with the best so far (``extra["interrupted"]``; the bound is what was proven by then);
elsewhere (``hmrta bench``, a library call) it is raised as usual. Models
with more than ``MAX_ARCS`` species arcs (about 110 tasks with 5 species) are not built: the whole
time goes to the heuristic, the status is ``none`` and the bound is the cheap one.

Rounding: every model time is >= 1000 x the float time, so the re-evaluated makespan of the
extracted routes is <= objective / 1000. Conversely the float optimum's routes have a model value
of at most 1000 x their makespan + ``slack`` (the rounding of at most M + 1 arcs on a chain), so
the reported float lower bound is ``(solver bound - slack) / 1000`` (and at least the cheap bounds
of :mod:`hmrta.bounds`). ``status == 'optimal'`` means optimal for the scaled model: the float
optimum is then within ``slack / 1000`` of the returned makespan (0.04 for 20 tasks).
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from ..instance import Instance
from ..errors import MethodError
from ..solution import Solution, evaluate_routes
from .listsched import SerialDecoder, best_list_schedule, order_of, parallel_anneal, prune_routes

SCALE = 1000


def _ceil_scaled(x: float) -> int:
    return int(math.ceil(x * SCALE))


def _integer_scale(values: np.ndarray, what: str) -> tuple[np.ndarray, int]:
    """Smallest power-of-ten scale (<= 1e6) making all values integers."""
    for p in range(7):
        f = 10**p
        v = np.asarray(values, dtype=np.float64) * f
        if np.all(np.abs(v - np.round(v)) <= 1e-9 * np.maximum(1.0, np.abs(v))):
            return np.round(v).astype(np.int64), f
    raise MethodError(f"cpsat: {what} must have at most 6 decimals")


class _Data:
    """Integer data of the scaled model."""

    def __init__(self, inst: Instance):
        self.inst = inst
        S, M = inst.n_species, inst.n_tasks
        self.S, self.M = S, M
        self.count = [s.count for s in inst.species]
        self.offset = np.concatenate([[0], np.cumsum(self.count)])[:-1].astype(int)
        self.dur = [_ceil_scaled(d) for d in inst.durations]
        loc = [tuple(p) for p in inst.task_locations]
        dep = [tuple(p) for p in inst.species_depots]
        self.t = [[_ceil_scaled(inst.travel_time(loc[i], loc[j])) if i != j else 0 for j in range(M)]
                  for i in range(M)]
        self.t_out = [[_ceil_scaled(inst.travel_time(dep[s], loc[m])) for m in range(M)] for s in range(S)]
        self.t_back = [[_ceil_scaled(inst.travel_time(loc[m], dep[s])) for m in range(M)] for s in range(S)]
        # requirement arithmetic in integers
        if inst.additive:
            both, _ = _integer_scale(np.concatenate([inst.species_traits.ravel(), inst.requirements.ravel()]),
                                     "traits and requirements")
            self.c = both[: S * inst.skills].reshape(S, inst.skills)
            self.q = both[S * inst.skills:].reshape(M, inst.skills)
        else:
            self.c = (inst.species_traits > 0).astype(np.int64)
            self.q = (inst.requirements > 0).astype(np.int64)
        K = inst.skills
        self.K = K
        # allowed species per task and member upper bounds
        self.ub = np.zeros((S, M), dtype=int)
        for s in range(S):
            for m in range(M):
                ks = [k for k in range(K) if self.c[s, k] > 0 and self.q[m, k] > 0]
                if not ks:
                    continue
                if inst.additive:
                    self.ub[s, m] = min(self.count[s], max(-(-int(self.q[m, k]) // int(self.c[s, k])) for k in ks))
                else:
                    self.ub[s, m] = 1
        self.useful = [[m for m in range(M) if self.ub[s, m] > 0] for s in range(S)]

    def arc(self, i: int, j: int) -> int:
        """Minimum start-to-start distance when an agent goes from task i to task j."""
        return max(1, self.dur[i] + self.t[i][j])

    def min_in(self, s: int, m: int) -> int:
        """Shortest possible travel of a species-s agent into task m (from its depot or a task)."""
        v = self.t_out[s][m]
        for i in self.useful[s]:
            if i != m:
                v = min(v, self.t[i][m])
        return v

    def slack(self) -> int:
        """Upper bound on model value - 1000 x float value along any chain (see module doc)."""
        inst = self.inst
        M = self.M
        if M == 0:
            return 0
        err = 0.0
        loc = [tuple(p) for p in inst.task_locations]
        dep = [tuple(p) for p in inst.species_depots]
        for i in range(M):
            for j in range(M):
                if i != j:
                    err = max(err, self.arc(i, j) - SCALE * (inst.durations[i] + inst.travel_time(loc[i], loc[j])))
            for s in range(self.S):
                err = max(err, self.t_out[s][i] - SCALE * inst.travel_time(dep[s], loc[i]))
                err = max(err, self.dur[i] + self.t_back[s][i]
                          - SCALE * (inst.durations[i] + inst.travel_time(loc[i], dep[s])))
        return int(math.ceil((M + 1) * err + 1e-6 * (M + 1)))


# ---------------------------------------------------------------------------------------------
# hint: integer schedule of given routes
# ---------------------------------------------------------------------------------------------
def _int_schedule(D: _Data, routes: list[list[int]]) -> tuple[list[int], int] | None:
    """Earliest integer start times of routes under the model's (rounded-up) times."""
    inst = D.inst
    A, M = inst.n_agents, D.M
    coal: list[list[int]] = [[] for _ in range(M)]
    for a, r in enumerate(routes):
        for m in r:
            coal[m].append(a)
    start = [None] * M
    ptr = [0] * A
    ready_node = [None] * A  # last task of agent a, None = depot
    left = M
    while left:
        prog = False
        for m in range(M):
            if start[m] is not None or not coal[m]:
                continue
            if all(ptr[a] < len(routes[a]) and routes[a][ptr[a]] == m for a in coal[m]):
                st = 0
                for a in coal[m]:
                    s = int(inst.agent_species[a])
                    p = ready_node[a]
                    st = max(st, D.t_out[s][m] if p is None else start[p] + D.arc(p, m))
                start[m] = st
                for a in coal[m]:
                    ready_node[a] = m
                    ptr[a] += 1
                left -= 1
                prog = True
        if not prog:
            return None
    C = 0
    for a in range(A):
        p = ready_node[a]
        if p is not None:
            C = max(C, start[p] + D.dur[p] + D.t_back[int(inst.agent_species[a])][p])
    return [int(v) for v in start], C


def _hint_valid(D: _Data, routes: list[list[int]]) -> bool:
    sp = D.inst.agent_species
    cnt = np.zeros((D.S, D.M), dtype=int)
    for a, r in enumerate(routes):
        for m in r:
            cnt[int(sp[a]), m] += 1
    return bool((cnt <= D.ub).all())


# ---------------------------------------------------------------------------------------------
# model
# ---------------------------------------------------------------------------------------------
DEFAULT_OPTS = {"workload": True, "species_cumulative": True, "skill_cumulative": True, "forced_sharing": True}


def _build(D: _Data, ub_C: int, lb_C: int, hint_routes: list[list[int]] | None, opts: dict | None = None):
    from ortools.sat.python import cp_model

    o = {**DEFAULT_OPTS, **(opts or {})}

    md = cp_model.CpModel()
    S, M = D.S, D.M
    C = md.NewIntVar(lb_C, ub_C, "C")
    start = []
    for m in range(M):
        lo = min(D.t_out[s][m] for s in range(S) if D.ub[s, m] > 0)
        hi = ub_C - D.dur[m] - min(D.t_back[s][m] for s in range(S) if D.ub[s, m] > 0)
        start.append(md.NewIntVar(lo, max(lo, hi), f"start{m}"))
    x: dict[tuple[int, int], Any] = {}
    z: dict[tuple[int, int], Any] = {}
    for s in range(S):
        for m in D.useful[s]:
            u = int(D.ub[s, m])
            if u == 1:
                x[s, m] = md.NewBoolVar(f"x{s}_{m}")
                z[s, m] = x[s, m]
            else:
                x[s, m] = md.NewIntVar(0, u, f"x{s}_{m}")
                z[s, m] = md.NewBoolVar(f"z{s}_{m}")
                md.Add(x[s, m] >= 1).OnlyEnforceIf(z[s, m])
                md.Add(x[s, m] == 0).OnlyEnforceIf(z[s, m].Not())
            md.Add(start[m] >= D.t_out[s][m]).OnlyEnforceIf(z[s, m])
            md.Add(C >= start[m] + D.dur[m] + D.t_back[s][m]).OnlyEnforceIf(z[s, m])
    # requirements
    for m in range(M):
        for k in range(D.K):
            q = int(D.q[m, k])
            if q <= 0:
                continue
            terms = [x[s, m] * int(D.c[s, k]) for s in range(S) if (s, m) in x and D.c[s, k] > 0]
            if D.inst.additive:
                md.Add(sum(terms) >= q)
            else:
                md.AddBoolOr([z[s, m] for s in range(S) if (s, m) in z and D.c[s, k] > 0])
    # flows per species; node -1 = depot
    f: dict[tuple[int, int, int], Any] = {}
    used: dict[tuple[int, int, int], Any] = {}
    users: dict[tuple[int, int], list] = {}
    for s in range(S):
        nodes = [-1] + D.useful[s]
        cap = {-1: D.count[s], **{m: int(D.ub[s, m]) for m in D.useful[s]}}
        for i in nodes:
            for j in nodes:
                if i == j:
                    continue
                hi = min(cap[i], cap[j])
                if hi == 1:
                    v = md.NewBoolVar(f"f{s}_{i}_{j}")
                    b = v
                else:
                    v = md.NewIntVar(0, hi, f"f{s}_{i}_{j}")
                    b = md.NewBoolVar(f"u{s}_{i}_{j}")
                    md.Add(v >= 1).OnlyEnforceIf(b)
                    md.Add(v == 0).OnlyEnforceIf(b.Not())
                f[s, i, j] = v
                used[s, i, j] = b
                if i >= 0 and j >= 0:
                    users.setdefault((i, j), []).append(b)
        for m in D.useful[s]:
            md.Add(sum(f[s, i, m] for i in nodes if i != m) == x[s, m])
            md.Add(sum(f[s, m, j] for j in nodes if j != m) == x[s, m])
        md.Add(sum(f[s, -1, j] for j in D.useful[s]) <= D.count[s])
        # workload: every agent's busy time (travel + work) <= C
        work = [f[s, i, j] * ((D.dur[i] if i >= 0 else 0)
                              + (D.t[i][j] if i >= 0 and j >= 0 else D.t_out[s][j] if i < 0 else D.t_back[s][i]))
                for (ss, i, j) in f if ss == s]
        if o["workload"]:
            md.Add(sum(work) <= D.count[s] * C)
        # cumulative: the species' agents are each in at most one task window at a time
        ivs, dem = [], []
        for m in D.useful[s]:
            a = D.min_in(s, m)
            ivs.append(md.NewFixedSizeIntervalVar(start[m] - a, a + D.dur[m], f"iv{s}_{m}"))
            dem.append(x[s, m])
        if ivs and o["species_cumulative"]:
            md.AddCumulative(ivs, dem, D.count[s])
    # arcs => precedence (shared by all species)
    y: dict[tuple[int, int], Any] = {}
    for (i, j), bs in users.items():
        yy = md.NewBoolVar(f"y{i}_{j}")
        y[i, j] = yy
        for b in bs:
            md.AddImplication(b, yy)
        md.AddBoolOr(bs).OnlyEnforceIf(yy)
        md.Add(start[j] >= start[i] + D.arc(i, j)).OnlyEnforceIf(yy)
    for (i, j), yy in y.items():
        if i < j and (j, i) in y:
            md.AddBoolOr([yy.Not(), y[j, i].Not()])
    # forced sharing: if x[s,i] + x[s,j] > count_s, some agent does both tasks, so (triangle
    # inequality) one of them precedes the other by its duration + the travel between them
    order: dict[tuple[int, int], Any] = {}
    share_lits: list = []
    if o["forced_sharing"]:
        for s in range(S):
            us = D.useful[s]
            for a_, i in enumerate(us):
                for j in us[a_ + 1:]:
                    if int(D.ub[s, i]) + int(D.ub[s, j]) <= D.count[s]:
                        continue
                    sh = md.NewBoolVar(f"sh{s}_{i}_{j}")
                    md.Add(x[s, i] + x[s, j] <= D.count[s]).OnlyEnforceIf(sh.Not())
                    if (i, j) not in order:
                        order[i, j] = md.NewBoolVar(f"o{i}_{j}")
                    oij = order[i, j]
                    # (-1: the triangle inequality may lose one unit to rounding up)
                    md.Add(start[j] >= start[i] + D.arc(i, j) - 1).OnlyEnforceIf([sh, oij])
                    md.Add(start[i] >= start[j] + D.arc(j, i) - 1).OnlyEnforceIf([sh, oij.Not()])
                    share_lits.append((s, i, j, sh))
        for (i, j), oij in order.items():
            if (i, j) in y:
                md.AddImplication(y[i, j], oij)
            if (j, i) in y:
                md.AddImplication(y[j, i], oij.Not())
    # per-skill cumulative with constant demand (capacity = team total of the skill)
    for k in range(D.K):
        capk = sum(int(D.c[s, k]) * D.count[s] for s in range(S))
        ivs, dem = [], []
        for m in range(M):
            if D.q[m, k] <= 0:
                continue
            sk = [s for s in range(S) if D.c[s, k] > 0 and D.ub[s, m] > 0]
            a = min(D.min_in(s, m) for s in sk)
            ivs.append(md.NewFixedSizeIntervalVar(start[m] - a, a + D.dur[m], f"ivk{k}_{m}"))
            dem.append(int(D.q[m, k]))
        if ivs and sum(dem) > capk and o["skill_cumulative"]:
            md.AddCumulative(ivs, dem, capk)
    md.Minimize(C)

    # hint
    if hint_routes is not None:
        sched = _int_schedule(D, hint_routes)
        assert sched is not None
        st, Ch = sched
        sp = D.inst.agent_species
        cnt: dict[tuple[int, int], int] = {}
        fl: dict[tuple[int, int, int], int] = {}
        for a, r in enumerate(hint_routes):
            s = int(sp[a])
            if not r:
                continue
            seq = [-1] + list(r) + [-1]
            for i, j in zip(seq, seq[1:]):
                fl[s, i, j] = fl.get((s, i, j), 0) + 1
            for m in r:
                cnt[s, m] = cnt.get((s, m), 0) + 1
        md.AddHint(C, Ch)
        for m in range(M):
            md.AddHint(start[m], st[m])
        for key, v in x.items():
            n = cnt.get(key, 0)
            if v is not z[key]:
                md.AddHint(v, n)
            md.AddHint(z[key], 1 if n else 0)
        for key, v in f.items():
            n = fl.get(key, 0)
            md.AddHint(v, n)
            if used[key] is not v:
                md.AddHint(used[key], 1 if n else 0)
        yh = {(i, j) for (s, i, j), n in fl.items() if n and i >= 0 and j >= 0}
        for key, v in y.items():
            md.AddHint(v, 1 if key in yh else 0)
        for (s_, i, j, sh) in share_lits:
            md.AddHint(sh, 1 if cnt.get((s_, i), 0) + cnt.get((s_, j), 0) > D.count[s_] else 0)
        for (i, j), oij in order.items():
            md.AddHint(oij, 1 if st[i] < st[j] or (st[i] == st[j] and i < j) else 0)
    return md, C, start, f


def _extract(D: _Data, solver, start, f) -> list[list[int]]:
    """Decompose each species' (acyclic) flow into one depot-to-depot path per agent."""
    st = [solver.Value(v) for v in start]
    routes: list[list[int]] = []
    for s in range(D.S):
        rem = {(i, j): solver.Value(v) for (ss, i, j), v in f.items() if ss == s}
        for k in range(D.count[s]):
            path: list[int] = []
            node = -1
            while True:
                nxt = [j for (i, j), v in rem.items() if i == node and v > 0]
                if not nxt:
                    break
                j = min(nxt, key=lambda j: (st[j] if j >= 0 else math.inf, j))
                rem[node, j] -= 1
                if j < 0:
                    break
                path.append(j)
                node = j
            routes.append(path)
        assert all(v == 0 for v in rem.values()), "flow decomposition left flow"
    return routes


# ---------------------------------------------------------------------------------------------
# method
# ---------------------------------------------------------------------------------------------
MAX_ARCS = 60_000  # larger models are not built (all the time goes to the heuristic)
LOG_SEARCH = False  # CP-SAT's own search log on stdout (for debugging the model)


def _warm(inst: Instance, warm_start: str | None, seed: int) -> Solution | None:
    from ..methods import solve

    if warm_start in (None, "", "none"):
        return None
    if warm_start == "greedy":
        return solve(inst, "greedy", seed)
    if warm_start == "rl":
        try:
            return solve(inst, "rl", seed)
        except Exception as e:  # the learned policy may be missing (no checkpoint / torch)
            raise MethodError(f"cpsat: --warm-start rl needs the learned policy, which failed: {e}") from None
    raise MethodError(f"cpsat: unknown warm start {warm_start!r} (expected greedy or rl)")


def _reeval(inst: Instance, sol: Solution | None, seed: int) -> Solution | None:
    if sol is None or not sol.success:
        return None
    try:
        return evaluate_routes(inst, [list(r) for r in sol.routes], "cpsat", seed)
    except Exception:
        return None


def _ProgressCallback(report: Callable[[str], None]):
    """A CP-SAT solution callback reporting every improving solution of the scaled model."""
    from ortools.sat.python import cp_model

    class _CB(cp_model.CpSolverSolutionCallback):
        def on_solution_callback(self) -> None:
            obj, bound = self.ObjectiveValue() / SCALE, self.BestObjectiveBound() / SCALE
            report(f"CP-SAT solution {obj:.3f}, model bound {bound:.3f}")

    return _CB()


def _interruptible_solve(solver, model, callback, keep: bool = False) -> tuple[Any, bool]:
    """(``solver.Solve(model, callback)`` run in a worker thread so that a Ctrl-C reaches the
    caller, whether it was interrupted).

    CP-SAT's own SIGINT handler ends the search and returns the incumbent as if the time limit
    had passed: the caller could not tell a cut-short solve from a finished one. Here the solver
    leaves SIGINT alone; the calling thread waits, and on KeyboardInterrupt stops the search, waits
    for the worker (it stops within ~0.2 s) and re-raises, or (``keep``) returns the status of
    the stopped search."""
    import threading

    solver.parameters.catch_sigint_signal = False
    done, out = threading.Event(), {}

    def work() -> None:
        try:
            out["code"] = solver.Solve(model, callback)
        except BaseException as e:  # noqa: BLE001 - handed to the caller below
            out["error"] = e
        finally:
            done.set()

    threading.Thread(target=work, name="cpsat", daemon=True).start()
    try:
        while not done.wait(0.1):  # an Event, not Thread.join: an interrupted join can lose the thread
            pass
    except KeyboardInterrupt:
        # again and again: a stop asked before the worker's Solve has begun (a loaded machine) is lost
        deadline = time.monotonic() + 30.0
        while True:
            solver.StopSearch()
            if done.wait(0.1) or time.monotonic() > deadline:
                break
        if not done.is_set() or not keep or "code" not in out:
            raise
        return out["code"], True
    if "error" in out:
        raise out["error"]
    return out["code"], False


def solve_cpsat(inst: Instance, seed: int = 0, time_limit: float = 60.0, warm_start: str | None = None,
                workers: int = 2, heuristic_seconds: float | None = None,
                progress: Callable[..., None] | None = None) -> Solution:
    """Anytime CP-SAT solve; see the module docstring. ``progress(done, total, unit, note)``, if
    given, is called with the seconds spent out of the time limit (unit "s") at every phase and
    every improving CP-SAT solution, the note naming the best makespan so far."""
    from ortools.sat.python import cp_model

    from ..bounds import lower_bounds
    from ..methods import keeping_best, solve

    t0 = time.perf_counter()
    time_limit = 60.0 if time_limit is None else time_limit
    workers = 2 if workers is None else workers
    if not isinstance(time_limit, (int, float)) or time_limit <= 0:
        raise MethodError(f"cpsat: time_limit must be positive, got {time_limit!r}")
    if int(workers) < 1:
        raise MethodError(f"cpsat: workers must be >= 1, got {workers!r}")
    cheap = lower_bounds(inst)["best"]
    if inst.n_tasks == 0:
        sol = evaluate_routes(inst, [[] for _ in range(inst.n_agents)], "cpsat", seed)
        sol.extra.update(status="optimal", lower_bound=0.0, objective=0.0)
        sol.compute_seconds = time.perf_counter() - t0
        return sol
    D = _Data(inst)
    # incumbents: warm start (what we must never be worse than), greedy, list scheduler
    warm = _warm(inst, warm_start, seed)
    warm_eval = _reeval(inst, warm, seed)
    cands = [c for c in (warm_eval, _reeval(inst, solve(inst, "greedy", seed), seed)) if c is not None]
    n_arcs = sum((len(u) + 1) ** 2 for u in D.useful)
    too_big = n_arcs > MAX_ARCS  # then no model: all the time goes to the heuristic
    hs = heuristic_seconds if heuristic_seconds is not None else 0.25 * time_limit
    if too_big:
        hs = max(0.0, time_limit - (time.perf_counter() - t0) - 0.5)
    best0 = min(cands, key=lambda c: c.makespan) if cands else None

    def report(note: str) -> None:
        if progress is not None:
            progress(time.perf_counter() - t0, float(time_limit), "s", note)

    report("heuristic" + (f", best {best0.makespan:.3f}" if best0 is not None else ""))
    interrupted = False
    hint_sol, hint_routes, hint_C = None, None, None
    try:  # a Ctrl-C from here up to the search keeps the heuristic's best (keep_best_on_interrupt)
        ls = best_list_schedule(inst, seed, min(1.0, 0.1 * hs), incumbent=best0)
        if ls is not None:
            cands.append(ls)
            left = hs - (time.perf_counter() - t0)
            if left > 0:
                _, order = parallel_anneal(inst, order_of(ls), seed, left, int(workers), target=cheap)
                _, r = SerialDecoder(inst).decode(order, routes_out=True)
                cands.append(evaluate_routes(inst, r, "cpsat", seed))
        # model hint: the best candidate, pruned to minimal coalitions
        for c in sorted(cands, key=lambda c: c.makespan):
            r = prune_routes(inst, c.routes)
            if not _hint_valid(D, r):
                continue
            sch = _int_schedule(D, r)
            if sch is None:
                continue
            if hint_C is None or sch[1] < hint_C:
                hint_sol, hint_routes, hint_C = evaluate_routes(inst, r, "cpsat", seed), r, sch[1]
        if hint_C is None:  # no usable hint: a trivial horizon (all tasks one after another by everyone)
            hint_C = sum(D.dur) + sum(max(max(D.t_out[s]) for s in range(D.S)) for _ in range(D.M + 1)) * 2 + 10
        if not too_big:
            lb_C = min(max(0, int(math.floor(cheap * SCALE * (1 - 1e-12)))), hint_C)
            md, Cv, start, f = _build(D, hint_C, lb_C, hint_routes)
    except KeyboardInterrupt:
        if not (keeping_best() and cands):
            raise
        interrupted = True  # no search: the best so far, as for a model too large to build
    if too_big or interrupted:  # too large to build, or stopped: the heuristic's solution, cheap bounds only
        best = min(cands, key=lambda c: c.makespan)
        out = evaluate_routes(inst, [list(r) for r in best.routes], "cpsat", seed)
        out.compute_seconds = time.perf_counter() - t0
        note = ("interrupted before the CP-SAT search: the heuristic's best solution so far" if interrupted else
                f"model not built: {n_arcs} arcs > MAX_ARCS={MAX_ARCS}; heuristic solution")
        if interrupted:
            out.extra["interrupted"] = True
        out.extra.update({"status": "none", "lower_bound": float(cheap), "objective": None,
                          "note": note,
                          "time_limit": float(time_limit), "workers": int(workers),
                          "warm_start": warm_start,
                          "warm_start_makespan": None if warm_eval is None else float(warm_eval.makespan),
                          "hint_makespan": float(best.makespan), "source": "heuristic"})
        return out
    solver = cp_model.CpSolver()
    remaining = max(0.05, time_limit - (time.perf_counter() - t0))
    solver.parameters.max_time_in_seconds = remaining
    solver.parameters.num_workers = int(workers)
    solver.parameters.random_seed = int(seed)
    solver.parameters.log_search_progress = LOG_SEARCH
    report(f"CP-SAT, best {min(c.makespan for c in cands):.3f}" if cands else "CP-SAT")
    t1 = time.perf_counter()
    code, interrupted = _interruptible_solve(solver, md, _ProgressCallback(report) if progress is not None else None,
                                             keep=keeping_best())
    solve_wall = time.perf_counter() - t1
    status = {cp_model.OPTIMAL: "optimal", cp_model.FEASIBLE: "feasible"}.get(code, "none")
    slack = D.slack()
    model_sol = None
    objective = None
    if status != "none":
        objective = solver.ObjectiveValue() / SCALE
        routes = _extract(D, solver, start, f)
        model_sol = evaluate_routes(inst, routes, "cpsat", seed)
        bound_int = solver.BestObjectiveBound()
    else:
        bound_int = lb_C  # no solution in time: claim nothing beyond the cheap bound
    solver_lb = (bound_int - slack) / SCALE
    pool = [c for c in (model_sol, hint_sol, warm_eval) if c is not None] + cands
    best = min(pool, key=lambda c: c.makespan)
    if model_sol is not None and model_sol.makespan <= best.makespan:
        best = model_sol
    out = evaluate_routes(inst, [list(r) for r in best.routes], "cpsat", seed)
    out.compute_seconds = time.perf_counter() - t0
    lb = max(cheap, solver_lb)
    report(f"{status}, makespan {out.makespan:.3f}, bound {lb:.3f}")
    out.extra.update({
        "status": status,
        "lower_bound": float(lb),
        "gap": float((out.makespan - lb) / out.makespan) if out.makespan > 0 else 0.0,
        "objective": objective,
        "model_bound": bound_int / SCALE,
        "time_scale": SCALE,
        "rounding_slack": slack / SCALE,
        "time_limit": float(time_limit),
        "workers": int(workers),
        "solver_seconds": round(solve_wall, 3),
        "warm_start": warm_start,
        "warm_start_makespan": None if warm_eval is None else float(warm_eval.makespan),
        "hint_makespan": None if hint_sol is None else float(hint_sol.makespan),
        "source": "model" if best is model_sol else "heuristic",
    })
    if interrupted:  # stopped by a Ctrl-C: the best so far, the bound proven by then
        out.extra["interrupted"] = True
    return out

