"""Instance files by format (SPEC §1, §6): an `hmrta-instance/1` YAML file, a CTAS-D-family
``config.json`` (or the folder holding it), or an `hmrta-scenario/1` file (a mission plus timed
events).

This module sits above :mod:`hmrta.instance` (the format and its validation), :mod:`hmrta.ctas`
(the CTAS-D import) and :mod:`hmrta.scenario` (the events), so that none of those imports another
format's module; the mission a scenario names by path is loaded here and handed to the scenario
parser. Files are read
with :mod:`hmrta.reading` (regular files only, UTF-8, safe YAML, bounded JSON depth); every
problem is an :class:`~hmrta.instance.InstanceError` naming the file (and the field).
"""
from __future__ import annotations

from pathlib import Path

from .ctas import instance_from_ctas_config
from .instance import Instance, InstanceError, instance_from_dict
from .reading import parse_json, parse_yaml, read_text
from .scenario import is_scenario, scenario_from_dict


def load_instance(path: str | Path) -> Instance:
    """Load an `hmrta-instance/1` YAML file, a CTAS-D-family ``config.json`` (SPEC §6: a ``.json``
    file, or a folder that holds a ``config.json``), or an `hmrta-scenario/1` file."""
    return _load(path, scenarios=True)


def _load_mission(path: Path) -> Instance:
    """The mission a scenario names by path: an instance file or CTAS-D config, never a scenario."""
    return _load(path, scenarios=False)


def ctas_config(path: str | Path) -> tuple[Path, dict] | None:
    """(the ``config.json``, its content) where ``path`` is a CTAS-D-family config (a ``.json``
    file or a folder holding a ``config.json``) as :func:`load_instance` reads it; None for any
    other mission file (YAML, or an `hmrta-instance/1` or `hmrta-scenario/1` mission written as
    JSON). Problems with the file are InstanceErrors, as the loader's."""
    p = _config_file(Path(path))
    if p.suffix.lower() != ".json":
        return None
    data = parse_json(read_text(p, InstanceError), str(p), InstanceError)
    return (p, data) if _json_kind(data, p) == "ctas" else None


def _config_file(p: Path) -> Path:
    """``p``, or the ``config.json`` of the folder ``p``."""
    if not p.is_dir():
        return p
    cfg = p / "config.json"
    if not cfg.exists():
        raise InstanceError(f"{p}: is a folder without a config.json")
    return cfg


def _json_kind(data: object, p: Path) -> str:
    """What a JSON mission file holds: "instance", "scenario" or "ctas" (anything else, which the
    CTAS-D reader validates); an InstanceError for another hmrta file (a solution, bench results)."""
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt == "hmrta-instance/1":  # a mission written as JSON (JSON is YAML: the same reader)
        return "instance"
    if is_scenario(data):
        return "scenario"
    if isinstance(fmt, str) and fmt.startswith("hmrta-"):  # e.g. a solution
        raise InstanceError(f"{p}: an {fmt} file, expected a mission (an hmrta-instance/1 YAML file or a "
                            f"CTAS-D config.json)")
    if isinstance(data, dict) and "setup" not in data and "methods" in data and "rows" in data:
        raise InstanceError(f"{p}: an hmrta bench results file, expected a mission (an hmrta-instance/1 YAML "
                            f"file or a CTAS-D config.json)")
    return "ctas"


def _load(path: str | Path, scenarios: bool) -> Instance:
    p = _config_file(Path(path))
    text = read_text(p, InstanceError)
    if p.suffix.lower() == ".json":
        data = parse_json(text, str(p), InstanceError)
        kind = _json_kind(data, p)
        if kind == "instance":
            return instance_from_dict(data, source=str(p))
        if kind == "scenario" and scenarios:
            return scenario_from_dict(data, str(p), text, load_mission=_load_mission)
        if kind == "scenario":
            raise InstanceError(f"{p}: expected a mission (hmrta-instance/1), got a scenario")
        return instance_from_ctas_config(data, source=str(p))
    data = parse_yaml(text, str(p), InstanceError)
    if data is None:  # no document at all: an empty file, or only comments
        raise InstanceError(f"{p}: the file is empty (expected an hmrta-instance/1 mission: a mapping with keys "
                            f"format, requirement_type, velocity, skills, species, tasks)")
    if is_scenario(data):  # a mission with timed events (hmrta-scenario/1)
        if not scenarios:
            raise InstanceError(f"{p}: expected a mission (hmrta-instance/1), got a scenario")
        return scenario_from_dict(data, str(p), text, load_mission=_load_mission)
    return instance_from_dict(data, source=str(p))
