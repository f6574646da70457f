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

from .instance import Instance, atomic_write_text, instance_from_dict, text_field
from .reading import finite, parse_json, read_text, short

FORMAT = "hmrta-solution/1"
ETA = 10.0  # redundancy of an unsatisfied task (paper Eq. 2)


class RouteError(ValueError):
    """Invalid routes for route evaluation (uncovered task, unknown id, unsatisfied, cyclic wait)."""


class SolutionError(ValueError):
    """An invalid `hmrta-solution/1` file, or one that does not belong to the instance (a user error;
    one line naming the file and the field)."""


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
    def from_dict(cls, d: Any, source: str = "<data>") -> "Solution":
        """Validate a parsed `hmrta-solution/1` mapping (types, and routes / members / agents
        consistent with one another); raises :class:`SolutionError` naming the field."""
        return _solution_from_dict(d, source)

    def summary(self) -> str:
        if not self.success:
            line = f"{self.instance}: {self.method} FAILED ({self.extra.get('failure', 'unknown reason')})"
            running = self.extra.get("in_progress") if isinstance(self.extra, dict) else None
            if isinstance(running, list) and running:  # a partial result: what was under way when it stopped
                line += "\n  coalitions complete when it stopped: " + ", ".join(
                    f"task {r['task']} (start {r['start']:.3f}, finish due {r['finish']:.3f}, robots {r['members']})"
                    for r in running)
            return line
        line = (f"{self.instance}: {self.method} makespan {self.makespan:.3f}  AWT {self.awt:.3f}  "
                f"redundancy {self.redundancy:.3f}  compute {self.compute_seconds:.3f}s")
        pf = self.extra.get("portfolio") if isinstance(self.extra, dict) else None
        if isinstance(pf, dict) and pf.get("chosen"):  # a method chosen per mission: which one, on what
            line += f"  chose {pf['chosen']}"
            if isinstance(pf.get("tasks_known_at_start"), int):
                line += f" on the {pf['tasks_known_at_start']} task(s) known at time 0"
            if isinstance(pf.get("left_out"), dict) and pf["left_out"]:
                by_why: dict = {}  # the candidates left out for one reason together
                for c, why in pf["left_out"].items():
                    by_why.setdefault(str(why), []).append(str(c))
                line += "\n  left out: " + "; ".join(f"{', '.join(cs)} ({why})" for why, cs in by_why.items())
        dyn = self.extra.get("dynamic") if isinstance(self.extra, dict) else None
        if isinstance(dyn, dict) and isinstance(dyn.get("tasks_lost"), dict):  # a mission with events
            lost = dyn["tasks_lost"]
            resp = (f"response time (finish - release) mean {dyn['mean_response']:.3f}, max {dyn['max_response']:.3f}"
                    if isinstance(dyn.get("mean_response"), (int, float)) and
                    isinstance(dyn.get("max_response"), (int, float)) else "no task done")
            line += (f"\n  {resp}; tasks lost: {lost.get('cancelled', 0)} cancelled, "
                     f"{lost.get('unsatisfiable', 0)} unsatisfiable, {lost.get('rejected', 0)} additions rejected")
            evs = dyn.get("events") if isinstance(dyn.get("events"), list) else []
            other = [e for e in evs if isinstance(e, dict) and "rejected" in e and e.get("type") != "add_task"]
            if other:  # a cancellation of a task already done, a robot event after the end, ...
                first = other[0]
                line += (f"\n  {len(other)} other event(s) not applied (first: {first.get('type')} at "
                         f"t={first.get('t')}: {first.get('rejected')})")
        return line


def _f(v: float) -> float | None:
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else float(v)


# ---------------------------------------------------------------------------------------------
# reading and checking solution files
# ---------------------------------------------------------------------------------------------
MAX_TIME = 1e15  # latest time a solution file may carry (instances keep every time far below it)
_KNOWN = ("format", "instance", "method", "seed", "success", "makespan", "awt", "redundancy",
          "compute_seconds", "routes", "tasks", "agents")
_TASK_KEYS = ("start", "finish", "members")
_AGENT_KEYS = ("species", "return_time")


def _serr(where: str, msg: str) -> SolutionError:
    return SolutionError(f"{where}: {msg}")


