"""Solutions (`hmrta-solution/1`), SPEC §4 metrics, and route evaluation (SPEC §3).

Route evaluation re-simulates given per-agent routes: a task's coalition is every agent whose route
contains it, it starts at the latest arrival of them all, each member leaves at its finish, and
after its last task every agent returns to its depot.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .instance import Instance, atomic_write_text

FORMAT = "hmrta-solution/1"
ETA = 10.0  # redundancy of an unsatisfied task (paper Eq. 2)


class RouteError(ValueError):
    """Invalid routes for route evaluation (uncovered task, unknown id, unsatisfied, cyclic wait)."""


@dataclass
class Solution:
    instance: str
    method: str
    seed: int
    success: bool
    makespan: float
    awt: float
    redundancy: float
    compute_seconds: float
    routes: list[list[int]]
    tasks: list[dict[str, Any]]  # {"start", "finish", "members"}
    agents: list[dict[str, Any]]  # {"species", "return_time"}
    extra: dict[str, Any] = field(default_factory=dict)  # e.g. failure, status, lower_bound

    def to_dict(self) -> dict[str, Any]:
        d = {
            "format": FORMAT,
            "instance": self.instance,
            "method": self.method,
            "seed": self.seed,
            "success": self.success,
            "makespan": _f(self.makespan),
            "awt": _f(self.awt),
            "redundancy": _f(self.redundancy),
            "compute_seconds": round(self.compute_seconds, 6),
            "routes": self.routes,
            "tasks": [{"start": _f(t["start"]), "finish": _f(t["finish"]), "members": list(t["members"])}
                      for t in self.tasks],
            "agents": [{"species": a["species"], "return_time": _f(a["return_time"])} for a in self.agents],
        }
        d.update(self.extra)
        return d

    def save(self, path: str | Path) -> None:
        atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Solution":
        known = {"format", "instance", "method", "seed", "success", "makespan", "awt", "redundancy",
                 "compute_seconds", "routes", "tasks", "agents"}
        return cls(
            d["instance"], d["method"], d["seed"], d["success"], _nan(d["makespan"]), _nan(d["awt"]),
            _nan(d["redundancy"]), d["compute_seconds"], d["routes"], d["tasks"], d["agents"],
            {k: v for k, v in d.items() if k not in known},
        )

    def summary(self) -> str:
        if not self.success:
            return f"{self.instance}: {self.method} FAILED ({self.extra.get('failure', 'unknown reason')})"
        return (f"{self.instance}: {self.method} makespan {self.makespan:.3f}  AWT {self.awt:.3f}  "
                f"redundancy {self.redundancy:.3f}  compute {self.compute_seconds:.3f}s")


def _f(v: float) -> float | None:
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else float(v)


def _nan(v: Any) -> float:
    return math.nan if v is None else float(v)


# ---------------------------------------------------------------------------------------------
# metrics (SPEC §4)
# ---------------------------------------------------------------------------------------------
def redundancy(inst: Instance, members: Sequence[Sequence[int]], satisfied: Sequence[bool]) -> float:
    """Ability redundancy W: mean over tasks of sum_k |c_L,k - q_k| / sum_k q_k (eta if unsatisfied)."""
    if inst.n_tasks == 0:
        return 0.0
    traits, req = inst.traits, inst.requirements
    w = []
    for m in range(inst.n_tasks):
        if not satisfied[m]:
            w.append(ETA)
            continue
        c = traits[list(members[m])].sum(0) if members[m] else np.zeros(inst.skills)  # [K]
        w.append(float(np.abs(c - req[m]).sum() / req[m].sum()))
    return float(np.mean(w))


def satisfies(inst: Instance, coalition: Sequence[int], m: int) -> list[int]:
    """Skills task m still lacks with this coalition (empty list: satisfied)."""
    c = inst.traits[list(coalition)].sum(0) if coalition else np.zeros(inst.skills)  # [K]
    q = inst.requirements[m]
    if inst.additive:
        return [k for k in range(inst.skills) if c[k] < q[k]]
    return [k for k in range(inst.skills) if q[k] > 0 and c[k] <= 0]


def solution_from_state(state, method: str, seed: int, compute_seconds: float) -> Solution:
    """Build a Solution from a finished :class:`hmrta.core.MissionState`."""
    from .core import DONE

    inst = state.inst
    ok = bool(state.success)
    done = [bool(s == DONE) for s in state.status]
    tasks = [
        {"start": float(state.start[m]) if done[m] else math.nan,
         "finish": float(state.finish[m]) if done[m] else math.nan,
         "members": sorted(int(a) for a in state.members[m])}
        for m in range(inst.n_tasks)
    ]
    ret = state.return_times()
    agents = [{"species": int(inst.agent_species[a]), "return_time": float(ret[a]) if ok else math.nan}
              for a in range(inst.n_agents)]
    extra: dict[str, Any] = {}
    if not ok:
        extra["failure"] = state.failure
    if int(state.depot_stops.sum()):
        extra["depot_stops"] = [int(x) for x in state.depot_stops]
    return Solution(
        inst.name, method, int(seed), ok,
        float(ret.max()) if ok and len(ret) else (0.0 if ok else math.nan),
        float(state.wait_total.mean()) if inst.n_agents else 0.0,
        redundancy(inst, state.members, done),
        compute_seconds,
        [list(map(int, r)) for r in state.routes], tasks, agents, extra,
    )


# ---------------------------------------------------------------------------------------------
# route evaluation
# ---------------------------------------------------------------------------------------------
def parse_routes(inst: Instance, data: Any, source: str = "routes") -> list[list[int]]:
    if not isinstance(data, dict) or "routes" not in data:
        raise RouteError(f"{source}: expected a JSON object with a 'routes' key")
    routes = data["routes"]
    A, M = inst.n_agents, inst.n_tasks
    if not isinstance(routes, list) or len(routes) != A:
        n = len(routes) if isinstance(routes, list) else type(routes).__name__
        raise RouteError(f"{source}: routes: expected a list of {A} routes (one per agent, species-major), got {n}")
    out = []
    for a, r in enumerate(routes):
        if not isinstance(r, list):
            raise RouteError(f"{source}: routes[{a}]: expected a list of task ids, got {r!r}")
        seen = set()
        for i, m in enumerate(r):
            if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < M:
                raise RouteError(f"{source}: routes[{a}][{i}]: unknown task id {m!r} (expected 0..{M - 1})")
            if m in seen:
                raise RouteError(f"{source}: routes[{a}]: agent {a} visits task {m} twice")
            seen.add(m)
        out.append(list(r))
    return out


def evaluate_routes(inst: Instance, routes: list[list[int]], method: str = "evaluate", seed: int = 0) -> Solution:
    """Re-simulate routes exactly (SPEC §3 'Route evaluation'). Raises RouteError."""
    A, M = inst.n_agents, inst.n_tasks
    coal: list[list[int]] = [[] for _ in range(M)]
    for a, r in enumerate(routes):
        for m in r:
            coal[m].append(a)
    for m in range(M):
        if not coal[m]:
            raise RouteError(f"task {m} is not covered by any route")
        lack = satisfies(inst, coal[m], m)
        if lack:
            raise RouteError(f"task {m}: its coalition (agents {coal[m]}) lacks skill(s) {lack}")
    # event-free fixed point: repeatedly start every task whose members all arrived
    pos_i = [0] * A  # index into each route of the next task
    ready = np.zeros(A)  # [A] time agent a is free at its current location
    where = np.array(inst.depots, dtype=np.float64)  # [A, 2]
    start = np.full(M, np.nan)
    finish = np.full(M, np.nan)
    arrival = {}  # (a, m) -> arrival time
    wait = np.zeros(A)
    remaining = M
    while remaining:
        progressed = False
        for m in range(M):
            if not math.isnan(start[m]):
                continue
            if all(pos_i[a] < len(routes[a]) and routes[a][pos_i[a]] == m for a in coal[m]):
                arr = []
                for a in coal[m]:
                    t = ready[a] + inst.travel_time(where[a], inst.task_locations[m])
                    arrival[(a, m)] = t
                    arr.append(t)
                start[m] = max(arr)
                finish[m] = start[m] + inst.durations[m]
                for a in coal[m]:
                    wait[a] += start[m] - arrival[(a, m)]
                    ready[a] = finish[m]
                    where[a] = inst.task_locations[m]
                    pos_i[a] += 1
                remaining -= 1
                progressed = True
        if not progressed:
            stuck = sorted({routes[a][pos_i[a]] for a in range(A) if pos_i[a] < len(routes[a])})
            raise RouteError(f"deadlock: cyclic waiting among tasks {stuck}")
    ret = np.array([ready[a] + inst.travel_time(where[a], inst.depots[a]) for a in range(A)])
    tasks = [{"start": float(start[m]), "finish": float(finish[m]), "members": sorted(coal[m])} for m in range(M)]
    agents = [{"species": int(inst.agent_species[a]), "return_time": float(ret[a])} for a in range(A)]
    return Solution(inst.name, method, seed, True, float(ret.max()) if A else 0.0,
                    float(wait.mean()) if A else 0.0, redundancy(inst, coal, [True] * M), 0.0,
                    [list(r) for r in routes], tasks, agents)
