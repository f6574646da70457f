"""A randomised greedy list scheduler (construction heuristic) and coalition pruning.

Used by the CP-SAT solver to build a complete, feasible hint and an incumbent upper bound.

One construction: every agent has a ready time and a position (depot or last task). Repeatedly,
for every unscheduled task m compute the earliest time ``T*_m`` at which a satisfying coalition can
be assembled there (agents sorted by arrival ``ready + travel``; ``T*_m`` is the arrival of the first
agent at which the agents arrived so far satisfy m); pick a task with (noisily) small ``T*_m``,
take the agents that arrived by then, prune members that are not needed (latest arrivals first),
and commit them: they start at ``T*_m`` and are next ready at its finish. Agents finally return
to their depots. The routes are re-evaluated by :func:`hmrta.solution.evaluate_routes`.

Pruning (:func:`prune_routes`): removing an agent from a coalition that stays satisfied never
makes any time later (Euclidean travel obeys the triangle inequality and a task starts at the
latest arrival of fewer members), so minimal coalitions dominate.
"""
from __future__ import annotations

import math
import random
import time

import numpy as np

from ..instance import Instance
from ..solution import Solution, evaluate_routes, satisfies


def capability(inst: Instance) -> tuple[np.ndarray, np.ndarray]:
    """(per agent capability [A,K], per task requirement [M,K]) in requirement arithmetic:
    AT uses traits and requirements, the requirements less the mission's cover tolerance (a sum
    that falls short by no more is met, as in the state machine:
    :func:`hmrta.instance.cover_tolerance`); BT uses 0/1 skill coverage."""
    if inst.additive:
        return np.asarray(inst.traits, dtype=np.float64), np.asarray(inst.requirements, dtype=np.float64) - inst.cover_tol
    return (np.asarray(inst.traits) > 0).astype(np.float64), (np.asarray(inst.requirements) > 0).astype(np.float64)


def travel_matrix(inst: Instance) -> np.ndarray:
    """[S + M, S + M] travel times between nodes: species depots first, then tasks.
    Entries are computed with ``inst.travel_time`` (bit-identical to route evaluation)."""
    pts = [tuple(p) for p in inst.species_depots] + [tuple(p) for p in inst.task_locations]
    n = len(pts)
    T = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            if i != j:
                T[i, j] = inst.travel_time(pts[i], pts[j])
    return T


def prune_routes(inst: Instance, routes: list[list[int]]) -> list[list[int]]:
    """Drop members whose removal keeps their task's coalition satisfied (latest-evaluated
    arrivals first). Returns new routes; never worse under evaluate_routes."""
    M = inst.n_tasks
    if M == 0:
        return [list(r) for r in routes]
    try:
        sol = evaluate_routes(inst, routes)
    except Exception:
        return [list(r) for r in routes]
    # arrival of agent a at task m under the evaluated schedule (to remove latest arrivals first)
    arrival: dict[tuple[int, int], float] = {}
    T = travel_matrix(inst)
    S = inst.n_species
    for a, r in enumerate(routes):
        prev, t = int(inst.agent_species[a]), 0.0
        for m in r:
            arrival[(a, m)] = t + T[prev, S + m]
            t = sol.tasks[m]["finish"]
            prev = S + m
    coal = [list(sol.tasks[m]["members"]) for m in range(M)]
    drop: set[tuple[int, int]] = set()
    for m in range(M):
        members = sorted(coal[m], key=lambda a: -arrival[(a, m)])
        keep = list(coal[m])
        for a in members:
            trial = [b for b in keep if b != a]
            if trial and not satisfies(inst, trial, m):
                keep = trial
                drop.add((a, m))
    return [[m for m in r if (a, m) not in drop] for a, r in enumerate(routes)]


