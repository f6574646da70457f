"""Mission instances (SPEC §1): the `hmrta-instance/1` format and its validation.

An :class:`Instance` is immutable. Agent ids are species-major: all agents of species 0, then
species 1, ... Task ids are 0-based positions in ``tasks``. Derived numpy arrays (per agent traits,
depots, task locations, ...) are computed once and cached on the instance.

Every validation problem raises :class:`InstanceError` with a one-line message that names the
file, the field (with task / species index) and what was expected. Files are read by
:func:`hmrta.formats.load_instance` (YAML or a CTAS-D config.json).
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .reading import short

FORMAT = "hmrta-instance/1"
REQUIREMENT_TYPES = ("additive", "binary")
DEFAULT_VELOCITY = 0.2
MAX_AGENTS = 10_000  # most agents a mission may have (all species together)
MAX_TASKS = 100_000  # most tasks a mission file may hold
MAX_SKILLS = 1_000  # most skills a mission may have (the learned policy reads at most 5)
# traits, requirements and durations at most MAX_VALUE, velocity in [MIN_VELOCITY, MAX_VALUE]: every
# time and capability sum of a mission then stays finite (and far from float overflow)
MAX_VALUE = 1e9
MIN_VELOCITY = 1e-9


COVER_RTOL = 1e-9  # relative tolerance of "a coalition meets a requirement" (cover_tolerance)


def exact_arithmetic(*values: np.ndarray) -> bool:
    """True when every entry is a multiple of 2^-24 and the absolute values sum below 2^28: every
    sum and difference of such numbers is then exact in float64, whatever their order."""
    total = sum(float(np.abs(v).sum()) for v in values)
    if not math.isfinite(total) or total >= 2.0 ** 28:
        return False
    return all(bool((np.ldexp(np.asarray(v, dtype=np.float64), 24) % 1.0 == 0).all()) for v in values)


def _whole_and_small(*values: np.ndarray) -> bool:
    """Every entry a whole number and their absolute values summing below 2^53: sums exact too."""
    total = sum(float(np.abs(v).sum()) for v in values)
    return math.isfinite(total) and total < 2.0 ** 53 and all(bool((np.mod(v, 1.0) == 0).all()) for v in values)


def cover_tolerance(cap: np.ndarray, req: np.ndarray) -> float:
    """By how much a coalition's summed capability may fall short of a requirement entry and
    still meet it, for capabilities ``cap`` [A, K] and requirements ``req`` [M, K]: 0 when the
    arithmetic is exact (:func:`exact_arithmetic`: the generators' integers, halves, quarters; or
    whole numbers of any size up to 2^53 in all), otherwise 1e-9 of the largest entry. Decimal capabilities add up with rounding error (0.1
    added eight times is 0.7999999999999999, short of 0.8), and a coalition they complete must
    complete the task in the state machine, the route evaluation and the solvers alike."""
    if exact_arithmetic(cap, req) or _whole_and_small(cap, req):
        return 0.0
    scale = max(float(np.abs(cap).max(initial=0.0)), float(np.abs(req).max(initial=0.0)))
    return COVER_RTOL * scale


class InstanceError(ValueError):
    """A user error in an instance file or instance data (one line, names the field)."""


@dataclass(frozen=True)
class Species:
    traits: tuple[float, ...]
    count: int
    depot: tuple[float, float]


@dataclass(frozen=True)
class Task:
    location: tuple[float, float]
    requirements: tuple[float, ...]
    duration: float
    release: float = 0.0  # when the task becomes known (0: at mission start; docs/semantics.md, events)


@dataclass(frozen=True, eq=False)
class Instance:
    """A validated mission: species of agents, tasks, requirement type and velocity."""

    requirement_type: str
    velocity: float
    skills: int
    species: tuple[Species, ...]
    tasks: tuple[Task, ...]
    name: str = "instance"
    # robots added during a mission (MissionState.add_agent): the species of each, ids after the
    # species-major block; timed external events of a scenario (hmrta.scenario), applied by MissionState
    added_agents: tuple[int, ...] = ()
    events: tuple[dict, ...] = ()
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ---- sizes -------------------------------------------------------------------------------
    @property
    def n_agents(self) -> int:
        return sum(s.count for s in self.species) + len(self.added_agents)

    @property
    def n_tasks(self) -> int:
        return len(self.tasks)

    @property
    def n_species(self) -> int:
        return len(self.species)

    @property
    def additive(self) -> bool:
        return self.requirement_type == "additive"

    # ---- derived arrays (read-only) ----------------------------------------------------------
    @cached_property
    def agent_species(self) -> np.ndarray:  # [agents] int
        base = np.repeat(np.arange(self.n_species), [s.count for s in self.species])
        return _ro(np.concatenate([base, np.array(self.added_agents, dtype=base.dtype)]))

    @cached_property
    def species_traits(self) -> np.ndarray:  # [species, skills]
        return _ro(np.array([s.traits for s in self.species], dtype=np.float64).reshape(-1, self.skills))

    @cached_property
    def traits(self) -> np.ndarray:  # [agents, skills]
        return _ro(self.species_traits[self.agent_species])

    @cached_property
    def species_depots(self) -> np.ndarray:  # [species, 2]
        return _ro(np.array([s.depot for s in self.species], dtype=np.float64).reshape(-1, 2))

    @cached_property
    def depots(self) -> np.ndarray:  # [agents, 2]
        return _ro(self.species_depots[self.agent_species])

    @cached_property
    def task_locations(self) -> np.ndarray:  # [tasks, 2]
        return _ro(np.array([t.location for t in self.tasks], dtype=np.float64).reshape(-1, 2))

    @cached_property
    def requirements(self) -> np.ndarray:  # [tasks, skills]
        return _ro(np.array([t.requirements for t in self.tasks], dtype=np.float64).reshape(-1, self.skills))

    @cached_property
    def fingerprint(self) -> str:
        """The sha256 of the mission as planned: its ``hmrta-instance/1`` mapping, its timed
        events and the robots they add. A solution records it (``instance_sha256``), so that a
        drawing or a bound refuses a solution of another version of the mission."""
        import hashlib

        d = {"instance": self.to_dict(), "events": list(self.events), "added_agents": list(self.added_agents)}
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()

    @cached_property
    def cover_tol(self) -> float:
        """:func:`cover_tolerance` of this mission's robots and tasks."""
        return cover_tolerance(self.traits, self.requirements)

    @cached_property
    def durations(self) -> np.ndarray:  # [tasks]
        return _ro(np.array([t.duration for t in self.tasks], dtype=np.float64))

    @cached_property
    def releases(self) -> np.ndarray:  # [tasks] release times (0: known at mission start)
        return _ro(np.array([t.release for t in self.tasks], dtype=np.float64))

    @property
    def dynamic(self) -> bool:
        """True when tasks are released over time or timed events are scheduled (a scenario)."""
        return bool(self.events) or any(t.release > 0 for t in self.tasks)

    def travel_time(self, a: Sequence[float], b: Sequence[float]) -> float:
        return math.hypot(a[0] - b[0], a[1] - b[1]) / self.velocity

    # ---- conversion --------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "name": self.name,
            "requirement_type": self.requirement_type,
            "velocity": _num(self.velocity),
            "skills": self.skills,
            "species": [
                {"traits": [_num(v) for v in s.traits], "count": s.count, "depot": [_num(v) for v in s.depot]}
                for s in self.species
            ],
            "tasks": [
                {
                    "location": [_num(v) for v in t.location],
                    "requirements": [_num(v) for v in t.requirements],
                    "duration": _num(t.duration),
                    **({"release": _num(t.release)} if t.release else {}),
                }
                for t in self.tasks
            ],
            # robots added during a mission (a live board republishes its grown mission)
            **({"added_agents": [int(s) for s in self.added_agents]} if self.added_agents else {}),
        }

    def to_yaml(self) -> str:
        """Compact, deterministic YAML (one flow mapping per species / task)."""
        d = self.to_dict()
        lines = [
            f"format: {FORMAT}",
            f"name: {_yaml_str(d['name'])}",
            f"requirement_type: {d['requirement_type']}",
            f"velocity: {_fmt(d['velocity'])}",
            f"skills: {d['skills']}",
            "species:",
        ]
        for s in d["species"]:
            lines.append(
                f"  - {{traits: {_fmt_list(s['traits'])}, count: {s['count']}, depot: {_fmt_list(s['depot'])}}}"
            )
        lines.append("tasks:" if d["tasks"] else "tasks: []")
        for t in d["tasks"]:
            lines.append(
                f"  - {{location: {_fmt_list(t['location'])}, requirements: {_fmt_list(t['requirements'])}, "
                f"duration: {_fmt(t['duration'])}"
                + (f", release: {_fmt(t['release'])}" if "release" in t else "") + "}"
            )
        if "added_agents" in d:
            lines.append(f"added_agents: [{', '.join(str(s) for s in d['added_agents'])}]")
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> None:
        """Write atomically (temp file + rename): never leaves a half-written instance."""
        atomic_write_text(Path(path), self.to_yaml())

    # ---- feasibility ---------------------------------------------------------------------------
    def infeasibility(self, labels: Sequence[str] | None = None) -> str | None:
        """None if the whole team can satisfy every task, else a message naming task and skill
        (task m named ``labels[m]`` if given: its key in the file it came from)."""
        count = np.bincount(self.agent_species, minlength=self.n_species)  # [species] robots added during a mission too
        team = (self.species_traits * count[:, None]).sum(0)  # [skills]
        for m, t in enumerate(self.tasks):
            name = m if labels is None else labels[m]
            for k, q in enumerate(t.requirements):
                if self.additive and q - team[k] > self.cover_tol:  # (short by no more: met)
                    return (
                        f"task {name} is infeasible: it needs {_num(q)} of skill {k} (skills count from 0) "
                        f"but the whole team has {_num(team[k])}"
                    )
                if not self.additive and q > 0 and team[k] <= 0:
                    return f"task {name} is infeasible: it needs skill {k} (skills count from 0), which no species has"
        return None


