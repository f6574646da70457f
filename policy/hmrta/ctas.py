"""Import of the CTAS-D planner family's ``config.json`` (SPEC §6).

``setup {robots, tasks, num_skills}``, ``tasks {"<j>": {pos {x, y}, skillset {"<k>": amount},
duration}}``, ``robots {"<a>": {pose {x, y}, skillset {"<k>": 0|1}}}``. Robots that share pose and
skillset form one species (their pose is its depot). Requirements are additive amounts; the
velocity is the SPEC default (0.2) unless the file carries ``setup.velocity``.

Files are read by :func:`hmrta.formats.load_instance`; every problem is an
:class:`~hmrta.instance.InstanceError` naming the file and the field.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from .instance import (DEFAULT_VELOCITY, FORMAT, MAX_SKILLS, MAX_VALUE, MIN_VELOCITY, Instance, InstanceError,
                       instance_from_dict)
from .reading import finite, short


def _get(d: Any, key: str, where: str) -> Any:
    if not isinstance(d, dict):
        raise InstanceError(f"{where}: expected an object, got {type(d).__name__}")
    if key not in d:
        raise InstanceError(f"{where}: missing key {key!r}")
    return d[key]


def _index(key: str, where: str) -> int:
    try:
        return int(key)
    except (TypeError, ValueError):
        raise InstanceError(f"{where}: expected integer keys, got {short(key)}") from None


def _indexed(d: dict, where: str) -> list[str]:
    """The keys of an object keyed by index, in index order; two keys for one index are an error."""
    keys = sorted(d, key=lambda s: _index(s, where))
    for a, b in zip(keys, keys[1:]):
        if _index(a, where) == _index(b, where):
            raise InstanceError(f"{where}: keys {short(a)} and {short(b)} are the same index")
    return keys


def _skillset(d: Any, k: int, where: str) -> list[float]:
    if not isinstance(d, dict):
        raise InstanceError(f"{where}: expected an object {{skill index: amount}}, got {short(d)}")
    out = [0.0] * k
    for key in _indexed(d, where):
        v = d[key]
        i = _index(key, where)
        if not 0 <= i < k:
            raise InstanceError(f"{where}: skill index {i} outside 0..{k - 1} (setup.num_skills = {k})")
        out[i] = _num(v, f"{where}[{short(key)}]", 0.0, MAX_VALUE)
    if not any(out):
        raise InstanceError(f"{where}: expected at least one non-zero amount (all zero)")
    return out


def _xy(d: Any, where: str) -> list[float]:
    return [_num(_get(d, c, where), f"{where}.{c}", 0.0, 1.0, "a coordinate in the unit square [0, 1]")
            for c in ("x", "y")]


def _num(v: Any, where: str, lo: float, hi: float, what: str = "") -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InstanceError(f"{where}: expected a number, got {short(v)}")
    if not finite(v):
        raise InstanceError(f"{where}: expected a finite number, got {short(v)}")
    if not lo <= v <= hi:
        raise InstanceError(f"{where}: expected {what or f'a value in [{lo:g}, {hi:g}]'}, got {short(v)}")
    return v


def instance_from_ctas_config(data: Any, source: str = "config.json") -> Instance:
    setup = _get(data, "setup", source)
    k = _get(setup, "num_skills", f"{source}: setup")
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= MAX_SKILLS:
        raise InstanceError(f"{source}: setup.num_skills: expected a positive integer "
                            f"(at most {MAX_SKILLS}), got {short(k)}")
    tasks_d = _get(data, "tasks", source)
    robots_d = _get(data, "robots", source)
    if not isinstance(tasks_d, dict) or not isinstance(robots_d, dict):
        raise InstanceError(f"{source}: tasks and robots: expected objects keyed by index")
    if not robots_d:
        raise InstanceError(f"{source}: robots: expected at least one robot, got none")
    for key, n in (("robots", len(robots_d)), ("tasks", len(tasks_d))):
        if key in setup and setup[key] != n:
            raise InstanceError(f"{source}: setup.{key} = {short(setup[key])} but {n} {key} are listed")
    species: list[dict] = []
    index: dict[tuple, int] = {}
    for key in _indexed(robots_d, f"{source}: robots"):
        r = robots_d[key]
        w = f"{source}: robots[{short(key)}]"
        pose = _xy(_get(r, "pose", w), f"{w}.pose")
        traits = _skillset(_get(r, "skillset", w), k, f"{w}.skillset")
        sig = (tuple(pose), tuple(traits))
        if sig in index:
            species[index[sig]]["count"] += 1
        else:
            index[sig] = len(species)
            species.append({"traits": traits, "count": 1, "depot": pose})
    tasks, labels = [], []
    for key in _indexed(tasks_d, f"{source}: tasks"):
        labels.append(short(key))
        t = tasks_d[key]
        w = f"{source}: tasks[{short(key)}]"
        tasks.append(
            {
                "location": _xy(_get(t, "pos", w), f"{w}.pos"),
                "requirements": _skillset(_get(t, "skillset", w), k, f"{w}.skillset"),
                "duration": _num(_get(t, "duration", w), f"{w}.duration", 0.0, MAX_VALUE),
            }
        )
    d = {
        "format": FORMAT,
        "name": Path(source).parent.name or Path(source).stem,
        "requirement_type": "additive",
        "velocity": _num(setup["velocity"], f"{source}: setup.velocity", MIN_VELOCITY, MAX_VALUE)
        if "velocity" in setup else DEFAULT_VELOCITY,
        "skills": k,
        "species": species,
        "tasks": tasks,
    }
    return instance_from_dict(d, source=source, task_labels=labels)  # errors name a task by its key
