"""Dynamic scenarios (`hmrta-scenario/1`): a mission plus timed external events.

```yaml
format: hmrta-scenario/1
name: storm                      # optional
instance: mission.yaml           # a path (relative to this file: an hmrta-instance/1 file or a CTAS-D
                                 # config.json / folder) or an inline hmrta-instance/1 mapping
events:                          # applied at time t, in time order (file order among equal times)
  - {t: 4.0, type: add_task, id: inspect-7, location: [0.3, 0.6], requirements: [1, 0, 2], duration: 2}
  - {t: 6.5, type: cancel_task, id: inspect-7}     # a client id, or an instance task index
  - {t: 8.0, type: add_robot, species: 1}          # optional position: [x, y] (default: its depot)
  - {t: 9.0, type: add_robot, traits: [1, 1, 0], position: [0.2, 0.2]}
  - {t: 12.0, type: lose_robot, robot: 3}
```

A scenario loads as an :class:`~hmrta.instance.Instance` whose ``events`` hold the core event
records (:mod:`hmrta.core`); every :class:`~hmrta.core.MissionState` built on it schedules them, so
the simulator, the batched rollouts and the task board run one semantics and every method plans
without knowing an event before its time. Every problem is a :class:`ScenarioError` (an
InstanceError) naming the file, the line and the field.

This module parses and validates a scenario mapping; it does not open files. Scenario files are
loaded by :func:`hmrta.formats.load_instance`, which dispatches on the format above this module,
:mod:`hmrta.instance` and :mod:`hmrta.ctas`, and hands :func:`scenario_from_dict` the loader for a
mission referenced by path.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import yaml

from .instance import MAX_VALUE, Instance, InstanceError, instance_from_dict
from .reading import SafeStrictLoader, finite, short

FORMAT = "hmrta-scenario/1"
TYPES = ("add_task", "cancel_task", "add_robot", "lose_robot")
_FIELDS = {"add_task": ({"id", "location", "requirements", "duration"}, set()),
           "cancel_task": ({"id"}, set()),
           "add_robot": (set(), {"species", "traits", "position"}),
           "lose_robot": ({"robot"}, set())}


class ScenarioError(InstanceError):
    """A user error in a scenario file (one line: file, line, field)."""


def is_scenario(data: Any) -> bool:
    return isinstance(data, dict) and data.get("format") == FORMAT


def _line(text: str | None, keys: list) -> str:
    """' (line N)' of the YAML node at keys (mapping keys / list indices), or ''."""
    if not text:
        return ""
    try:
        node = yaml.compose(text, Loader=SafeStrictLoader)
        for k in keys:
            if isinstance(node, yaml.MappingNode):
                node = next(v for kn, v in node.value if kn.value == k)
            elif isinstance(node, yaml.SequenceNode):
                node = node.value[k]
        return f" (line {node.start_mark.line + 1})"
    except Exception:  # noqa: BLE001 - the line is a courtesy; the field is always named
        return ""


def scenario_from_dict(d: Any, source: str = "<data>", text: str | None = None,
                       load_mission: Callable[[Path], Instance] | None = None) -> Instance:
    """Validate a parsed `hmrta-scenario/1` mapping -> an Instance carrying the timed events.

    ``text`` (the file's YAML, optional) lets errors name the line. ``load_mission`` loads the
    mission of ``instance: PATH`` (a path relative to ``source``'s folder);
    :func:`hmrta.formats.load_instance` passes its mission loader. Without it only an inline
    mission is accepted."""
    def err(keys: list, field: str, msg: str) -> ScenarioError:
        return ScenarioError(f"{source}{_line(text, keys)}: {field}: {msg}")

    if not isinstance(d, dict):
        raise ScenarioError(f"{source}: expected a mapping with keys format, instance, events")
    allowed = {"format", "name", "instance", "events"}
    for k in d:
        if k not in allowed:
            raise err([k], str(k), f"unknown key (expected one of {sorted(allowed)})")
    for k in ("format", "instance", "events"):
        if k not in d:
            raise ScenarioError(f"{source}: missing key {k!r}")
    if d["format"] != FORMAT:
        raise err(["format"], "format", f"expected {FORMAT!r}, got {short(d['format'])}")
    src = d["instance"]
    if isinstance(src, str):
        if load_mission is None:
            raise err(["instance"], "instance", "expected an inline hmrta-instance/1 mapping (a path is "
                                                "resolved only when the scenario is loaded from a file)")
        ipath = Path(source).parent / src if source != "<data>" else Path(src)
        try:
            inst = load_mission(ipath)
        except InstanceError as e:
            raise ScenarioError(f"{source}{_line(text, ['instance'])}: instance: {e}") from None
    elif isinstance(src, dict):
        try:
            inst = instance_from_dict(src, f"{source}: instance")
        except InstanceError as e:
            raise ScenarioError(f"{e}{_line(text, ['instance'])}") from None
    else:
        raise err(["instance"], "instance", f"expected a path or an hmrta-instance/1 mapping, got {short(src)}")
    if inst.events:
        raise err(["instance"], "instance", "expected a mission, got another scenario")
    evs = d["events"]
    if not isinstance(evs, list):
        raise err(["events"], "events", f"expected a list of events, got {short(evs)}")
    K, M, A, S = inst.skills, inst.n_tasks, inst.n_agents, inst.n_species
    records: list[tuple[float, int, dict]] = []
    ids: set[str] = set()
    robots = A + sum(isinstance(x, dict) and x.get("type") == "add_robot" for x in evs)  # at the end (below: in time)
    for i, e in enumerate(evs):
        w, keys = f"events[{i}]", ["events", i]
        if not isinstance(e, dict):
            raise err(keys, w, f"expected a mapping {{t, type, ...}}, got {short(e)}")
        kind = e.get("type")
        if kind not in TYPES:
            raise err(keys + ["type"] if "type" in e else keys, f"{w}.type",
                      f"expected one of {', '.join(TYPES)}, got {short(kind)}")
        required, optional = _FIELDS[kind]
        for k in e:
            if k not in required | optional | {"t", "type"}:
                raise err(keys + [k], f"{w}.{k}", f"unknown field for {kind} (expected {sorted(required | optional | {'t', 'type'})})")
        for k in sorted(required | {"t"}):
            if k not in e:
                raise err(keys, w, f"missing field {k!r} for {kind}")
        t = e["t"]
        if not finite(t) or not 0 <= t <= MAX_VALUE:
            raise err(keys + ["t"], f"{w}.t", f"expected a finite time in [0, {MAX_VALUE:g}], got {short(t)}")

        def vec(k: str, n: int, unit: bool = False) -> list[float]:
            v = e[k]
            if not isinstance(v, list) or len(v) != n or not all(finite(x) and 0 <= x <= MAX_VALUE for x in v):
                raise err(keys + [k], f"{w}.{k}", f"expected a list of {n} numbers in [0, {MAX_VALUE:g}], got {short(v)}")
            if unit and not all(x <= 1 for x in v):
                raise err(keys + [k], f"{w}.{k}", f"expected a point in the unit square [0, 1], got {short(v)}")
            if not unit and not any(v):
                raise err(keys + [k], f"{w}.{k}", "expected at least one non-zero value (all zero)")
            return [float(x) for x in v]

        rec: dict[str, Any] = {"t": float(t)}
        if kind == "add_task":
            cid = e["id"]
            if not isinstance(cid, str) or not cid:
                raise err(keys + ["id"], f"{w}.id", f"expected a client id (a non-empty string), got {short(cid)}")
            if cid in ids:
                raise err(keys + ["id"], f"{w}.id", f"duplicate task id {cid!r}")
            if cid.isascii() and cid.isdigit():  # as for operators (hmrta-task cancel 7: the mission's task 7)
                raise err(keys + ["id"], f"{w}.id", f"an id of decimal digits names a task of the mission by its "
                                                   f"index: choose an id with a letter, got {cid!r}")
            ids.add(cid)
            dur = e["duration"]
            if not finite(dur) or not 0 <= dur <= MAX_VALUE:
                raise err(keys + ["duration"], f"{w}.duration", f"expected a number in [0, {MAX_VALUE:g}], got {short(dur)}")
            rec.update(type="add_task", name=cid, task={"location": vec("location", 2, True),
                                                        "requirements": vec("requirements", K),
                                                        "duration": float(dur)})
        elif kind == "cancel_task":
            cid = e["id"]
            if isinstance(cid, str):
                if cid not in {x.get("id") for x in evs if isinstance(x, dict) and x.get("type") == "add_task"}:
                    raise err(keys + ["id"], f"{w}.id", f"no add_task event has id {cid!r}")
                rec.update(type="cancel_task", name=cid)
            elif isinstance(cid, int) and not isinstance(cid, bool) and 0 <= cid < M:
                rec.update(type="cancel_task", task=cid)
            else:
                raise err(keys + ["id"], f"{w}.id", f"expected a client id or a task index in 0..{M - 1}, "
                                                   f"got {short(cid)}")
        elif kind == "add_robot":
            if ("species" in e) == ("traits" in e):
                raise err(keys, w, "add_robot: give exactly one of species and traits")
            rec["type"] = "add_agent"
            if "species" in e:
                s = e["species"]
                if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < S:
                    raise err(keys + ["species"], f"{w}.species", f"expected a species index in 0..{S - 1}, got {short(s)}")
                rec["species"] = s
            else:
                if "position" not in e:
                    raise err(keys, w, "add_robot with traits: missing field 'position' (its depot)")
                rec["traits"] = vec("traits", K)
            if "position" in e:
                rec["position"] = vec("position", 2, True)
        else:
            r = e["robot"]
            if isinstance(r, bool) or not isinstance(r, int) or not 0 <= r < robots:
                raise err(keys + ["robot"], f"{w}.robot", f"expected a robot index in 0..{robots - 1}, got {short(r)}")
            rec.update(type="drop_agent", agent=r)
        records.append((rec["t"], i, rec))
    records.sort(key=lambda x: x[:2])
    # in the order the mission applies them: a robot is lost once, after it joined; a task is
    # cancelled once, after it was added
    robots, lost, added, cancelled = A, set(), set(), set()
    for t, i, rec in records:
        if rec["type"] == "add_task":
            added.add(rec["name"])
        elif rec["type"] == "cancel_task":
            which = rec.get("name", rec.get("task"))
            keys = ["events", i, "id"]
            if "name" in rec and which not in added:
                raise err(keys, f"events[{i}].id", f"task {which!r} is cancelled at t={t:g}, before its add_task "
                                                   f"event (expected it after the task is added)")
            if which in cancelled:
                raise err(keys, f"events[{i}].id", f"task {which!r} is cancelled twice (expected each task "
                                                   f"cancelled once)")
            cancelled.add(which)
        elif rec["type"] == "add_agent":
            robots += 1
        elif rec["type"] == "drop_agent":
            r, keys = rec["agent"], ["events", i, "robot"]
            if r >= robots:
                raise err(keys, f"events[{i}].robot", f"expected a robot of the mission at t={t:g} (0..{robots - 1}), "
                                                      f"got {r}: it is added later")
            if r in lost:
                raise err(keys, f"events[{i}].robot", f"robot {r} is lost twice (expected each robot lost once)")
            lost.add(r)
    name = d.get("name", inst.name)
    if not isinstance(name, str):
        raise err(["name"], "name", f"expected a string, got {short(name)}")
    return dataclasses.replace(inst, name=name, events=tuple(r for _, _, r in records), _cache={})