def _moves(v: Any, where: str) -> list[list[list]]:
    """The ``moves`` extra: per robot, [t, node] pairs in time order (node 0 its depot, 1 + m task
    m, -1 a stop where it was)."""
    rows = _list(v, where)
    out = []  # (one list per robot: checked against the mission where it is used, hmrta.render)
    for a, row in enumerate(rows):
        mv, last = [], -math.inf
        for i, e in enumerate(_list(row, f"{where}[{a}]")):
            w = f"{where}[{a}][{i}]"
            if not isinstance(e, (list, tuple)) or len(e) != 2:
                raise _serr(w, f"expected [time, node], got {short(e)}")
            t, n = _time(e[0], f"{w}[0]"), e[1]
            if isinstance(n, bool) or not isinstance(n, int) or n < -1:  # (tasks: checked against the mission)
                raise _serr(f"{w}[1]", f"expected a node >= -1 (0 the depot, 1 + m task m, -1 a stop), got {short(n)}")
            if not t >= last:
                raise _serr(f"{w}[0]", f"expected times in order (>= {short(last)}), got {short(e[0])}")
            mv.append([t, n])
            last = t
        out.append(mv)
    return out


def _int(v: Any, where: str, lo: int = 0) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise _serr(where, f"expected an integer >= {lo}, got {short(v)}")
    return v


def _time(v: Any, where: str, hi: float = MAX_TIME) -> float:
    """A number in [0, hi], or null (NaN: not done / failed)."""
    if v is None:
        return math.nan
    if not finite(v) or not 0 <= v <= hi:
        raise _serr(where, f"expected a number in [0, {hi:g}] or null, got {short(v)}")
    return float(v)


def _fields(v: Any, keys: tuple[str, ...], where: str, extra: bool = False) -> dict:
    if not isinstance(v, dict):
        raise _serr(where, f"expected an object with keys {list(keys)}, got {short(v)}")
    for k in keys:
        if k not in v:
            raise _serr(where, f"missing key {k!r}")
    if not extra:
        for k in v:
            if k not in keys:
                raise _serr(where, f"unknown key {short(k)} (expected one of {list(keys)})")
    return v


def _list(v: Any, where: str) -> list:
    if not isinstance(v, list):
        raise _serr(where, f"expected a list, got {short(v)}")
    return v


def _members(v: Any, A: int, where: str) -> list[int]:
    """A coalition: a list of agent ids of the A agents the file lists."""
    for i, a in enumerate(_list(v, where)):
        if isinstance(a, bool) or not isinstance(a, int) or not 0 <= a < A:
            raise _serr(f"{where}[{i}]", f"unknown agent id {short(a)} (expected 0..{A - 1}: the file lists {A} agents)")
    return list(v)


def _operator_cancelled(d: dict) -> bool:
    """Whether a dynamic mission's operator cancelled tasks (they stay undone in a success)."""
    dyn = d.get("dynamic")
    lost = dyn.get("tasks_lost") if isinstance(dyn, dict) else None
    return isinstance(lost, dict) and bool(lost.get("cancelled"))