def _ro(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _num(v: float) -> float | int:
    v = float(v)
    return int(v) if v.is_integer() and abs(v) < 2**53 else v


def _fmt(v: float | int) -> str:
    if not isinstance(v, float):
        return str(v)
    r = repr(v)
    # YAML 1.1 (PyYAML) reads '1e-05' as a string: its floats need a '.' in the mantissa
    return r.replace("e", ".0e", 1) if "e" in r and "." not in r else r


def _yaml_str(s: str) -> str:
    """Double-quoted YAML scalar. JSON escapes, except characters beyond U+FFFF as \\UXXXXXXXX:
    YAML reads JSON's surrogate-pair escapes back as two lone surrogates."""
    return '"' + "".join(f"\\U{ord(c):08x}" if ord(c) > 0xFFFF else json.dumps(c)[1:-1] for c in s) + '"'


def _fmt_list(vs: Sequence[float | int]) -> str:
    return "[" + ", ".join(_fmt(v) for v in vs) + "]"


def atomic_write_text(path: Path, text: str) -> None:
    path = Path(path)
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    finally:  # a failed write (or a folder at ``path``) leaves no temp file behind
        tmp.unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------
_TOP_KEYS = {"format", "name", "requirement_type", "velocity", "skills", "species", "tasks", "added_agents"}
_REQUIRED_TOP = {"format", "requirement_type", "velocity", "skills", "species", "tasks"}
_SPECIES_KEYS = {"traits", "count", "depot"}
_TASK_KEYS = {"location", "requirements", "duration"}
_TASK_OPTIONAL = {"release"}


def _err(where: str, msg: str) -> InstanceError:
    return InstanceError(f"{where}: {msg}")


def _number(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _err(where, f"expected a number, got {short(v)}")
    try:
        f = float(v)
    except OverflowError:  # an integer beyond the float range
        f = math.inf
    if math.isnan(f) or math.isinf(f):
        raise _err(where, f"expected a finite number, got {short(v)}")
    return f


def _vector(v: Any, n: int, where: str, *, unit: bool = False, nonneg: bool = True) -> tuple[float, ...]:
    if not isinstance(v, list):
        raise _err(where, f"expected a list of {n} numbers, got {short(v)}")
    if len(v) != n:
        raise _err(where, f"expected {n} values, got {len(v)}")
    out = []
    for i, x in enumerate(v):
        f = _number(x, f"{where}[{i}]")
        if unit and not 0.0 <= f <= 1.0:  # (a coordinate says so, whatever its size)
            raise _err(f"{where}[{i}]", f"expected a coordinate in the unit square [0, 1], got {short(x)}")
        if nonneg and f < 0:
            raise _err(f"{where}[{i}]", f"expected a value >= 0, got {short(x)}")
        if f > MAX_VALUE:
            raise _err(f"{where}[{i}]", f"expected a value <= {MAX_VALUE:g}, got {short(x)}")
        out.append(f)
    return tuple(out)


def _keys(d: Any, allowed: set[str], required: set[str], where: str) -> dict:
    if not isinstance(d, dict):
        got = "nothing (an empty value)" if d is None else type(d).__name__
        raise _err(where, f"expected a mapping with keys {sorted(required)}, got {got}")
    unknown = sorted({k if isinstance(k, str) else short(k) for k in d} - allowed)
    if unknown:
        raise _err(where, f"unknown key {short(unknown[0])} (expected one of {sorted(allowed)})")
    missing = sorted(required - set(d))
    if missing:
        raise _err(where, f"missing key {missing[0]!r}")
    return d


def instance_from_dict(d: Any, source: str = "<data>", task_labels: Sequence[str] | None = None) -> Instance:
    """Validate a parsed `hmrta-instance/1` mapping and build an Instance. ``task_labels``: how
    errors name each task (its key in a file of another format; default: its index)."""
    d = _keys(d, _TOP_KEYS, _REQUIRED_TOP, source)
    if d["format"] != FORMAT:
        raise _err(f"{source}: format", f"expected {FORMAT!r}, got {short(d['format'])}")
    rt = d["requirement_type"]
    if not isinstance(rt, str) or rt not in REQUIREMENT_TYPES:
        raise _err(f"{source}: requirement_type", f"expected 'additive' or 'binary', got {short(rt)}")
    vel = _number(d["velocity"], f"{source}: velocity")
    if vel <= 0:
        raise _err(f"{source}: velocity", f"expected a positive number, got {short(d['velocity'])}")
    if not MIN_VELOCITY <= vel <= MAX_VALUE:
        raise _err(f"{source}: velocity", f"expected a number in [{MIN_VELOCITY:g}, {MAX_VALUE:g}], "
                                          f"got {short(d['velocity'])}")
    k = d["skills"]
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= MAX_SKILLS:
        raise _err(f"{source}: skills", f"expected an integer in 1..{MAX_SKILLS}, got {short(k)}")
    name = d.get("name", Path(source).stem if source != "<data>" else "instance")
    if isinstance(name, bool) or not isinstance(name, (str, int, float)):
        raise _err(f"{source}: name", f"expected a string, got {short(name)}")
    name = text_field(name, f"{source}: name")
    if not isinstance(d["species"], list) or not d["species"]:
        raise _err(f"{source}: species", "expected a non-empty list of species")
    if not isinstance(d["tasks"], list):
        raise _err(f"{source}: tasks", "expected a list of tasks")
    if len(d["tasks"]) > MAX_TASKS:
        raise _err(f"{source}: tasks", f"{len(d['tasks'])} tasks; at most {MAX_TASKS}")
    added = d.get("added_agents", [])  # robots added during a mission: the species of each
    if not isinstance(added, list) or not all(isinstance(a, int) and not isinstance(a, bool) and a >= 0
                                              for a in added):
        raise _err(f"{source}: added_agents", f"expected a list of species indices, got {short(added)}")
    species = []
    for i, s in enumerate(d["species"]):
        w = f"{source}: species[{i}]"
        s = _keys(s, _SPECIES_KEYS, _SPECIES_KEYS, w)
        traits = _vector(s["traits"], k, f"{w}.traits")
        if not any(traits):
            raise _err(f"{w}.traits", "expected at least one non-zero trait (all zero)")
        c = s["count"]
        # count 0: a species only robots added during the mission have (added_agents)
        if (isinstance(c, bool) or not isinstance(c, int) or not 0 <= c <= MAX_AGENTS
                or (c == 0 and i not in added)):
            raise _err(f"{w}.count", f"expected a positive integer (at most {MAX_AGENTS}), got {short(c)}")
        depot = _vector(s["depot"], 2, f"{w}.depot", unit=True)
        species.append(Species(traits, c, depot))  # type: ignore[arg-type]
    if any(a >= len(species) for a in added):
        raise _err(f"{source}: added_agents", f"expected species indices in 0..{len(species) - 1}, got "
                                              f"{short(max(added))}")
    if sum(s.count for s in species) + len(added) > MAX_AGENTS:
        raise _err(f"{source}: species", f"{sum(s.count for s in species) + len(added)} agents in all; "
                                         f"at most {MAX_AGENTS}")
    tasks = []
    for m, t in enumerate(d["tasks"]):
        w = f"{source}: tasks[{m if task_labels is None else task_labels[m]}]"
        t = _keys(t, _TASK_KEYS | _TASK_OPTIONAL, _TASK_KEYS, w)
        loc = _vector(t["location"], 2, f"{w}.location", unit=True)
        req = _vector(t["requirements"], k, f"{w}.requirements")
        if not any(req):
            raise _err(f"{w}.requirements", "expected at least one non-zero requirement (all zero)")
        dur = _number(t["duration"], f"{w}.duration")
        if not 0 <= dur <= MAX_VALUE:
            raise _err(f"{w}.duration", f"expected a value >= 0 and <= {MAX_VALUE:g}, got {short(t['duration'])}")
        rel = _number(t.get("release", 0), f"{w}.release")
        if not 0 <= rel <= MAX_VALUE:
            raise _err(f"{w}.release", f"expected a time >= 0 and <= {MAX_VALUE:g}, got {short(t['release'])}")
        tasks.append(Task(loc, req, dur, rel))  # type: ignore[arg-type]
    inst = Instance(rt, vel, k, tuple(species), tuple(tasks), name, added_agents=tuple(added))
    why = inst.infeasibility(task_labels)
    if why:
        raise InstanceError(f"{source}: {why}")
    return inst


def text_field(v: Any, where: str) -> str:
    """A name-like field as text: numbers become their text; text that cannot be written as UTF-8
    (lone surrogates, e.g. from a YAML escape) or that holds a control character (a newline, a
    terminal escape: it is printed on consoles and in logs) is an error naming the field."""
    try:
        t = v if isinstance(v, str) else str(v)
    except ValueError:  # an integer too long to write out
        raise _err(where, f"expected a string, got {short(v)}") from None
    try:
        t.encode("utf-8")
    except UnicodeEncodeError as e:
        raise _err(where, f"expected text, got an invalid character at position {e.start} "
                          f"(lone surrogate {t[e.start]!a})") from None
    bad = CONTROL.search(t)
    if bad:
        raise _err(where, f"expected text on one line, got a control character at position {bad.start()} "
                          f"({bad.group()!a}) in {short(t)}")
    return t


CONTROL = re.compile("[\x00-\x1f\x7f-\x9f]")  # C0, DEL and C1 control characters (a newline, a terminal escape)
