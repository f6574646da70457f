"""hmrta-instance/1 loader: valid files, round trips, and every validation error (issue 2, point 2).

Every rejection must be an InstanceError with a one-line message naming the file, the field (with
the task / species index) and what was expected.
"""
from __future__ import annotations

import math
import re

import numpy as np
import pytest
import yaml

from hmrta.formats import load_instance
from hmrta.instance import Instance, InstanceError, Species, Task, instance_from_dict

NAN, INF = float("nan"), float("inf")


def _set(path, value):
    """Mutator: set d[path...] = value (path like ('species', 1, 'traits'))."""

    def f(d):
        obj = d
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value

    return f


def _del(path):
    def f(d):
        obj = d
        for k in path[:-1]:
            obj = obj[k]
        del obj[path[-1]]

    return f


# (id, mutator, substrings the message must contain)
CASES = [
    # missing keys
    ("missing-top", _del(("velocity",)), ["velocity", "missing key"]),
    ("missing-format", _del(("format",)), ["missing key 'format'"]),
    ("missing-species-key", _del(("species", 1, "count")), ["species[1]", "missing key 'count'"]),
    ("missing-task-key", _del(("tasks", 0, "duration")), ["tasks[0]", "missing key 'duration'"]),
    # unknown keys
    ("unknown-top", _set(("agents",), 3), ["unknown key 'agents'", "expected one of"]),
    ("unknown-species-key", _set(("species", 0, "speed"), 1.0), ["species[0]", "unknown key 'speed'"]),
    ("unknown-task-key", _set(("tasks", 1, "priority"), 2), ["tasks[1]", "unknown key 'priority'"]),
    # wrong vector lengths
    ("traits-len", _set(("species", 1, "traits"), [0, 1]), ["species[1].traits", "expected 3 values, got 2"]),
    ("requirements-len", _set(("tasks", 0, "requirements"), [0, 1, 1, 0]),
     ["tasks[0].requirements", "expected 3 values, got 4"]),
    ("location-len", _set(("tasks", 1, "location"), [0.2, 0.2, 0.0]), ["tasks[1].location", "expected 2 values, got 3"]),
    ("depot-len", _set(("species", 0, "depot"), [0.1]), ["species[0].depot", "expected 2 values, got 1"]),
    ("traits-not-list", _set(("species", 0, "traits"), 1), ["species[0].traits", "expected a list of 3 numbers"]),
    # negative values
    ("negative-trait", _set(("species", 0, "traits"), [1, -1, 1]), ["species[0].traits[1]", "expected a value >= 0"]),
    ("negative-requirement", _set(("tasks", 1, "requirements"), [2, -1, 0]),
     ["tasks[1].requirements[1]", "expected a value >= 0"]),
    ("negative-duration", _set(("tasks", 1, "duration"), -0.5), ["tasks[1].duration", "expected a value >= 0"]),
    ("negative-velocity", _set(("velocity",), -0.2), ["velocity", "expected a positive number"]),
    ("zero-velocity", _set(("velocity",), 0), ["velocity", "expected a positive number"]),
    ("negative-depot", _set(("species", 1, "depot"), [-0.1, 0.5]), ["species[1].depot[0]", "expected"]),
    # NaN / inf
    ("nan-duration", _set(("tasks", 0, "duration"), NAN), ["tasks[0].duration", "expected a finite number"]),
    ("inf-duration", _set(("tasks", 1, "duration"), INF), ["tasks[1].duration", "expected a finite number"]),
    ("nan-trait", _set(("species", 1, "traits"), [0, NAN, 0]), ["species[1].traits[1]", "expected a finite number"]),
    ("inf-requirement", _set(("tasks", 0, "requirements"), [0, INF, 1]),
     ["tasks[0].requirements[1]", "expected a finite number"]),
    ("nan-location", _set(("tasks", 1, "location"), [0.2, NAN]), ["tasks[1].location[1]", "expected a finite number"]),
    ("inf-velocity", _set(("velocity",), INF), ["velocity", "expected a finite number"]),
    ("minus-inf-depot", _set(("species", 0, "depot"), [-INF, 0.1]), ["species[0].depot[0]", "expected a finite number"]),
    # wrong types
    ("string-duration", _set(("tasks", 0, "duration"), "3.5"), ["tasks[0].duration", "expected a number"]),
    ("bool-trait", _set(("species", 0, "traits"), [True, 0, 1]), ["species[0].traits[0]", "expected a number"]),
    ("count-zero", _set(("species", 1, "count"), 0), ["species[1].count", "expected a positive integer"]),
    ("count-float", _set(("species", 0, "count"), 1.5), ["species[0].count", "expected a positive integer"]),
    ("skills-zero", _set(("skills",), 0), ["skills", "expected an integer in 1..1000"]),
    ("skills-string", _set(("skills",), "3"), ["skills", "expected an integer in 1..1000"]),
    ("skills-huge", _set(("skills",), 10**9), ["skills", "expected an integer in 1..1000, got 1000000000"]),
    ("species-empty", _set(("species",), []), ["species", "expected a non-empty list"]),
    ("tasks-not-list", _set(("tasks",), {"a": 1}), ["tasks", "expected a list"]),
    ("species-entry-not-mapping", _set(("species", 1), [0, 1, 0]), ["species[1]", "expected a mapping"]),
    # locations outside the unit square
    ("location-outside", _set(("tasks", 0, "location"), [1.2, 0.5]),
     ["tasks[0].location[0]", "unit square"]),
    ("depot-outside", _set(("species", 1, "depot"), [0.5, 1.01]), ["species[1].depot[1]", "unit square"]),
    # all-zero vectors
    ("zero-requirements", _set(("tasks", 1, "requirements"), [0, 0, 0]),
     ["tasks[1].requirements", "expected at least one non-zero requirement"]),
    ("zero-traits", _set(("species", 1, "traits"), [0, 0, 0]),
     ["species[1].traits", "expected at least one non-zero trait"]),
    # enums and format
    ("requirement-type", _set(("requirement_type",), "multiplicative"),
     ["requirement_type", "expected 'additive' or 'binary'", "multiplicative"]),
    ("format", _set(("format",), "hmrta-instance/2"), ["format", "expected 'hmrta-instance/1'"]),
    # infeasible: team traits are [2, 1, 2]
    ("infeasible-at", _set(("tasks", 1, "requirements"), [2, 2, 0]),
     ["task 1 is infeasible", "skill 1", "needs 2", "whole team has 1"]),
]