def _solution_from_dict(d: Any, source: str) -> Solution:
    d = _fields(d, _KNOWN, source, extra=True)
    if d["format"] != FORMAT:
        raise _serr(f"{source}: format", f"expected {FORMAT!r}, got {short(d['format'])}")
    texts = {}
    for k in ("instance", "method"):
        if not isinstance(d[k], str):
            raise _serr(f"{source}: {k}", f"expected a string, got {short(d[k])}")
        texts[k] = text_field(d[k], f"{source}: {k}")
    seed = d["seed"]
    if isinstance(seed, bool) or not isinstance(seed, int) or seed.bit_length() > 64:
        raise _serr(f"{source}: seed", f"expected an integer, got {short(seed)}")
    if not isinstance(d["success"], bool):
        raise _serr(f"{source}: success", f"expected true or false, got {short(d['success'])}")
    metrics = [_time(d[k], f"{source}: {k}") for k in ("makespan", "awt", "redundancy")]
    cs = d["compute_seconds"]
    if not finite(cs) or cs < 0:
        raise _serr(f"{source}: compute_seconds", f"expected a number >= 0, got {short(cs)}")
    agents = []
    for a, info in enumerate(_list(d["agents"], f"{source}: agents")):
        w = f"{source}: agents[{a}]"
        info = _fields(info, _AGENT_KEYS, w)
        agents.append({"species": _int(info["species"], f"{w}.species"),
                       "return_time": _time(info["return_time"], f"{w}.return_time")})
    A = len(agents)
    raw_tasks = _list(d["tasks"], f"{source}: tasks")
    M = len(raw_tasks)
    tasks = []
    for m, t in enumerate(raw_tasks):
        w = f"{source}: tasks[{m}]"
        t = _fields(t, _TASK_KEYS, w)
        members = _members(t["members"], A, f"{w}.members")
        start, finish = _time(t["start"], f"{w}.start"), _time(t["finish"], f"{w}.finish")
        if math.isnan(start) != math.isnan(finish) or finish < start:
            raise _serr(f"{w}.finish", f"expected a finish >= the start ({short(t['start'])}), got {short(t['finish'])}")
        if d["success"] and math.isnan(start) and not _operator_cancelled(d):  # cancelled tasks have no start
            raise _serr(f"{w}.start", "expected a time: the solution succeeded, so every task was done")
        tasks.append({"start": start, "finish": finish, "members": members})
    routes = _list(d["routes"], f"{source}: routes")
    if len(routes) != A:
        raise _serr(f"{source}: routes", f"expected one route per agent ({A} agents listed), got {len(routes)}")
    for a, r in enumerate(routes):
        for i, m in enumerate(_list(r, f"{source}: routes[{a}]")):
            if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < M:
                raise _serr(f"{source}: routes[{a}][{i}]", f"unknown task id {short(m)} (expected 0..{M - 1}: "
                                                          f"the file lists {M} tasks)")
    extra = {k: v for k, v in d.items() if k not in _KNOWN}
    for k in ("failure", "status"):
        if extra.get(k) is not None and not isinstance(extra[k], str):
            raise _serr(f"{source}: {k}", f"expected a string, got {short(extra[k])}")
    if extra.get("lower_bound") is not None:
        _time(extra["lower_bound"], f"{source}: lower_bound")
    if "in_progress" in extra:
        extra["in_progress"] = _in_progress(extra["in_progress"], tasks, routes, d["success"], f"{source}: in_progress")
    if "moves" in extra:
        extra["moves"] = _moves(extra["moves"], f"{source}: moves")
    if d["success"]:
        if math.isnan(metrics[0]):
            raise _serr(f"{source}: makespan", "expected a number: the solution succeeded")
        last = max([t["finish"] for t in tasks] + [a["return_time"] for a in agents if not math.isnan(a["return_time"])],
                   default=0.0)
        if metrics[0] < last * (1 - 1e-9) - 1e-9:
            raise _serr(f"{source}: makespan", f"expected at least the last finish or return time ({last:g}), "
                                               f"got {short(d['makespan'])}")
    return Solution(texts["instance"], texts["method"], seed, d["success"], *metrics, float(cs),
                    [list(r) for r in routes], tasks, agents, extra)


def _in_progress(raw: Any, tasks: list[dict], routes: list[list[int]], success: bool, where: str) -> list[dict]:
    """The validated ``in_progress`` list of a partial result: tasks not done (no finish in
    ``tasks``), each once, with a start, a planned finish not before it, and a coalition of
    distinct agents whose routes hold the task."""
    A = len(routes)
    if success:
        raise _serr(where, "expected no tasks in progress: the solution succeeded")
    out, seen = [], set()
    for i, r in enumerate(_list(raw, where)):
        w = f"{where}[{i}]"
        r = _fields(r, ("task", "start", "finish", "members"), w)
        m = _int(r["task"], f"{w}.task")
        if not m < len(tasks) or m in seen or not math.isnan(tasks[m]["finish"]):
            raise _serr(f"{w}.task", f"expected a task not done and listed once (0..{len(tasks) - 1}), got {short(m)}")
        seen.add(m)
        start, finish = _time(r["start"], f"{w}.start"), _time(r["finish"], f"{w}.finish")
        if not finish >= start:  # (also refuses a missing time)
            raise _serr(f"{w}.finish", f"expected a planned finish >= the start ({short(r['start'])}), "
                                       f"got {short(r['finish'])}")
        members = _members(r["members"], A, f"{w}.members")
        if not members or len(set(members)) < len(members):
            raise _serr(f"{w}.members", f"expected the distinct agents of a coalition, got {short(members)}")
        stray = [a for a in members if m not in routes[a]]
        if stray:
            raise _serr(f"{w}.members", f"agent {stray[0]} does not have task {m} on its route (routes[{stray[0]}])")
        out.append({"task": m, "start": start, "finish": finish, "members": members})
    return out


