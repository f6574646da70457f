"""Import of the CTAS-D-family config.json (SPEC §6; issue 2, point 3)."""
from __future__ import annotations

import json

import pytest

from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.ctas import instance_from_ctas_config
from hmrta.formats import load_instance
from hmrta.instance import InstanceError
from hmrta.sim import simulate


@pytest.fixture
def cfg(data_dir):
    return json.loads((data_dir / "ctas_small" / "config.json").read_text())


def test_species_grouping_by_pose_and_skillset(data_dir):
    inst = load_instance(data_dir / "ctas_small" / "config.json")
    # robots 0,2 -> species 0; robots 1,4 -> species 1; robot 3 (same pose as 0, other skills) -> species 2
    got = [(s.traits, s.count, s.depot) for s in inst.species]
    assert got == [
        ((1.0, 0.0, 1.0), 2, (0.1, 0.2)),
        ((0.0, 1.0, 0.0), 2, (0.9, 0.9)),
        ((0.0, 1.0, 0.0), 1, (0.1, 0.2)),
    ]
    assert inst.n_agents == 5 and inst.agent_species.tolist() == [0, 0, 1, 1, 2]
    assert inst.requirement_type == "additive" and inst.velocity == 0.2 and inst.skills == 3
    assert [t.location for t in inst.tasks] == [(0.5, 0.5), (0.3, 0.7), (0.8, 0.2)]
    assert [t.requirements for t in inst.tasks] == [(2.0, 1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 3.0, 0.0)]
    assert [t.duration for t in inst.tasks] == [1.5, 0.0, 2.25]
    assert inst.name == "ctas_small"  # the folder name


def test_folder_and_file_load_the_same(data_dir):
    a = load_instance(data_dir / "ctas_small")
    b = load_instance(data_dir / "ctas_small" / "config.json")
    assert a.to_yaml() == b.to_yaml()


def test_round_trip_to_yaml(data_dir, tmp_path):
    inst = load_instance(data_dir / "ctas_small")
    p = tmp_path / "x.yaml"
    inst.save(p)
    back = load_instance(p)
    assert back.to_dict() == inst.to_dict()
    assert back.to_yaml() == p.read_text()
    sol = simulate(back, Greedy(), 0, GREEDY_RULES)
    assert sol.success


def test_numeric_key_order(tmp_path):
    """Keys are indices: "10" sorts after "9", not after "1"."""
    tasks = {str(j): {"pos": {"x": j / 20, "y": 0.5}, "skillset": {"0": 1}, "duration": j} for j in range(12)}
    cfg = {"setup": {"robots": 1, "tasks": 12, "num_skills": 1},
           "robots": {"0": {"pose": {"x": 0, "y": 0}, "skillset": {"0": 1}}},
           "tasks": dict(sorted(tasks.items()))}  # lexicographic file order: 0, 1, 10, 11, 2, ...
    p = tmp_path / "config.json"
    p.write_text(json.dumps(cfg))
    inst = load_instance(p)
    assert [t.duration for t in inst.tasks] == list(range(12))
    assert inst.name == tmp_path.name


def test_setup_velocity_is_used(cfg):
    cfg["setup"]["velocity"] = 0.5
    assert instance_from_ctas_config(cfg).velocity == 0.5


def _mut(cfg, path, value=None, delete=False):
    obj = cfg
    for k in path[:-1]:
        obj = obj[k]
    if delete:
        del obj[path[-1]]
    else:
        obj[path[-1]] = value