@pytest.mark.parametrize("mutate,expect", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_loader_rejects(valid_dict, write_yaml, mutate, expect):
    mutate(valid_dict)
    path = write_yaml(valid_dict)
    with pytest.raises(InstanceError) as ei:
        load_instance(path)
    msg = str(ei.value)
    assert "\n" not in msg, msg
    assert msg.startswith(str(path)), msg  # names the file
    for s in expect:
        assert s in msg, (s, msg)
    # the same data without a file: same message, with the in-memory source name
    with pytest.raises(InstanceError) as ei2:
        instance_from_dict(yaml.safe_load(path.read_text()), source="mem")
    assert str(ei2.value) == msg.replace(str(path), "mem", 1)


def test_infeasible_binary_names_task_and_skill(valid_dict, write_yaml):
    d = valid_dict
    d["requirement_type"] = "binary"
    d["species"] = [{"traits": [1, 0, 0], "count": 3, "depot": [0, 0]},
                    {"traits": [0, 1, 0], "count": 1, "depot": [1, 1]}]
    d["tasks"][0]["requirements"] = [1, 0, 0]
    d["tasks"][1]["requirements"] = [0, 1, 1]  # skill 2: nobody has it
    with pytest.raises(InstanceError) as ei:
        load_instance(write_yaml(d))
    msg = str(ei.value)
    assert "\n" not in msg
    assert "task 1 is infeasible" in msg and "skill 2" in msg


def test_binary_requirement_amounts_are_coverage(valid_dict):
    """In BT a requirement of 2 means 'needs the skill': one agent with it is enough (feasible)."""
    d = valid_dict
    d["requirement_type"] = "binary"
    d["tasks"][1]["requirements"] = [5, 3, 0]  # AT-infeasible, BT-feasible
    inst = instance_from_dict(d)
    assert inst.requirement_type == "binary" and inst.infeasibility() is None


def test_robots_added_during_a_mission_count_in_the_team(valid_dict):
    """The mission as it ended (``added_agents``: robots that joined) is feasible when the robots
    that joined can do what only they can do; a species of count 0 has only such robots."""
    d = valid_dict
    d["species"].append({"traits": [0, 0, 4], "count": 0, "depot": [0.5, 0.5]})
    d["tasks"][1]["requirements"] = [0, 0, 4]  # only the new species can do it
    with pytest.raises(InstanceError, match="count"):
        instance_from_dict(d)  # count 0 without a robot that joined
    d["added_agents"] = [len(d["species"]) - 1]
    inst = instance_from_dict(d)
    assert inst.infeasibility() is None and inst.n_agents == sum(s["count"] for s in d["species"]) + 1
    d["tasks"][1]["requirements"] = [0, 0, 7]  # more than the team that ever was (2 + 4)
    with pytest.raises(InstanceError, match="task 1 is infeasible.*whole team has 6"):
        instance_from_dict(d)


@pytest.mark.parametrize("text,line", [
    ("format: hmrta-instance/1\nskills: 3\nspecies:\n  - {traits: [1, 0, 1], count: 2\n", 5),
    ("format: hmrta-instance/1\nskills: [3\nvelocity: 0.2\n", 3),
    ("format: hmrta-instance/1\n  skills: 3\n bad: : :\n", 2),
])
def test_invalid_yaml_names_line(write_yaml, text, line):
    p = write_yaml(text)
    with pytest.raises(InstanceError) as ei:
        load_instance(p)
    msg = str(ei.value)
    assert "\n" not in msg
    assert msg.startswith(f"{p}:{line}: invalid YAML"), msg


@pytest.mark.parametrize("text,expect", [
    ("", "the file is empty (expected an hmrta-instance/1 mission: a mapping"),  # empty file -> None
    ("- 1\n- 2\n", "expected a mapping"),
    ("just a string\n", "expected a mapping"),
])
def test_top_level_not_a_mapping(write_yaml, text, expect):
    with pytest.raises(InstanceError) as ei:
        load_instance(write_yaml(text))
    assert expect in str(ei.value) and "\n" not in str(ei.value)


def test_missing_file(tmp_path):
    p = tmp_path / "nope.yaml"
    with pytest.raises(InstanceError) as ei:
        load_instance(p)
    assert str(ei.value) == f"{p}: no such file"


def test_folder_without_config(tmp_path):
    with pytest.raises(InstanceError, match="config.json"):
        load_instance(tmp_path)


# ---------------------------------------------------------------------------------------------
# valid files
# ---------------------------------------------------------------------------------------------
def test_valid_load_and_derived_arrays(valid_dict, write_yaml):
    inst = load_instance(write_yaml(valid_dict))
    assert (inst.n_agents, inst.n_species, inst.n_tasks, inst.skills) == (3, 2, 2, 3)
    assert inst.name == "valid" and inst.additive and inst.velocity == 0.2
    # agent ids are species-major
    assert inst.agent_species.tolist() == [0, 0, 1]
    assert inst.traits.tolist() == [[1, 0, 1], [1, 0, 1], [0, 1, 0]]
    assert inst.depots.tolist() == [[0.1, 0.8], [0.1, 0.8], [0.5, 0.5]]
    assert inst.task_locations.tolist() == [[0.5, 0.9], [0.2, 0.2]]
    assert inst.requirements.tolist() == [[0, 1, 1], [2, 1, 0]]
    assert inst.durations.tolist() == [3.5, 0.0]
    assert not inst.traits.flags.writeable  # derived arrays are read-only
    # travel time = distance / velocity: (0.1,0.8) -> (0.5,0.5) is 0.5 -> 2.5
    assert inst.travel_time(inst.depots[0], inst.depots[2]) == pytest.approx(2.5)


def test_name_defaults_to_file_stem(valid_dict, write_yaml):
    del valid_dict["name"]
    assert load_instance(write_yaml(valid_dict, "my_mission.yaml")).name == "my_mission"


def test_yaml_round_trip_is_exact(valid_dict, write_yaml, tmp_path):
    inst = load_instance(write_yaml(valid_dict))
    text = inst.to_yaml()
    out = tmp_path / "sub" / "copy.yaml"
    inst.save(out)
    assert out.read_text() == text
    back = load_instance(out)
    assert back.to_yaml() == text
    assert back.to_dict() == inst.to_dict()
    assert not list(out.parent.glob(".*.tmp"))  # atomic write leaves no temp file
    (tmp_path / "taken").mkdir()
    with pytest.raises(IsADirectoryError):  # a failed write leaves no temp file either
        inst.save(tmp_path / "taken")
    assert not list(tmp_path.glob(".*tmp*"))


def test_round_trip_awkward_floats(tmp_path):
    """Floats whose repr has no '.' (1e-05) or are long must survive to_yaml -> load exactly."""
    inst = Instance(
        "additive", 0.2, 2,
        (Species((1.0, 2.5), 2, (1e-05, 0.1 + 0.2)), Species((3e-07, 0.0), 1, (1.0, 0.0))),
        (Task((0.5, 1e-10), (1.0, 2.0), 4.999999999999999), Task((0.0, 1.0), (3e-07, 1.0), 0.0)),
        name='odd "name": x \\ é \N{GRINNING FACE}',
    )
    p = tmp_path / "odd.yaml"
    inst.save(p)
    back = load_instance(p)
    assert back.to_dict() == inst.to_dict()
    assert back.to_yaml() == inst.to_yaml()
    assert back.name.endswith("\N{GRINNING FACE}")  # not two lone surrogates


def test_example_fixture_file(data_dir):
    """The hand-written fixture in tests/policy/data loads and matches the documented example."""
    inst = load_instance(data_dir / "example.yaml")
    assert inst.name == "example" and inst.n_agents == 5 and inst.n_tasks == 3
    assert inst.species[0].traits == (1.0, 0.0, 1.0) and inst.species[0].count == 3
    assert np.array_equal(inst.requirements[0], [0, 2, 1])
    assert math.isclose(inst.durations[0], 3.5)


@pytest.mark.parametrize("name,text,expect", [
    ("dup.yaml", "format: hmrta-instance/1\nrequirement_type: additive\nvelocity: 0.2\nvelocity: 0.3\nskills: 1\n"
                 "species: [{traits: [1], count: 1, depot: [0, 0]}]\ntasks: []\n",
     r"dup.yaml:4: .*duplicate key 'velocity' \(first on line 3\)"),  # YAML: with its line
    ("dup.json", '{"format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2, "velocity": 50, '
                 '"skills": 1, "species": [{"traits": [1], "count": 1, "depot": [0, 0]}], "tasks": []}',
     r"dup.json: invalid JSON \(duplicate key 'velocity'"),  # JSON keeps the last one silently
])
def test_a_key_written_twice_is_rejected(tmp_path, name, text, expect):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(InstanceError, match=expect):
        load_instance(p)


def test_format_dispatch_sits_above_instance_and_ctas():
    """hmrta.formats dispatches by format; hmrta.instance imports neither hmrta.ctas nor
    hmrta.formats (not even in a function), hmrta.ctas never imports hmrta.formats: no import
    cycle between the three."""
    import ast
    import subprocess
    import sys
    from pathlib import Path

    import hmrta

    def imports(name, module_level_only=False):
        tree = ast.parse((Path(hmrta.__file__).parent / f"{name}.py").read_text())
        nodes = tree.body if module_level_only else list(ast.walk(tree))
        return {n.module for n in nodes if isinstance(n, ast.ImportFrom) and n.module}

    assert not {"ctas", "formats"} & imports("instance")
    assert "formats" not in imports("ctas") and "instance" in imports("ctas")
    assert {"instance", "ctas"} <= imports("formats", module_level_only=True)
    out = subprocess.run([sys.executable, "-c", "import sys, hmrta.instance, hmrta.ctas; "
                          "print(sorted(m for m in sys.modules if m in ('hmrta.formats', 'hmrta.cli')))"],
                         capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_value_limits_keep_every_time_finite(valid_dict):
    from hmrta.instance import MAX_AGENTS

    for path, value, expect in [
        (("velocity",), 1e-300, "velocity: expected a number in [1e-09, 1e+09]"),
        (("tasks", 0, "duration"), 1e308, "tasks[0].duration: expected a value >= 0 and <= 1e+09"),
        (("species", 0, "traits"), [1e300, 0, 1], "species[0].traits[0]: expected a value <= 1e+09"),
        # a coordinate says so at any size (1e15 read 'a value <= 1e+09', 1e9 'the unit square')
        (("species", 0, "depot"), [1e15, 0.5], "species[0].depot[0]: expected a coordinate in the unit square"),
        (("tasks", 0, "location"), [0.5, -1e15], "tasks[0].location[1]: expected a coordinate in the unit square"),
        (("species", 0, "count"), MAX_AGENTS + 1, f"species[0].count: expected a positive integer (at most {MAX_AGENTS})"),
        (("tasks", 1, "duration"), 10**400, "tasks[1].duration: expected a finite number, got <an integer of"),
        (("name",), "\ud800", "name: expected text, got an invalid character at position 0"),
        # printed on consoles and in logs: a newline or a terminal escape would forge or hide a line
        (("name",), "two\nlines", "name: expected text on one line, got a control character at position 3 ('\\n')"),
        (("name",), "a\x1b[31m", "name: expected text on one line, got a control character at position 1 ('\\x1b')"),
    ]:
        d = yaml.safe_load(yaml.safe_dump(valid_dict))
        _set(path, value)(d)
        with pytest.raises(InstanceError, match=re.escape(expect)):
            instance_from_dict(d, "m.yaml")
    from hmrta.instance import MAX_TASKS

    d = yaml.safe_load(yaml.safe_dump(valid_dict))
    d["tasks"] = d["tasks"][:1] * (MAX_TASKS + 1)
    with pytest.raises(InstanceError, match=re.escape(f"tasks: {MAX_TASKS + 1} tasks; at most {MAX_TASKS}")):
        instance_from_dict(d, "m.yaml")


def test_numbers_with_an_exponent_and_no_decimal_point_are_numbers(write_yaml):
    """2e-1 is a number to YAML 1.2 and to people (PyYAML's YAML 1.1 read it as a string)."""
    text = ("format: hmrta-instance/1\nrequirement_type: additive\nvelocity: 2e-1\nskills: 1\n"
            "species:\n  - {traits: [1], count: 2, depot: [1e-1, 0.5]}\n"
            "tasks:\n  - {location: [0.5, 0.5], requirements: [1], duration: 3E0}\n")
    inst = load_instance(write_yaml(text))
    assert inst.velocity == 0.2 and inst.depots[0][0] == 0.1 and inst.tasks[0].duration == 3.0


def test_an_hmrta_output_given_as_a_mission_is_named(tmp_path):
    """A solution or a bench results file where a mission belongs: said so, not read as a CTAS-D
    config that lacks 'setup'."""
    from hmrta.generators import ScenarioGenerator
    from hmrta.methods import solve

    sol = tmp_path / "sol.json"
    sol.write_text(__import__("json").dumps(solve(ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(0, 0), "greedy").to_dict()))
    res = tmp_path / "results.json"
    res.write_text('{"seed": 1000, "count": 5, "methods": ["greedy"], "rows": [], "provenance": {}}')
    with pytest.raises(InstanceError, match="an hmrta-solution/1 file, expected a mission"):
        load_instance(sol)
    with pytest.raises(InstanceError, match="an hmrta bench results file, expected a mission"):
        load_instance(res)


def test_a_mission_written_as_json_reads_as_the_yaml_one(tmp_path):
    """An hmrta-instance/1 mission saved as .json is that mission (not a CTAS-D config); a
    scenario saved as .json is a scenario."""
    import json
    from pathlib import Path

    example = Path(__file__).parent / "data" / "example.yaml"
    data = yaml.safe_load(example.read_text())
    (tmp_path / "m.json").write_text(json.dumps(data))
    a, b = load_instance(example), load_instance(tmp_path / "m.json")
    assert a.to_dict() == b.to_dict()
    scen = {"format": "hmrta-scenario/1", "instance": str(example),
            "events": [{"t": 2.0, "type": "cancel_task", "id": 1}]}
    (tmp_path / "s.json").write_text(json.dumps(scen))
    assert load_instance(tmp_path / "s.json").dynamic