def read_solution(path: str | Path) -> Solution:
    """Read and validate an `hmrta-solution/1` JSON file (SolutionError naming file and field)."""
    return Solution.from_dict(parse_json(read_text(path, SolutionError), str(path), SolutionError), str(path))


def check_planned_for(inst: Instance, sol: Solution, source: str = "solution") -> None:
    """Refuse a solution that records the mission it planned (``instance_sha256``, written by
    ``hmrta solve``) when ``inst``, the mission as read from its file, is another version of it
    (neither that mission nor, for one that grew, the mission as it ended: ``final_instance``)."""
    sha = sol.extra.get("instance_sha256") if isinstance(sol.extra, dict) else None
    if sol.instance and sol.instance != inst.name:
        return  # another mission by its name: check_solution says so
    if isinstance(sha, str) and sha != inst.fingerprint:
        final = sol.extra.get("final_instance")  # or the mission as it ended (tasks and robots added)
        if isinstance(final, dict):
            try:
                if instance_from_dict(final).to_dict() == inst.to_dict():
                    return
            except ValueError:
                pass
        if isinstance(sol.extra.get("dynamic"), dict) and not inst.dynamic:  # a scenario's, given its base mission
            raise _serr(source, f"solution does not match the instance {short(inst.name)}: it is the solution of a "
                                f"mission with events (a scenario, or a mission changed while it ran), this is the "
                                f"mission without them: give the scenario file it was solved from")
        raise _serr(source, f"solution does not match the instance {short(inst.name)}: it was planned for another "
                            f"version of the mission (its instance_sha256 differs: the mission file changed since)")


def check_solution(inst: Instance, sol: Solution, source: str = "solution") -> None:
    """Refuse a solution that does not belong to the instance: another instance name, other agent
    or task counts, or agents of other species."""
    if sol.instance and sol.instance != inst.name:
        raise _serr(source, f"solution does not match the instance: it is for instance {short(sol.instance)}, "
                            f"not {short(inst.name)}")
    if len(sol.agents) != inst.n_agents or len(sol.routes) != inst.n_agents or len(sol.tasks) != inst.n_tasks:
        raise _serr(source, f"solution does not match the instance {short(inst.name)}: {len(sol.routes)} routes / "
                            f"{len(sol.tasks)} tasks, expected {inst.n_agents} / {inst.n_tasks}")
    for a, info in enumerate(sol.agents):
        if info["species"] != int(inst.agent_species[a]):
            raise _serr(f"{source}: agents[{a}].species", f"solution does not match the instance "
                        f"{short(inst.name)}: species {info['species']}, the instance's agent {a} is of "
                        f"species {int(inst.agent_species[a])}")
    for a, r in enumerate(sol.routes):
        for i, m in enumerate(r):
            if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < inst.n_tasks:
                raise _serr(f"{source}: routes[{a}][{i}]", f"unknown task id {short(m)} "
                                                          f"(expected 0..{inst.n_tasks - 1})")
    on_route = [set(r) for r in sol.routes]
    for m, t in enumerate(sol.tasks):  # a task done by robots whose routes never visit it: routes edited
        finish = t.get("finish")
        if finish is None or finish != finish:  # not done
            continue
        for a in t.get("members") or ():
            if not (isinstance(a, int) and 0 <= a < len(on_route) and m in on_route[a]):
                raise _serr(f"{source}: tasks[{m}].members", f"robot {short(a)} did task {m}, but task {m} is "
                                                            f"not on its route: the routes and tasks disagree")
    for a, r in enumerate(sol.routes):  # a robot does its tasks one after the other, in its route's order
        prev = None
        for i, m in enumerate(r):
            t = sol.tasks[m]
            start, finish = t.get("start"), t.get("finish")
            if (a not in (t.get("members") or ()) or not isinstance(start, (int, float))
                    or not isinstance(finish, (int, float)) or not (start == start and finish == finish)):
                continue  # not done by this robot (cancelled, left, lost): no time to order it by
            if prev is not None and start < prev[1] - 1e-9 * max(1.0, abs(prev[1])):
                raise _serr(f"{source}: routes[{a}][{i}]", f"task {m} starts at {start:g}, before task {prev[0]} "
                                                          f"(earlier on robot {a}'s route) finishes at {prev[1]:g}: "
                                                          f"the routes and tasks disagree")
            prev = (m, finish)