@pytest.mark.parametrize("path,value,delete,expect", [
    (("setup",), None, True, "missing key 'setup'"),
    (("robots",), None, True, "missing key 'robots'"),
    (("robots",), {}, False, "robots: expected at least one robot, got none"),
    (("setup", "num_skills"), 0, False, "setup.num_skills: expected a positive integer"),
    (("setup", "robots"), 4, False, "setup.robots = 4 but 5 robots are listed"),
    (("setup", "tasks"), 7, False, "setup.tasks = 7 but 3 tasks are listed"),
    (("robots", "1", "pose"), None, True, "robots['1']: missing key 'pose'"),
    (("tasks", "2", "pos", "y"), None, True, "tasks['2'].pos: missing key 'y'"),
    (("tasks", "0", "skillset", "3"), 1, False, "skill index 3 outside 0..2"),
    (("tasks", "0", "skillset", "1"), "x", False, "expected a number"),
    (("tasks", "1", "pos", "x"), 1.5, False, "tasks['1'].pos.x: expected a coordinate in the unit square"),
    (("robots", "3", "pose", "y"), -0.5, False, "robots['3'].pose.y: expected a coordinate in the unit square"),
    (("robots", "3", "pose", "y"), [0.5], False, "robots['3'].pose.y: expected a number, got [0.5]"),
    (("robots", "4", "skillset"), {"1": 0}, False, "robots['4'].skillset: expected at least one non-zero"),
    (("tasks", "0", "skillset", "0"), -2, False, "tasks['0'].skillset['0']: expected a value in [0, 1e+09]"),
    (("tasks", "0", "duration"), "long", False, "tasks['0'].duration: expected a number, got 'long'"),
    (("setup", "velocity"), 1e-300, False, "setup.velocity: expected a value in [1e-09, 1e+09]"),
    (("setup", "num_skills"), 10**12, False, "setup.num_skills: expected a positive integer (at most 1000)"),
    (("tasks", "2", "skillset", "1"), 4, False, "task '2' is infeasible"),  # team has 3 of skill 1
])
def test_config_errors(cfg, tmp_path, path, value, delete, expect):
    _mut(cfg, path, value, delete)
    p = tmp_path / "config.json"
    p.write_text(json.dumps(cfg))
    with pytest.raises(InstanceError) as ei:
        load_instance(p)
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith(str(p)), msg
    assert expect in msg, msg


def test_non_integer_key(cfg, tmp_path):
    cfg["robots"]["x"] = cfg["robots"].pop("4")
    p = tmp_path / "config.json"
    p.write_text(json.dumps(cfg))
    with pytest.raises(InstanceError, match=r"robots: expected integer keys, got 'x'"):
        load_instance(p)


def test_invalid_json_names_line(tmp_path):
    p = tmp_path / "config.json"
    p.write_text('{\n  "setup": {"robots": 1,\n  "tasks": }\n}\n')
    with pytest.raises(InstanceError) as ei:
        load_instance(p)
    assert str(ei.value).startswith(f"{p}:3: invalid JSON")


def test_two_keys_for_one_index(cfg, tmp_path):
    cfg["tasks"]["02"] = cfg["tasks"]["2"]
    cfg["setup"]["tasks"] = 4
    p = tmp_path / "config.json"
    p.write_text(json.dumps(cfg))
    with pytest.raises(InstanceError, match=r"tasks: keys '02' and '2' are the same index|tasks: keys '2' and '02'"):
        load_instance(p)


def test_a_key_written_twice_is_refused(cfg, tmp_path):
    """JSON keeps the last of two equal keys silently: a robot written twice would vanish."""
    text = json.dumps(cfg, indent=1)
    p = tmp_path / "config.json"
    p.write_text(text.replace('"robots": {', '"robots": {\n  "1": {"pos": [0, 0]},', 1))
    with pytest.raises(InstanceError, match=r"config.json: invalid JSON \(duplicate key '1' in one object"):
        load_instance(p)


def test_errors_name_a_task_by_its_key(cfg, tmp_path):
    """Tasks keyed from 1: the task keyed '2' (index 1 in the mission) is named by its key."""
    cfg["tasks"] = {str(int(k) + 1): t for k, t in cfg["tasks"].items()}
    cfg["tasks"]["2"]["skillset"]["1"] = 4  # the team has 3 of skill 1
    p = tmp_path / "config.json"
    p.write_text(json.dumps(cfg))
    with pytest.raises(InstanceError, match=r"config.json: task '2' is infeasible: it needs 4 of skill 1"):
        load_instance(p)
    cfg["tasks"]["2"]["skillset"] = {"0": 0, "1": 0, "2": 0}
    p.write_text(json.dumps(cfg))
    with pytest.raises(InstanceError, match=r"tasks\['2'\].skillset: expected at least one non-zero"):
        load_instance(p)
