"""Import of the CTAS-D planner family's ``config.json`` (SPEC §6).

``setup {robots, tasks, num_skills}``, ``tasks {"<j>": {pos {x, y}, skillset {"<k>": amount},
duration}}``, ``robots {"<a>": {pose {x, y}, skillset {"<k>": 0|1}}}``. Robots that share pose and
skillset form one species (their pose is its depot). Requirements are additive amounts; the
velocity is the SPEC default (0.2) unless the file carries ``setup.velocity``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from .instance import DEFAULT_VELOCITY, FORMAT, Instance, InstanceError, instance_from_dict


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
        raise InstanceError(f"{where}: expected integer keys, got {key!r}") from None


def _skillset(d: Any, k: int, where: str) -> list[float]:
    if not isinstance(d, dict):
        raise InstanceError(f"{where}: expected an object {{skill index: amount}}, got {d!r}")
    out = [0.0] * k
    for key, v in d.items():
        i = _index(key, where)
        if not 0 <= i < k:
            raise InstanceError(f"{where}: skill index {i} outside 0..{k - 1} (setup.num_skills = {k})")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InstanceError(f"{where}[{key!r}]: expected a number, got {v!r}")
        out[i] = v
    return out


def _xy(d: Any, where: str) -> list[float]:
    return [_get(d, "x", where), _get(d, "y", where)]


def instance_from_ctas_config(data: Any, source: str = "config.json") -> Instance:
    setup = _get(data, "setup", source)
    k = _get(setup, "num_skills", f"{source}: setup")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise InstanceError(f"{source}: setup.num_skills: expected a positive integer, got {k!r}")
    tasks_d = _get(data, "tasks", source)
    robots_d = _get(data, "robots", source)
    if not isinstance(tasks_d, dict) or not isinstance(robots_d, dict):
        raise InstanceError(f"{source}: tasks and robots: expected objects keyed by index")
    for key, n in (("robots", len(robots_d)), ("tasks", len(tasks_d))):
        if key in setup and setup[key] != n:
            raise InstanceError(f"{source}: setup.{key} = {setup[key]!r} but {n} {key} are listed")
    species: list[dict] = []
    index: dict[tuple, int] = {}
    for key in sorted(robots_d, key=lambda s: _index(s, f"{source}: robots")):
        r = robots_d[key]
        w = f"{source}: robots[{key!r}]"
        pose = _xy(_get(r, "pose", w), f"{w}.pose")
        traits = _skillset(_get(r, "skillset", w), k, f"{w}.skillset")
        sig = (tuple(pose), tuple(traits))
        if sig in index:
            species[index[sig]]["count"] += 1
        else:
            index[sig] = len(species)
            species.append({"traits": traits, "count": 1, "depot": pose})
    tasks = []
    for key in sorted(tasks_d, key=lambda s: _index(s, f"{source}: tasks")):
        t = tasks_d[key]
        w = f"{source}: tasks[{key!r}]"
        tasks.append(
            {
                "location": _xy(_get(t, "pos", w), f"{w}.pos"),
                "requirements": _skillset(_get(t, "skillset", w), k, f"{w}.skillset"),
                "duration": _get(t, "duration", w),
            }
        )
    d = {
        "format": FORMAT,
        "name": Path(source).parent.name or Path(source).stem,
        "requirement_type": "additive",
        "velocity": setup.get("velocity", DEFAULT_VELOCITY),
        "skills": k,
        "species": species,
        "tasks": tasks,
    }
    return instance_from_dict(d, source=source)