def final_instance(inst: Instance, sol: Solution, source: str = "solution") -> Instance:
    """The instance ``sol`` indexes: ``inst``, or, for a mission that grew while it ran (tasks added,
    robots joining), the mission as it ended, which such a solution carries (``final_instance``
    in its extra fields) when it was made from ``inst``. Raises SolutionError for a solution of
    another instance."""
    grown = sol.extra.get("final_instance") if isinstance(sol.extra, dict) else None
    if grown is None or (len(sol.tasks), len(sol.routes)) == (inst.n_tasks, inst.n_agents):
        return inst
    try:
        out = instance_from_dict(grown, f"{source}: final_instance")
    except ValueError as e:  # (its message names f"{source}: final_instance")
        raise SolutionError(str(e)) from None
    if out.name != inst.name or out.n_tasks < inst.n_tasks or out.n_agents < inst.n_agents:
        raise _serr(source, f"solution does not match the instance {short(inst.name)}: it ended as mission "
                            f"{short(out.name)} with {out.n_agents} robots and {out.n_tasks} tasks")
    return out


def read_routes(inst: Instance, path: str | Path) -> list[list[int]]:
    """Read a routes JSON file (any object with a 'routes' key) and check it against the instance."""
    return parse_routes(inst, parse_json(read_text(path, RouteError), str(path), RouteError), str(path))


# ---------------------------------------------------------------------------------------------
# metrics (SPEC §4)
# ---------------------------------------------------------------------------------------------
def redundancy(inst: Instance, members: Sequence[Sequence[int]], satisfied: Sequence[bool],
               counted: Sequence[bool] | None = None) -> float:
    """Ability redundancy W: mean over tasks of sum_k |c_L,k - q_k| / sum_k q_k (eta if unsatisfied),
    over the ``counted`` tasks only when given (a task the operator cancelled needs no coalition)."""
    if inst.n_tasks == 0:
        return 0.0
    traits, req = inst.traits, inst.requirements
    w = []
    for m in range(inst.n_tasks):
        if counted is not None and not counted[m]:
            continue
        if not satisfied[m]:
            w.append(ETA)
            continue
        c = traits[sorted(members[m])].sum(0) if members[m] else np.zeros(inst.skills)  # [K] (by id: one sum order)
        w.append(float(np.abs(c - req[m]).sum() / req[m].sum()))
    return float(np.mean(w)) if w else 0.0


def satisfies(inst: Instance, coalition: Sequence[int], m: int) -> list[int]:
    """Skills task m still lacks with this coalition (empty list: satisfied)."""
    c = inst.traits[sorted(coalition)].sum(0) if coalition else np.zeros(inst.skills)  # [K] (by id: one sum order)
    q = inst.requirements[m]
    if inst.additive:  # short by no more than the cover tolerance: met (as in the state machine)
        return [k for k in range(inst.skills) if q[k] - c[k] > inst.cover_tol]
    return [k for k in range(inst.skills) if q[k] > 0 and c[k] <= 0]


