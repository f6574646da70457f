"""Cheap lower bounds on the optimal makespan (``hmrta bound``).

Every bound is valid for the optimum of the problem of SPEC §1: some optimal solution uses only
*minimal* coalitions (removing a member whose skills are not needed never makes anything later,
because travel obeys the triangle inequality and a task starts at the latest arrival), so the
bounds may assume that every member of a coalition contributes a needed skill. Definitions:

* ``rt[s,m]`` = travel depot_s -> m -> depot_s (round trip);
* ``in[s,m]`` = the shortest travel a species-s agent can make into task m: from its depot or from
  another task where species s can contribute.

Bounds (all in time units):

``task_round_trip``
    For each task m and required skill k, the coalition must hold ``q[m,k]`` of skill k (AT; BT:
    one agent with skill k). Sorting the species having skill k by round trip, ``r[m,k]`` is the
    smallest round trip at which the species so far (at full count) hold enough of it; some member
    has at least that round trip, and it travels out, works the whole duration, and travels home:
    ``C >= max_k r[m,k] + dur[m]``. The bound is the max over tasks.
``team_workload``
    Every agent's busy time (travel into each of its tasks + their durations) fits in ``[0, C]``.
    Task m costs at least ``w[m] = min over satisfying coalitions of sum_members (dur[m] + in[s,m])``
    (exact enumeration of member counts per species; a fractional relaxation when that would be too
    large). ``C >= sum_m w[m] / agents``.
``skill_workload``
    The same with skill capacity: agents weighted by their amount of skill k are busy for at least
    ``sum_m q[m,k] (dur[m] + min_{s with k} in[s,m])`` in total, and hold ``cap_k`` (team total of
    skill k) at a time: ``C >= that / cap_k``. BT counts agents having the skill and tasks needing it.
``species_workload``
    Species s must send at least ``need[s,m]`` members to task m, the number still missing when
    every other species comes at full count. ``C >= sum_m need[s,m] (dur[m] + in[s,m]) / count_s``.
``release``
    A task released at ``r[m] > 0`` (``release`` in the mission file) cannot start before it (no
    robot sets off for it earlier; one may be at the spot already), is worked ``dur[m]``, and its
    members then go home: ``C >= r[m] + dur[m] + min_s back[s,m]`` over the species that can
    contribute. 0 when every task is known at 0.
``best``
    The maximum of the above (``best_name`` names it).

The CP-SAT solver reports its own proven bound in its solution's ``lower_bound``.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from .instance import Instance

BOUND_FORMAT = "hmrta-bound/1"  # hmrta bound --json (docs/schemas/hmrta-bound-1.schema.json)
BOUND_DOCS = {
    "task_round_trip": "per task: farthest needed depot round trip + duration (max over tasks)",
    "team_workload": "total minimum busy time (in-travel + work) of all coalitions / agents",
    "skill_workload": "per skill: skill-weighted busy time / team capacity of the skill (max over skills)",
    "species_workload": "per species: busy time of its unavoidable members / its count (max over species)",
    "release": "per task released later: release + duration + shortest way home (max over tasks)",
}

_ENUM_LIMIT = 20000


def _data(inst: Instance):
    S, M = inst.n_species, inst.n_tasks
    if inst.additive:  # (requirements less the cover tolerance: what the state machine takes as met)
        c = np.asarray(inst.species_traits, dtype=np.float64)  # [S, K]
        q = np.asarray(inst.requirements, dtype=np.float64)  # [M, K]
        q = np.where(q > 0, np.maximum(q - inst.cover_tol, 1e-300), 0.0)  # a need stays a need
    else:
        c = (np.asarray(inst.species_traits) > 0).astype(np.float64)
        q = (np.asarray(inst.requirements) > 0).astype(np.float64)
    n = np.array([s.count for s in inst.species], dtype=np.float64)  # [S]
    loc = [tuple(p) for p in inst.task_locations]
    dep = [tuple(p) for p in inst.species_depots]
    t_out = np.array([[inst.travel_time(dep[s], loc[m]) for m in range(M)] for s in range(S)]).reshape(S, M)
    t_back = np.array([[inst.travel_time(loc[m], dep[s]) for m in range(M)] for s in range(S)]).reshape(S, M)
    useful = (c[:, None, :] > 0) & (q[None, :, :] > 0)  # [S, M, K]
    useful_sm = useful.any(-1)  # [S, M]
    tt = np.array([[inst.travel_time(loc[i], loc[j]) for j in range(M)] for i in range(M)]).reshape(M, M)
    t_in = t_out.copy()  # [S, M]
    for s in range(S):
        for m in range(M):
            for i in range(M):
                if i != m and useful_sm[s, i]:
                    t_in[s, m] = min(t_in[s, m], tt[i, m])
    return c, q, n, t_out, t_back, useful_sm, t_in


def _min_coalition_cost(c: np.ndarray, q: np.ndarray, n: np.ndarray, cost: np.ndarray, ok: np.ndarray) -> float:
    """min sum_s x_s cost_s s.t. sum_s x_s c_s >= q, 0 <= x_s <= n_s integer, x_s = 0 if not ok_s."""
    S = len(n)
    ub = []
    for s in range(S):
        if not ok[s]:
            ub.append(0)
            continue
        ks = [k for k in range(len(q)) if q[k] > 0 and c[s, k] > 0]
        ub.append(int(min(n[s], max(math.ceil(q[k] / c[s, k] - 1e-12) for k in ks))))
    if math.prod(u + 1 for u in ub) <= _ENUM_LIMIT:
        best = math.inf
        for x in itertools.product(*[range(u + 1) for u in ub]):
            xv = np.asarray(x, dtype=np.float64)
            if (xv @ c >= q - 1e-12).all():
                best = min(best, float(xv @ cost))
        return best
    # fractional relaxation per skill (valid lower bound)
    lb = 0.0
    for k in range(len(q)):
        if q[k] > 0:
            ratios = [cost[s] / c[s, k] for s in range(S) if ok[s] and c[s, k] > 0]
            lb = max(lb, q[k] * min(ratios))
    return lb


def lower_bounds(inst: Instance) -> dict:
    """Cheap lower bounds on the optimal makespan (see the module docstring)."""
    S, M, K = inst.n_species, inst.n_tasks, inst.skills
    out = {"task_round_trip": 0.0, "team_workload": 0.0, "skill_workload": 0.0, "species_workload": 0.0,
           "release": 0.0}
    if M == 0:
        out.update(best=0.0, best_name="task_round_trip")
        return out
    c, q, n, t_out, t_back, useful, t_in = _data(inst)
    dur = np.asarray(inst.durations, dtype=np.float64)
    # task round trip
    rt = []
    for m in range(M):
        worst = 0.0
        for k in range(K):
            if q[m, k] <= 0:
                continue
            sp = sorted((s for s in range(S) if c[s, k] > 0), key=lambda s: t_out[s, m] + t_back[s, m])
            have = 0.0
            for s in sp:
                have += n[s] * c[s, k]
                if have >= q[m, k] - 1e-12:
                    # same float order as route evaluation: (out + duration) + back
                    worst = max(worst, (t_out[s, m] + dur[m]) + t_back[s, m])
                    break
        rt.append(worst)
    out["task_round_trip"] = float(max(rt))
    # team workload
    A = float(n.sum())
    total = 0.0
    for m in range(M):
        total += _min_coalition_cost(c, q[m], n, dur[m] + t_in[:, m], useful[:, m])
    out["team_workload"] = float(total / A)
    # skill workload
    sk = 0.0
    for k in range(K):
        cap = float((n * c[:, k]).sum())
        if cap <= 0:
            continue
        work = 0.0
        for m in range(M):
            if q[m, k] > 0:
                ins = [t_in[s, m] for s in range(S) if c[s, k] > 0 and useful[s, m]]
                work += q[m, k] * (dur[m] + min(ins))
        sk = max(sk, work / cap)
    out["skill_workload"] = float(sk)
    # species workload
    spw = 0.0
    for s in range(S):
        others = (n[:, None] * c).sum(0) - n[s] * c[s]  # [K]
        work = 0.0
        for m in range(M):
            need = 0
            for k in range(K):
                miss = q[m, k] - others[k]
                if miss > 1e-12 and c[s, k] > 0:
                    need = max(need, math.ceil(miss / c[s, k] - 1e-12))
            work += need * (dur[m] + t_in[s, m])
        spw = max(spw, work / n[s])
    out["species_workload"] = float(spw)
    # release times
    rel = np.asarray(inst.releases, dtype=np.float64)  # [M]
    for m in np.flatnonzero(rel > 0):
        ok = useful[:, m]  # [S] species that can contribute
        if ok.any():
            out["release"] = max(out["release"], float((rel[m] + dur[m]) + t_back[ok, m].min()))
    name = max(BOUND_DOCS, key=lambda k: out[k])
    out["best"] = out[name]
    out["best_name"] = name
    return out


def bound_report(inst: Instance, solutions: list | None = None) -> dict:
    """Cheap bounds plus, for given solutions, their makespans, the solver bounds they carry
    (``extra['lower_bound']``, e.g. from cpsat) and each one's gap to the best bound.

    Returns ``{"format": "hmrta-bound/1", "instance", "bounds": {name: value}, "best", "best_name", "solutions": [{"method",
    "makespan", "lower_bound", "status", "gap"}]}``; ``gap = (makespan - best) / makespan``."""
    lb = lower_bounds(inst)
    best, best_name = lb["best"], lb["best_name"]
    sols = []
    for s in solutions or []:
        v = s.extra.get("lower_bound")
        if isinstance(v, (int, float)) and v > best:
            best, best_name = float(v), f"{s.method} (solver)"
    for s in solutions or []:
        ok = s.success and s.makespan > 0
        sols.append({"method": s.method, "makespan": s.makespan if s.success else None,
                     "lower_bound": s.extra.get("lower_bound"), "status": s.extra.get("status"),
                     "gap": (s.makespan - best) / s.makespan if ok else None})
    return {"format": BOUND_FORMAT, "instance": inst.name, "bounds": {k: lb[k] for k in BOUND_DOCS}, "best": best,
            "best_name": best_name, "solutions": sols}


def format_report(rep: dict) -> str:
    """Human-readable text of :func:`bound_report` (what ``hmrta bound`` prints)."""
    lines = [f"{rep['instance']}: lower bounds on the optimal makespan"]
    for k, v in rep["bounds"].items():
        lines.append(f"  {k:<18} {v:10.3f}   {BOUND_DOCS[k]}")
    for s in rep["solutions"]:
        if s["lower_bound"] is not None:
            lines.append(f"  {s['method'] + ' (solver)':<18} {s['lower_bound']:10.3f}   proven by the solver "
                         f"(status {s['status']})")
    lines.append(f"  {'best':<18} {rep['best']:10.3f}   ({rep['best_name']})")
    for s in rep["solutions"]:
        if s["makespan"] is None:
            lines.append(f"  {s['method']}: failed")
        else:
            gap = "no gap (makespan 0)" if s["gap"] is None else f"gap to best bound {100 * s['gap']:.1f}%"
            lines.append(f"  {s['method']}: makespan {s['makespan']:.3f}, {gap}")
    return "\n".join(lines)
