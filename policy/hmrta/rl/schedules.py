"""The solver as a teacher: datasets of near-optimal schedules and the route-following labeller.

**Datasets** (``hmrta schedules``): the anytime solver (``cpsat``: list scheduler, annealing and
CP-SAT, a few seconds per mission) solves missions ``0..count-1`` of a seeded generator, and the
routes are stored compactly, one JSON line per mission, after a header line::

    {"format": "hmrta-schedules/1", "generator": {"kind": "broad", "min_tasks": 10, "max_tasks": 30},
     "seed": 7, "solver": {"method": "cpsat", "time_limit": 1.5, "workers": 1}}
    {"index": 0, "makespan": 21.98, "routes": [[3, 0], [3], ...]}

Instances are not stored: mission ``index`` is regenerated from (generator, seed, index), so a
dataset is a deterministic function of them up to the solver's time limit (an anytime solver stops
on the clock). Routes are pruned to minimal coalitions (:func:`hmrta.solvers.listsched.prune_routes`)
so that, replayed in the state machine, every planned commitment is still needed. Generation
appends as missions finish (in any order) and is resumable: a rerun on the same file skips the
missions it holds, and a torn last line (a write cut short) is dropped first. Missions fan out on
Ray (:mod:`hmrta.fanout`) with ``jobs > 1`` or a cluster address.

**Labels** (:class:`RouteTeacher`): replayed in the state machine without a max-open-task cap, a
schedule's routes reproduce its makespan exactly: at each decision the deciding robot's label is
the next task on its route (its depot after the last). Where that choice is not admissible (a
max-open cap, or a state off the schedule's trajectory) the label comes from the ``fallback``
decider (greedy-coalition in training; docs/training.md).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from ..core import CANCELLED, DONE, IN_PROGRESS, MissionState
from ..families import BroadGenerator
from ..generators import ScenarioGenerator, TrainingGenerator
from ..instance import Instance
from ..reading import InputError, short

FORMAT = "hmrta-schedules/1"
GENERATORS = ("broad", "paper", "single-skill")


class ScheduleError(InputError):
    """A schedules file that cannot be used (one line: file, line, what was expected)."""


# ---- generators by name ------------------------------------------------------------------------
@dataclass(frozen=True)
class PaperTraining:
    """The paper's training distribution (MA-AT, 3-5 species of 3-5 robots, K = 5) with
    ``min_tasks..max_tasks`` tasks, as a seeded generator of indexed instances."""

    max_tasks: int = 30
    min_tasks: int = 15

    def instance(self, seed: int, index: int) -> Instance:
        import numpy as np

        rng = np.random.default_rng([seed, index, 0x70617072])  # "papr": apart from the test rows
        g = TrainingGenerator(tasks=(self.min_tasks, self.max_tasks))
        return g.sample(rng)


@dataclass(frozen=True)
class SingleSkillTraining:
    """Single-skill teams (the paper's SA scenarios, outside its training distribution): 3-5
    species of 2-10 robots, each species with one of K = species skills, additive (SA-AT) or binary
    (SA-BT) requirements with equal odds, ``min_tasks..max_tasks`` tasks; a seeded generator of
    indexed instances on its own salted stream (never a paper test or dev row's)."""

    max_tasks: int = 40
    min_tasks: int = 10

    def instance(self, seed: int, index: int) -> Instance:
        import numpy as np

        rng = np.random.default_rng([seed, index, 0x73696e67])  # "sing"
        try:
            return self.sample(rng)
        except ValueError as e:
            raise ValueError(f"{e} (seed {seed}, index {index})") from None

    def sample(self, rng) -> Instance:
        """One mission drawn from ``rng`` (a numpy Generator)."""
        for _ in range(100):  # a team too small for the drawn requirements is redrawn
            s, n = int(rng.integers(3, 6)), int(rng.integers(2, 11))
            m = int(rng.integers(self.min_tasks, self.max_tasks + 1))
            scenario = "SA-AT" if rng.random() < 0.5 else "SA-BT"
            try:
                return ScenarioGenerator(scenario, s * n, s, m, s).sample(rng, f"single-skill_{s * n}-{s}-{m}")
            except ValueError:
                continue
        raise ValueError("single-skill generator: no feasible mission in 100 draws")

    def generate(self, count: int, seed: int) -> list[Instance]:
        return [self.instance(seed, i) for i in range(count)]


def make_generator(spec: dict[str, Any]):
    """A generator from its header entry (``{"kind": "broad"|"paper"|"single-skill", "min_tasks",
    "max_tasks"}``, and for broad optionally ``"team_scale": [low, high]``: teams grown by a
    factor in that range, :class:`hmrta.families.BroadGenerator`)."""
    kind = spec.get("kind")
    lo, hi = spec.get("min_tasks"), spec.get("max_tasks")
    if kind not in GENERATORS:
        raise ScheduleError(f"generator.kind: expected one of {', '.join(GENERATORS)}, got {short(kind)}")
    if not (isinstance(lo, int) and isinstance(hi, int) and 1 <= lo <= hi <= 200):
        raise ScheduleError(f"generator: expected integer min_tasks <= max_tasks in 1..200, got {short(lo)}..{short(hi)}")
    scale = spec.get("team_scale", [1, 1])
    if not (isinstance(scale, (list, tuple)) and len(scale) == 2
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in scale)
            and 1 <= scale[0] <= scale[1] <= 20) or (kind != "broad" and "team_scale" in spec):
        raise ScheduleError(f"generator.team_scale: expected [low, high] with 1 <= low <= high <= 20 "
                            f"(broad only), got {short(scale)}")
    if kind == "broad":
        return BroadGenerator(max_tasks=hi, min_tasks=lo, team_scale=(float(scale[0]), float(scale[1])))
    return (PaperTraining if kind == "paper" else SingleSkillTraining)(max_tasks=hi, min_tasks=lo)


# ---- the labeller --------------------------------------------------------------------------------
class RouteTeacher:
    """A decider that follows a schedule's routes (module docstring). ``hits`` / ``misses`` count
    the decisions that followed the routes and those that fell back."""

    def __init__(self, routes: list[list[int]], fallback: Callable[[MissionState], int]):
        self.routes = routes
        self.ptr = [0] * len(routes)
        self.fallback = fallback
        self.hits = self.misses = 0

    def planned(self, st: MissionState) -> int | None:
        """The node the routes plan for the current decider (None: not admissible now)."""
        a = st.agent
        r = self.routes[a] if a < len(self.routes) else []
        mask = st.mask()
        i = self.ptr[a]
        while i < len(r) and st.status[r[i]] in (IN_PROGRESS, DONE, CANCELLED) and not mask[r[i] + 1]:
            i += 1  # taken over by others (off the schedule's trajectory): skip it
        self.ptr[a] = i
        n = r[i] + 1 if i < len(r) else 0
        return n if mask[n] else None

    def __call__(self, st: MissionState) -> int:
        n = self.planned(st)
        if n is None:
            self.misses += 1
            return self.fallback(st)
        if n:
            self.ptr[st.agent] += 1
        self.hits += 1
        return n


# ---- files -----------------------------------------------------------------------------------------
def header(generator: dict[str, Any], seed: int, time_limit: float, workers: int = 1) -> dict[str, Any]:
    return {"format": FORMAT, "generator": dict(generator), "seed": int(seed),
            "solver": {"method": "cpsat", "time_limit": float(time_limit), "workers": int(workers)}}


def _check_header(h: Any, where: str) -> dict[str, Any]:
    if not isinstance(h, dict) or h.get("format") != FORMAT:
        got = h.get("format") if isinstance(h, dict) else h
        raise ScheduleError(f"{where}: expected a header with format {FORMAT!r}, got {short(got)}")
    try:
        make_generator(h.get("generator") if isinstance(h.get("generator"), dict) else {})
    except ScheduleError as e:
        raise ScheduleError(f"{where}: {e}") from None
    if not isinstance(h.get("seed"), int) or isinstance(h.get("seed"), bool) or h["seed"] < 0:
        raise ScheduleError(f"{where}: seed: expected an integer >= 0, got {short(h.get('seed'))}")
    s = h.get("solver")
    if not isinstance(s, dict) or not isinstance(s.get("time_limit"), (int, float)) or not s["time_limit"] > 0:
        raise ScheduleError(f"{where}: solver.time_limit: expected a positive number")
    return h


def _check_row(r: Any, where: str) -> dict[str, Any]:
    if not isinstance(r, dict):
        raise ScheduleError(f"{where}: expected an object with index, makespan, routes")
    i, mk, routes = r.get("index"), r.get("makespan"), r.get("routes")
    if not isinstance(i, int) or isinstance(i, bool) or i < 0:
        raise ScheduleError(f"{where}: index: expected an integer >= 0, got {short(i)}")
    if not isinstance(mk, (int, float)) or isinstance(mk, bool) or not math.isfinite(mk) or mk < 0:
        raise ScheduleError(f"{where}: makespan: expected a number >= 0, got {short(mk)}")
    if not isinstance(routes, list) or not all(
            isinstance(x, list) and all(isinstance(m, int) and not isinstance(m, bool) and m >= 0 for m in x)
            for x in routes):
        raise ScheduleError(f"{where}: routes: expected a list of lists of task indices")
    return r


def read_schedules(path: str | os.PathLike) -> tuple[dict[str, Any], dict[int, dict[str, Any]], bool]:
    """(header, rows by index, torn): a torn last line (no newline, or not JSON) is reported, not
    returned. Raises ScheduleError (file and line) for anything else that is not as expected."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ScheduleError(f"{p}: cannot read ({e.__class__.__name__}: {e})") from None
    lines = text.split("\n")
    torn = bool(lines and lines[-1])  # the last line lacks its newline
    body = lines[:-1]
    if not body:  # nothing, or one line without its newline (a header cut short, or not a dataset)
        what = "empty" if not text.strip() else "no complete line (a dataset's lines end with a newline)"
        raise ScheduleError(f"{p}: {what}; expected a {FORMAT} header line")
    parsed = []
    for n, line in enumerate(body, 1):
        try:
            parsed.append(json.loads(line))
        except json.JSONDecodeError as e:
            raise ScheduleError(f"{p}:{n}: not a JSON line ({e.msg})") from None
    h = _check_header(parsed[0], f"{p}:1")
    rows: dict[int, dict[str, Any]] = {}
    for n, r in enumerate(parsed[1:], 2):
        r = _check_row(r, f"{p}:{n}")
        rows[r["index"]] = r
    return h, rows, torn


class ScheduleSet:
    """A schedules dataset: ``len``, and ``items()`` yielding (index, instance, routes, makespan)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.header, self.rows, _ = read_schedules(path)
        self.generator = make_generator(self.header["generator"])
        self.seed = self.header["seed"]

    def __len__(self) -> int:
        return len(self.rows)

    def indices(self) -> list[int]:
        return sorted(self.rows)

    def item(self, index: int) -> tuple[Instance, list[list[int]], float]:
        r = self.rows[index]
        inst = self.generator.instance(self.seed, index)
        routes = r["routes"]
        if len(routes) != inst.n_agents or any(m >= inst.n_tasks for x in routes for m in x):
            raise ScheduleError(f"{self.path}: mission {index}: routes do not fit the regenerated instance "
                                f"({inst.n_agents} robots, {inst.n_tasks} tasks): another generator version?")
        return inst, routes, float(r["makespan"])

    def items(self) -> Iterator[tuple[int, Instance, list[list[int]], float]]:
        for i in self.indices():
            yield (i, *self.item(i))


# ---- generation ------------------------------------------------------------------------------------
def _solve_one(job: tuple[dict, int, int, float, int]) -> dict[str, Any]:
    """One mission: the solver's schedule, pruned (a fanned-out work item)."""
    from ..methods import solve
    from ..solution import evaluate_routes
    from ..solvers.listsched import prune_routes

    spec, seed, index, time_limit, workers = job
    inst = make_generator(spec).instance(seed, index)
    sol = solve(inst, "cpsat", seed=index, time_limit=time_limit, workers=workers)
    routes = prune_routes(inst, sol.routes)
    mk = evaluate_routes(inst, routes).makespan
    return {"index": index, "makespan": round(float(mk), 6), "routes": routes}


def generate(path: str | os.PathLike, generator: dict[str, Any], seed: int, count: int,
             time_limit: float = 1.5, workers: int = 1, jobs: int = 1, ray_address: str | None = None,
             progress: bool = True) -> int:
    """Solve missions ``0..count-1`` into ``path`` (resumable; module docstring). Returns how many
    missions were solved now. A file of another generator, seed or solver is refused."""
    from ..fanout import Fanout

    make_generator(generator)
    p = Path(path)
    want = header(generator, seed, time_limit, workers)
    done: set[int] = set()
    if p.exists() and p.stat().st_size:
        h, rows, torn = read_schedules(p)
        if {k: h[k] for k in ("generator", "seed", "solver")} != {k: want[k] for k in ("generator", "seed", "solver")}:
            raise ScheduleError(f"{p}: holds schedules of another generator, seed or solver "
                                f"({json.dumps({k: h[k] for k in ('generator', 'seed', 'solver')})}); use another --out")
        if torn:  # drop the torn last line before appending
            keep = p.read_bytes()
            p.write_bytes(keep[:keep.rfind(b"\n") + 1])
        done = set(rows)
    else:
        p.parent.mkdir(parents=True, exist_ok=True)
        with open(p, "w", encoding="utf-8") as f:
            f.write(json.dumps(want) + "\n")
            f.flush()
            os.fsync(f.fileno())
    todo = [(dict(generator), seed, i, float(time_limit), int(workers)) for i in range(count) if i not in done]
    if not todo:
        return 0
    with open(p, "a", encoding="utf-8") as f:
        def write(_: int, row: dict[str, Any]) -> None:
            f.write(json.dumps(row, separators=(",", ":")) + "\n")
            f.flush()

        with Fanout(jobs, ray_address) as fan:
            fan.map(_solve_one, todo, on_result=write, progress="schedules" if progress else False)
        os.fsync(f.fileno())
    return len(todo)