def solution_from_state(state, method: str, seed: int, compute_seconds: float) -> Solution:
    """Build a Solution from a finished :class:`hmrta.core.MissionState`, or from one that stopped
    (a partial result): then ``tasks`` holds the times of the tasks done only, and the tasks in
    progress (their coalition complete: started, or starting once its members arrive) are listed
    in ``extra["in_progress"]`` with their start, planned finish and coalition."""
    from .core import CANCELLED, DONE, IN_PROGRESS

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
        running = np.flatnonzero(state.status == IN_PROGRESS)  # [R] started, not finished when it stopped
        if len(running):
            extra["in_progress"] = [{"task": int(m), "start": float(state.start[m]), "finish": float(state.finish[m]),
                                     "members": sorted(int(a) for a in state.members[m])} for m in running]
    if int(state.depot_stops.sum()):
        extra["depot_stops"] = [int(x) for x in state.depot_stops]
    if getattr(state, "moves", None) is not None:  # how the robots moved: what a drawing shows (hmrta.render)
        extra["moves"] = [[[float(t), int(n)] for t, n in mv] for mv in state.moves]
    if state.log or state.M > state.base[0] or bool((state.release > 0).any()):
        extra["dynamic"] = dynamic_metrics(state)
    if (state.M, state.A, inst.n_species) != tuple(state.base):  # tasks or robots were added: the mission as it
        extra["final_instance"] = inst.to_dict()  # ended, which the routes and tasks index (see final_instance)
    return Solution(
        inst.name, method, int(seed), ok,
        float(ret.max()) if ok and len(ret) else (0.0 if ok else math.nan),
        float(state.wait_total.mean()) if inst.n_agents else 0.0,
        redundancy(inst, state.members, done, ~(state.by_operator & (state.status == CANCELLED))),
        compute_seconds,
        [list(map(int, r)) for r in state.routes], tasks, agents, extra,
    )


def dynamic_metrics(state) -> dict[str, Any]:
    """Metrics of a mission with events (docs/semantics.md, "Events during a mission"): per-task
    release and response time (finish - release; null for a task not done), their mean and max
    over done tasks, and the tasks lost: cancelled by the operator, closed as unsatisfiable after a
    robot loss, and additions rejected (no robot left with a skill). ``events`` lists the external
    events as applied (or rejected, with the reason)."""
    from .core import CANCELLED, DONE

    done = state.status == DONE
    resp = np.where(done, state.finish - state.release, np.nan)  # [M]
    r = resp[done]
    by_op = state.by_operator & (state.status == CANCELLED)
    return {
        "release": [float(x) for x in state.release],
        "response": [_f(float(x)) for x in resp],
        "mean_response": float(r.mean()) if len(r) else None,
        "max_response": float(r.max()) if len(r) else None,
        "names": list(state.names),
        "tasks_lost": {"cancelled": int(by_op.sum()),
                       "unsatisfiable": int(((state.status == CANCELLED) & ~state.by_operator).sum()),
                       "rejected": sum(1 for e in state.log if e.get("type") == "add_task" and "rejected" in e)},
        "events": state.log,
    }


# ---------------------------------------------------------------------------------------------
# route evaluation
# ---------------------------------------------------------------------------------------------
def parse_routes(inst: Instance, data: Any, source: str = "routes") -> list[list[int]]:
    if not isinstance(data, dict) or "routes" not in data:
        raise RouteError(f"{source}: expected a JSON object with a 'routes' key")
    if isinstance(data.get("dynamic"), dict):  # the routes of a mission with events
        raise RouteError(f"{source}: the solution of a mission with events (tasks released, added or cancelled, "
                         f"robots joining or lost): its routes do not replay on a mission known at time 0; its "
                         f"schedule is the run itself (hmrta render draws it)")
    routes = data["routes"]
    A, M = inst.n_agents, inst.n_tasks
    if not isinstance(routes, list) or len(routes) != A:
        n = len(routes) if isinstance(routes, list) else type(routes).__name__
        raise RouteError(f"{source}: routes: expected a list of {A} routes (one per agent, species-major), got {n}")
    out = []
    for a, r in enumerate(routes):
        if not isinstance(r, list):
            raise RouteError(f"{source}: routes[{a}]: expected a list of task ids, got {short(r)}")
        seen = set()
        for i, m in enumerate(r):
            if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < M:
                raise RouteError(f"{source}: routes[{a}][{i}]: unknown task id {short(m)} (expected 0..{M - 1})")
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
