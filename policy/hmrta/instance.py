"""Mission instances (SPEC §1): the `hmrta-instance/1` YAML format, validation and import.

An :class:`Instance` is immutable. Agent ids are species-major: all agents of species 0, then
species 1, ... Task ids are 0-based positions in ``tasks``. Derived numpy arrays (per agent traits,
depots, task locations, ...) are computed once and cached on the instance.

Every loader problem raises :class:`InstanceError` with a one-line message that names the file,
the field (with task / species index) and what was expected.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

FORMAT = "hmrta-instance/1"
REQUIREMENT_TYPES = ("additive", "binary")
DEFAULT_VELOCITY = 0.2


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


@dataclass(frozen=True, eq=False)
class Instance:
    """A validated mission: species of agents, tasks, requirement type and velocity."""

    requirement_type: str
    velocity: float
    skills: int
    species: tuple[Species, ...]
    tasks: tuple[Task, ...]
    name: str = "instance"
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ---- sizes -------------------------------------------------------------------------------
    @property
    def n_agents(self) -> int:
        return sum(s.count for s in self.species)

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
        return _ro(np.repeat(np.arange(self.n_species), [s.count for s in self.species]))

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
    def durations(self) -> np.ndarray:  # [tasks]
        return _ro(np.array([t.duration for t in self.tasks], dtype=np.float64))

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
                }
                for t in self.tasks
            ],
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
                f"duration: {_fmt(t['duration'])}}}"
            )
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> None:
        """Write atomically (temp file + rename): never leaves a half-written instance."""
        atomic_write_text(Path(path), self.to_yaml())

    # ---- feasibility ---------------------------------------------------------------------------
    def infeasibility(self) -> str | None:
        """None if the whole team can satisfy every task, else a message naming task and skill."""
        team = (self.species_traits * np.array([s.count for s in self.species])[:, None]).sum(0)  # [skills]
        for m, t in enumerate(self.tasks):
            for k, q in enumerate(t.requirements):
                if self.additive and q > team[k]:
                    return (
                        f"task {m} is infeasible: it needs {_num(q)} of skill {k} "
                        f"but the whole team has {_num(team[k])}"
                    )
                if not self.additive and q > 0 and team[k] <= 0:
                    return f"task {m} is infeasible: it needs skill {k}, which no species has"
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
    tmp.write_text(text)
    tmp.replace(path)


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------
_TOP_KEYS = {"format", "name", "requirement_type", "velocity", "skills", "species", "tasks"}
_REQUIRED_TOP = {"format", "requirement_type", "velocity", "skills", "species", "tasks"}
_SPECIES_KEYS = {"traits", "count", "depot"}
_TASK_KEYS = {"location", "requirements", "duration"}


def _err(where: str, msg: str) -> InstanceError:
    return InstanceError(f"{where}: {msg}")


def _number(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _err(where, f"expected a number, got {v!r}")
    f = float(v)
    if math.isnan(f) or math.isinf(f):
        raise _err(where, f"expected a finite number, got {v!r}")
    return f


def _vector(v: Any, n: int, where: str, *, unit: bool = False, nonneg: bool = True) -> tuple[float, ...]:
    if not isinstance(v, list):
        raise _err(where, f"expected a list of {n} numbers, got {v!r}")
    if len(v) != n:
        raise _err(where, f"expected {n} values, got {len(v)}")
    out = []
    for i, x in enumerate(v):
        f = _number(x, f"{where}[{i}]")
        if nonneg and f < 0:
            raise _err(f"{where}[{i}]", f"expected a value >= 0, got {x!r}")
        if unit and not 0.0 <= f <= 1.0:
            raise _err(f"{where}[{i}]", f"expected a coordinate in the unit square [0, 1], got {x!r}")
        out.append(f)
    return tuple(out)


def _keys(d: Any, allowed: set[str], required: set[str], where: str) -> dict:
    if not isinstance(d, dict):
        raise _err(where, f"expected a mapping with keys {sorted(required)}, got {type(d).__name__}")
    unknown = sorted(set(map(str, d)) - allowed)
    if unknown:
        raise _err(where, f"unknown key {unknown[0]!r} (expected one of {sorted(allowed)})")
    missing = sorted(required - set(d))
    if missing:
        raise _err(where, f"missing key {missing[0]!r}")
    return d


def instance_from_dict(d: Any, source: str = "<data>") -> Instance:
    """Validate a parsed `hmrta-instance/1` mapping and build an Instance."""
    d = _keys(d, _TOP_KEYS, _REQUIRED_TOP, source)
    if d["format"] != FORMAT:
        raise _err(f"{source}: format", f"expected {FORMAT!r}, got {d['format']!r}")
    rt = d["requirement_type"]
    if rt not in REQUIREMENT_TYPES:
        raise _err(f"{source}: requirement_type", f"expected 'additive' or 'binary', got {rt!r}")
    vel = _number(d["velocity"], f"{source}: velocity")
    if vel <= 0:
        raise _err(f"{source}: velocity", f"expected a positive number, got {d['velocity']!r}")
    k = d["skills"]
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise _err(f"{source}: skills", f"expected a positive integer, got {k!r}")
    name = d.get("name", Path(source).stem if source != "<data>" else "instance")
    if not isinstance(name, (str, int, float)):
        raise _err(f"{source}: name", f"expected a string, got {name!r}")
    if not isinstance(d["species"], list) or not d["species"]:
        raise _err(f"{source}: species", "expected a non-empty list of species")
    if not isinstance(d["tasks"], list):
        raise _err(f"{source}: tasks", "expected a list of tasks")
    species = []
    for i, s in enumerate(d["species"]):
        w = f"{source}: species[{i}]"
        s = _keys(s, _SPECIES_KEYS, _SPECIES_KEYS, w)
        traits = _vector(s["traits"], k, f"{w}.traits")
        if not any(traits):
            raise _err(f"{w}.traits", "expected at least one non-zero trait (all zero)")
        c = s["count"]
        if isinstance(c, bool) or not isinstance(c, int) or c < 1:
            raise _err(f"{w}.count", f"expected a positive integer, got {c!r}")
        depot = _vector(s["depot"], 2, f"{w}.depot", unit=True)
        species.append(Species(traits, c, depot))  # type: ignore[arg-type]
    tasks = []
    for m, t in enumerate(d["tasks"]):
        w = f"{source}: tasks[{m}]"
        t = _keys(t, _TASK_KEYS, _TASK_KEYS, w)
        loc = _vector(t["location"], 2, f"{w}.location", unit=True)
        req = _vector(t["requirements"], k, f"{w}.requirements")
        if not any(req):
            raise _err(f"{w}.requirements", "expected at least one non-zero requirement (all zero)")
        dur = _number(t["duration"], f"{w}.duration")
        if dur < 0:
            raise _err(f"{w}.duration", f"expected a value >= 0, got {t['duration']!r}")
        tasks.append(Task(loc, req, dur))  # type: ignore[arg-type]
    inst = Instance(rt, vel, k, tuple(species), tuple(tasks), str(name))
    why = inst.infeasibility()
    if why:
        raise InstanceError(f"{source}: {why}")
    return inst


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that rejects a key written twice in one mapping (the last would silently win)."""


def _no_duplicates(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False):
    seen: dict = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (first on line {seen[key] + 1})", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _no_duplicates)


def load_instance(path: str | Path) -> Instance:
    """Load an `hmrta-instance/1` YAML file, or a CTAS-D-family ``config.json`` (SPEC §6)."""
    p = Path(path)
    if p.is_dir():
        cfg = p / "config.json"
        if not cfg.exists():
            raise InstanceError(f"{p}: is a folder without a config.json")
        p = cfg
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise InstanceError(f"{p}: no such file") from None
    except OSError as e:
        raise InstanceError(f"{p}: cannot read ({e.strerror})") from None
    if p.suffix.lower() == ".json":
        from .ctas import instance_from_ctas_config

        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise InstanceError(f"{p}:{e.lineno}: invalid JSON ({e.msg})") from None
        return instance_from_ctas_config(data, source=str(p))
    try:
        data = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise InstanceError(f"{p}{line}: invalid YAML ({problem})") from None
    return instance_from_dict(data, source=str(p))