class ListScheduler:
    """Randomised earliest-start list scheduling. ``construct(rng, noise)`` returns routes."""

    def __init__(self, inst: Instance):
        self.inst = inst
        self.cap, self.req = capability(inst)  # [A,K], [M,K]
        self.T = travel_matrix(inst)  # [S+M, S+M]
        self.S, self.M, self.A = inst.n_species, inst.n_tasks, inst.n_agents
        self.home = np.asarray(inst.agent_species, dtype=np.int64)  # [A] node index of each depot
        self.dur = np.asarray(inst.durations, dtype=np.float64)

    def construct(self, rng: random.Random, noise: float = 0.0, finish_weight: float = 0.0) -> list[list[int]]:
        A, M, S = self.A, self.M, self.S
        ready = np.zeros(A)
        pos = self.home.copy()  # [A] node index
        todo = np.ones(M, dtype=bool)
        routes: list[list[int]] = [[] for _ in range(A)]
        req, cap = self.req, self.cap
        for _ in range(M):
            cand = np.flatnonzero(todo)
            arr = ready[:, None] + self.T[pos][:, S + cand]  # [A, C]
            if noise > 0:  # jitter the arrival order (ties / near ties) a little
                arr_key = arr + noise * np.asarray([rng.random() for _ in range(arr.size)]).reshape(arr.shape)
            else:
                arr_key = arr
            order = np.argsort(arr_key, axis=0, kind="stable")  # [A, C]
            cum = np.cumsum(cap[order], axis=0)  # [A, C, K]
            ok = (cum >= req[cand][None]).all(-1)  # [A, C]
            first = ok.argmax(0)  # [C]  (feasible instance: some prefix satisfies)
            sorted_arr = np.maximum.accumulate(np.take_along_axis(arr, order, 0), axis=0)  # [A, C]
            tstar = sorted_arr[first, np.arange(len(cand))]  # [C] earliest start of each task
            score = tstar + finish_weight * self.dur[cand]
            if noise > 0:
                score = score * (1.0 + noise * np.asarray([rng.random() for _ in cand]))
            c = int(np.argmin(score))
            m = int(cand[c])
            members = list(order[: first[c] + 1, c])
            # prune: latest arrivals first, keep satisfied
            members.sort(key=lambda a: -arr[a, c])
            keep = list(members)
            for a in members:
                trial = [b for b in keep if b != a]
                if trial and (cap[trial].sum(0) >= req[m]).all():
                    keep = trial
            start = max(arr[a, c] for a in keep)
            for a in keep:
                ready[a] = start + self.dur[m]
                pos[a] = S + m
                routes[a].append(m)
            todo[m] = False
        return routes


def best_list_schedule(inst: Instance, seed: int = 0, seconds: float = 1.0, max_iters: int = 100000,
                       incumbent: Solution | None = None) -> Solution | None:
    """Run randomised constructions for ``seconds`` (at least one deterministic one), keep the best
    re-evaluated solution (or ``incumbent`` if none is better)."""
    if inst.n_tasks == 0:
        return incumbent
    ls = ListScheduler(inst)
    rng = random.Random(seed)
    best = incumbent
    t0 = time.perf_counter()
    it = 0
    while it < max_iters:
        if it == 0:
            noise, fw = 0.0, 0.0
        elif it == 1:
            noise, fw = 0.0, 1.0
        else:
            noise, fw = rng.choice((0.02, 0.05, 0.1, 0.2, 0.3)), rng.choice((0.0, 0.0, 0.5, 1.0))
        routes = ls.construct(rng, noise, fw)
        sol = evaluate_routes(inst, routes, "list", seed)
        if best is None or sol.makespan < best.makespan - 1e-12:
            best = sol
        it += 1
        if time.perf_counter() - t0 >= seconds:
            break
    return best


# ---------------------------------------------------------------------------------------------
# serial schedule generation from a task order + simulated annealing over orders
# ---------------------------------------------------------------------------------------------
def prune_latest(members: list, have: list, need: list, ks: list, cap: list) -> list:
    """``members`` ((arrival, robot) by arrival) without those whose capability is not needed to
    cover ``need`` on skills ``ks``, latest arrivals first (``have``, their total, is updated)."""
    for i in range(len(members) - 1, -1, -1):
        ca = cap[members[i][1]]
        if all(have[k] - ca[k] >= need[k] for k in ks):
            for k in ks:
                have[k] -= ca[k]
            members[i] = None
    return [x for x in members if x is not None]


class SerialDecoder:
    """Decode a task order: each task in turn gets the earliest-assembling coalition (agents sorted
    by arrival, smallest satisfying prefix, then unnecessary members pruned, latest first) and
    starts at its latest member's arrival. Times follow route-evaluation semantics exactly."""

    def __init__(self, inst: Instance):
        self.inst = inst
        cap, req = capability(inst)
        self.S, self.M, self.A = inst.n_species, inst.n_tasks, inst.n_agents
        self.K = inst.skills
        T = travel_matrix(inst)
        self.Tl = T.tolist()
        self.home = [int(s) for s in inst.agent_species]
        self.dur = [float(d) for d in inst.durations]
        self.cap = cap.tolist()
        self.req = req.tolist()
        # only agents that contribute a needed skill are candidates for a task
        self.cand = [[a for a in range(self.A) if any(cap[a, k] > 0 and req[m, k] > 0 for k in range(self.K))]
                     for m in range(self.M)]
        self.needk = [[k for k in range(self.K) if req[m, k] > 0] for m in range(self.M)]

    def decode(self, order, routes_out: bool = False):
        """Makespan of the order (and the routes with ``routes_out``)."""
        ms, _, routes = self.run(order, 0, None, record=False, routes_out=routes_out)
        return (ms, routes) if routes_out else ms

    def run(self, order, p: int, snap, record: bool = True, routes_out: bool = False):
        """Decode ``order[p:]`` from ``snap`` = (ready, pos) before position p (None: the start).
        Returns (makespan, snapshots before each position p.. if ``record``, routes or None)."""
        S, Tl, cap, dur, K = self.S, self.Tl, self.cap, self.dur, self.K
        if snap is None:
            ready, pos = [0.0] * self.A, list(self.home)
        else:
            ready, pos = list(snap[0]), list(snap[1])
        snaps = [] if record else None
        routes = [[] for _ in range(self.A)] if routes_out else None
        for idx in range(p, len(order)):
            if record:
                snaps.append((ready[:], pos[:]))
            m = order[idx]
            col = S + m
            req = self.req[m]
            ks = self.needk[m]
            arr = sorted([(ready[a] + Tl[pos[a]][col], a) for a in self.cand[m]])
            have = [0.0] * K
            members = []
            for t, a in arr:
                members.append((t, a))
                ca = cap[a]
                for k in ks:
                    have[k] += ca[k]
                if all(have[k] >= req[k] for k in ks):
                    break
            if len(members) > 1:
                members = prune_latest(members, have, req, ks, cap)
            fin = max(t for t, _ in members) + dur[m]
            for _, a in members:
                ready[a] = fin
                pos[a] = col
                if routes_out:
                    routes[a].append(m)
        ms = 0.0
        home = self.home
        for a in range(self.A):
            v = ready[a] + Tl[pos[a]][home[a]]
            if v > ms:
                ms = v
        return ms, snaps, routes


def order_of(sol: Solution) -> list[int]:
    """Tasks sorted by start time (a serial order that reproduces the schedule's sequence)."""
    return sorted(range(len(sol.tasks)), key=lambda m: (sol.tasks[m]["start"], m))


def anneal(inst: Instance, order: list[int], seed: int = 0, seconds: float = 1.0,
           max_evals: int = 10**9, patience: int | None = None, target: float = 0.0,
           t0_frac: float = 0.02, cycles: int = 2, decoder=None) -> tuple[float, list[int]]:
    """Simulated annealing over task orders with the serial decoder (insert / swap moves; only
    the suffix after the first changed position is re-decoded). ``decoder``: another decoder with
    :meth:`SerialDecoder.run`'s protocol (:class:`hmrta.solvers.fromstate.StateDecoder` plans
    from a mid-mission state); an order it cannot decode has an infinite makespan. ``cycles`` equal cooling cycles
    (linear cooling from ``t0_frac`` x makespan, halved each cycle), each restarting from the best
    order so far. Stops after ``seconds``, ``max_evals`` decodes, ``patience`` decodes without
    improvement (default max(20000, 2000 x tasks)), or on reaching ``target`` (a lower bound).
    Returns (best makespan, best order)."""
    dec = SerialDecoder(inst) if decoder is None else decoder
    rng = random.Random(seed)
    M = len(order)
    best_v, _, _ = dec.run(order, 0, None, record=False)
    best = list(order)
    if M < 2:
        return best_v, best
    patience = patience if patience is not None else max(20000, 2000 * M)
    t_start = time.perf_counter()
    n = last = 0
    for c in range(cycles):
        cur = list(best)
        cur_v, snaps, _ = dec.run(cur, 0, None)
        T0 = t0_frac * cur_v * 0.5**c
        c_t0, c_n0 = time.perf_counter(), n
        c_sec = (seconds - (c_t0 - t_start)) / (cycles - c)
        c_evals = (max_evals - n) // (cycles - c)
        while n - c_n0 < c_evals and n - last < patience and best_v > target + 1e-9:
            el = time.perf_counter() - c_t0
            if el >= c_sec:
                break
            temp = T0 * (1.0 - max(el / c_sec, (n - c_n0) / c_evals)) + 1e-9
            for _ in range(50):
                cand = list(cur)
                i, j = rng.randrange(M), rng.randrange(M)
                if i == j:
                    continue
                if rng.random() < 0.5:
                    cand.insert(j, cand.pop(i))
                else:
                    cand[i], cand[j] = cand[j], cand[i]
                p = min(i, j)
                v, tail, _ = dec.run(cand, p, snaps[p])
                n += 1
                if v <= cur_v or rng.random() < math.exp((cur_v - v) / temp):
                    cur, cur_v = cand, v
                    snaps = snaps[:p] + tail
                    if v < best_v - 1e-12:
                        best_v, best, last = v, list(cand), n
    return best_v, best


def _anneal_child(conn, inst, order, seed, seconds, target) -> None:  # pragma: no cover - subprocess
    try:
        conn.send(anneal(inst, order, seed, seconds, target=target))
    except BaseException as e:  # report, never hang the parent
        try:
            conn.send(repr(e))
        except Exception:
            pass
    finally:
        conn.close()


def parallel_anneal(inst: Instance, order: list[int], seed: int, seconds: float, workers: int = 1,
                    target: float = 0.0) -> tuple[float, list[int]]:
    """``workers`` independent annealing runs (different seeds) at once: the calling process runs
    one, ``workers - 1`` forked processes run the others; the best order wins. Uses the ``fork``
    start method only (``spawn`` would re-run the caller's main script); where it is unavailable,
    or a process fails or does not answer in time, only the local run counts."""
    import multiprocessing as mp

    procs = []
    if workers > 1 and seconds >= 1.0 and "fork" in mp.get_all_start_methods():
        try:
            ctx = mp.get_context("fork")
            for w in range(1, workers):
                rx, tx = ctx.Pipe(duplex=False)
                p = ctx.Process(target=_anneal_child, args=(tx, inst, list(order), seed + 7919 * w,
                                                            seconds, target), daemon=True)
                p.start()
                tx.close()
                procs.append((p, rx))
        except Exception:
            for p, rx in procs:
                p.terminate()
            procs = []
    try:
        best = anneal(inst, order, seed, seconds, target=target)
    except BaseException:  # e.g. a Ctrl-C: the other runs end with this one
        for p, rx in procs:
            p.terminate()
            p.join(timeout=0.5)
            rx.close()
        raise
    deadline = time.perf_counter() + 2.0
    for p, rx in procs:
        try:
            if rx.poll(max(0.01, deadline - time.perf_counter())):
                r = rx.recv()
                if isinstance(r, tuple) and r[0] < best[0]:
                    best = r
        except (EOFError, OSError):
            pass
        finally:
            rx.close()
            p.join(timeout=0.5)
            if p.is_alive():
                p.terminate()
                p.join(timeout=0.5)
    return best
