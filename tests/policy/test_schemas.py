"""The published JSON Schemas (docs/schemas/): every schema is valid draft 2020-12, every hmrta-*
format the code writes has one, and what the code writes validates against it: instance files,
solutions of several methods, and state snapshots at many points of a mission. Also the
hmrta-state/1 reader: unknown formats, versions and malformed fields are a SnapshotError naming
the field."""
from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import jsonschema
import pytest
import yaml
from referencing import Registry, Resource

from hmrta.baselines import GREEDY_RULES, CoalitionGreedy, Greedy, RandomPolicy
from hmrta.core import STATE_FORMAT, MissionState, Rules, SnapshotError, parse_rules
from hmrta.generators import ScenarioGenerator
from hmrta.formats import load_instance
from hmrta.instance import InstanceError, instance_from_dict
from hmrta.methods import solve
from hmrta.sim import simulate
from hmrta.solution import Solution, evaluate_routes

ROOT = Path(__file__).resolve().parents[2]
SCHEMAS = ROOT / "docs" / "schemas"
EXAMPLE = ROOT / "policy" / "hmrta" / "data" / "example.yaml"
FORMAT_RE = re.compile(r"\bhmrta-[a-z]+(?:-[a-z]+)*/[0-9]+\b")


def _load() -> dict[str, dict]:
    return {s["$id"]: s for s in (json.loads(p.read_text()) for p in sorted(SCHEMAS.glob("*.schema.json")))}


ALL = _load()
REGISTRY = Registry().with_resources((k, Resource.from_contents(v)) for k, v in ALL.items())


def errors(fmt: str, doc) -> list[str]:
    """Validation errors of doc against the schema of format fmt (``name/1#/$defs/x`` for a part)."""
    v = jsonschema.Draft202012Validator({"$ref": fmt}, registry=REGISTRY)
    return [f"{list(e.absolute_path)}: {e.message[:200]}" for e in v.iter_errors(doc)]


def assert_valid(fmt: str, doc) -> None:
    errs = errors(fmt, doc)
    assert not errs, f"{fmt}: " + "; ".join(errs[:5])


def as_json(d):
    return json.loads(json.dumps(d, allow_nan=False))


# ---------------------------------------------------------------------------------------------
# the schema files themselves
# ---------------------------------------------------------------------------------------------
def test_every_schema_file_is_a_valid_schema_named_by_its_format():
    files = sorted(SCHEMAS.glob("*.schema.json"))
    assert len(files) >= 8 and len(ALL) == len(files)
    for p in files:
        s = json.loads(p.read_text())
        jsonschema.Draft202012Validator.check_schema(s)
        assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema", p.name
        name, version = re.fullmatch(r"(hmrta-[a-z-]+)-([0-9]+)\.schema\.json", p.name).groups()
        assert s["$id"] == f"{name}/{version}", p.name
        assert s["properties"]["format"] == {"const": s["$id"], "description": s["properties"]["format"]["description"]}
        assert s.get("title") and s.get("description"), p.name
    listed = (SCHEMAS / "README.md").read_text()
    for p in files:
        assert p.name in listed, f"docs/schemas/README.md does not list {p.name}"


def test_every_format_the_code_names_has_a_schema():
    used: dict[str, str] = {}
    for base in (ROOT / "policy" / "hmrta", ROOT / "ros2_ws" / "src"):
        for p in base.rglob("*.py"):
            for fmt in FORMAT_RE.findall(p.read_text()):
                used.setdefault(fmt, str(p.relative_to(ROOT)))
    # the scan finds the formats it must (a broken pattern would make this test pass vacuously)
    assert {"hmrta-instance/1", "hmrta-solution/1", "hmrta-state/1", "hmrta-mission/1", "hmrta-board/2",
            "hmrta-choice/1", "hmrta-status/1", "hmrta-rejection/1"} <= set(used)
    missing = {f: where for f, where in used.items() if f not in ALL}
    assert not missing, f"formats without a schema in docs/schemas/: {missing}"


def test_schemas_reject_another_version_and_unknown_fields():
    inst = as_json(yaml.safe_load(EXAMPLE.read_text()))
    assert_valid("hmrta-instance/1", inst)
    assert errors("hmrta-instance/1", {**inst, "format": "hmrta-instance/2"})
    assert errors("hmrta-instance/1", {**inst, "colour": "red"})
    state = MissionState(load_instance(EXAMPLE), seed=1).snapshot()
    assert errors("hmrta-state/1", {**state, "format": "hmrta-state/2"})
    assert errors("hmrta-state/1", {**state, "_seq": 3})  # no private fields
    assert errors("hmrta-state/1", {k: v for k, v in state.items() if k != "rng"})


# ---------------------------------------------------------------------------------------------
# hmrta-instance/1: files written by Instance.save
# ---------------------------------------------------------------------------------------------
GENERATED = [("SA-AT", 9, 3, 20, 3), ("SA-BT", 9, 3, 20, 3), ("MA-AT", 15, 5, 20, 5), ("MA-BT", 6, 3, 8, 3)]


@pytest.mark.parametrize("family", GENERATED, ids=lambda f: f[0])
def test_saved_instances_validate(tmp_path, family):
    for index in range(2):
        inst = ScenarioGenerator(*family).instance(seed=3, index=index)
        path = tmp_path / f"{family[0]}-{index}.yaml"
        inst.save(path)
        assert_valid("hmrta-instance/1", yaml.safe_load(path.read_text()))


def test_builtin_example_validates(tmp_path):
    assert_valid("hmrta-instance/1", yaml.safe_load(EXAMPLE.read_text()))
    load_instance(EXAMPLE).save(tmp_path / "again.yaml")
    assert_valid("hmrta-instance/1", yaml.safe_load((tmp_path / "again.yaml").read_text()))


@pytest.mark.parametrize("path,value", [
    (("velocity",), -1), (("skills",), 0), (("requirement_type",), "some"), (("species",), []),
    (("species", 0, "count"), 0), (("species", 0, "depot"), [0.5, 1.5]), (("species", 0, "traits"), [0, 0, 0, 0, 0]),
    (("tasks", 0, "duration"), -1), (("tasks", 0, "location"), [0.5]), (("tasks", 0, "requirements", 1), -2),
])
def test_schema_and_loader_agree_on_bad_instances(path, value):
    d = yaml.safe_load(EXAMPLE.read_text())
    node = d
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    assert errors("hmrta-instance/1", d)
    with pytest.raises(InstanceError):
        instance_from_dict(d)


# ---------------------------------------------------------------------------------------------
# hmrta-solution/1: solutions of several methods, failed runs, route evaluation
# ---------------------------------------------------------------------------------------------
INST = ScenarioGenerator("MA-AT", 6, 3, 8, 3).instance(seed=5, index=0)


@pytest.mark.parametrize("method,options", [("greedy", {}), ("greedy-coalition", {}), ("random", {})])
def test_solutions_validate(tmp_path, method, options):
    sol = solve(INST, method, 1, **options)
    assert_valid("hmrta-solution/1", as_json(sol.to_dict()))
    sol.save(tmp_path / "sol.json")
    saved = json.loads((tmp_path / "sol.json").read_text())
    assert_valid("hmrta-solution/1", saved)
    assert Solution.from_dict(saved).to_dict() == saved


def test_rl_solutions_validate():
    pytest.importorskip("torch")
    for method, options in (("rl", {}), ("rl-sample", {"samples": 2})):
        sol = solve(INST, method, 1, **options)
        assert_valid("hmrta-solution/1", as_json(sol.to_dict()))


def test_cpsat_solution_validates():
    pytest.importorskip("ortools")
    small = ScenarioGenerator("SA-AT", 4, 2, 4, 2).instance(seed=1, index=0)
    sol = solve(small, "cpsat", 1, time_limit=0.5, workers=1)
    d = as_json(sol.to_dict())
    assert "lower_bound" in d and "status" in d
    assert_valid("hmrta-solution/1", d)


def test_failed_and_evaluated_solutions_validate():
    failed = simulate(INST, Greedy(), 1, Rules(t_max=0.01, safety=True))
    d = as_json(failed.to_dict())
    assert d["success"] is False and d["makespan"] is None and d["failure"]
    assert_valid("hmrta-solution/1", d)
    stopped = simulate(ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(1, 0), Greedy(), 0,
                       Rules(t_max=12.0, safety=True))  # stopped with coalitions under way
    assert stopped.extra["in_progress"]
    assert_valid("hmrta-solution/1", as_json(stopped.to_dict()))
    ok = solve(INST, "greedy", 1)
    assert_valid("hmrta-solution/1", as_json(evaluate_routes(INST, ok.routes, "evaluate", 1).to_dict()))
    # a solution missing a field, or of another version, does not validate
    assert errors("hmrta-solution/1", {k: v for k, v in d.items() if k != "routes"})
    assert errors("hmrta-solution/1", {**d, "format": "hmrta-solution/2"})


# ---------------------------------------------------------------------------------------------
# hmrta-state/1: snapshots at every point of missions (drop_agent included)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("family,pol,rules", [
    (("MA-AT", 9, 3, 12, 3), Greedy, GREEDY_RULES),
    (("SA-BT", 6, 3, 10, 3), lambda: RandomPolicy(4), Rules()),
    (("MA-AT", 15, 5, 20, 5), CoalitionGreedy, Rules(max_open="team", backdate=False, t_max=500.0)),
])
def test_snapshots_validate_throughout_a_mission(family, pol, rules):
    inst = ScenarioGenerator(*family).instance(seed=2, index=1)
    state = MissionState(inst, seed=3, rules=rules)
    policy = pol()
    n = 0
    while True:
        snap = as_json(state.snapshot())
        if n % 3 == 0 or state.done:
            assert_valid("hmrta-state/1", snap)
            assert json.dumps(MissionState.from_snapshot(inst, snap).snapshot()) == json.dumps(snap)
        if state.done:
            break
        state.step(policy(state))
        n += 1
    assert n > 5 and snap["done"] and snap["decider"] is None and snap["mask"] is None


def test_snapshots_validate_after_robot_loss():
    inst = ScenarioGenerator("MA-AT", 9, 3, 12, 3).instance(seed=1, index=0)
    state = MissionState(inst, seed=1, rules=GREEDY_RULES)
    for _ in range(8):
        state.step(Greedy()(state))
    for a in (0, 4, 7):
        state.drop_agent(a)
        snap = as_json(state.snapshot())
        assert_valid("hmrta-state/1", snap)
        assert snap["agents"]["mode"][a] == "lost"
    while not state.done:
        state.step(Greedy()(state))
    assert_valid("hmrta-state/1", as_json(state.snapshot()))


def test_board_stream_headers_and_keyframes_validate():
    """What the board publishes through a mission with dynamic events: every version's header
    (its events are journal records) and every keyframe (header with until, legs, state)."""
    from hmrta.board import MissionBoard, board_header
    from test_board import greedy_turn
    from hmrta.generators import ScenarioGenerator as G

    inst = G("MA-AT", 6, 3, 10, 3).instance(4, 0)
    b = MissionBoard(inst, seed=3, rules=GREEDY_RULES, wait_for_robots=False, tolerance=1e9)
    for a in range(inst.n_agents):
        b.pose(a, *inst.depots[a])
    kinds, keyframes = set(), 0
    for i in range(5000):
        v = b.poll()
        if v is not None:
            head = as_json(board_header(v))
            assert_valid("hmrta-board/2", head)
            assert ("until" in head) == v.keyframe
            kinds |= {ev["type"] for ev in head["ev"]}
            if v.keyframe:
                keyframes += 1
                assert_valid("hmrta-board/2#/$defs/legs", as_json(v.legs))
                assert_valid("hmrta-board/2#/$defs/state", json.loads(v.state_json))
        if b.finished:
            break
        if i == 30:
            b.task_request("add", "op-1", {"location": [0.5, 0.5], "requirements": [1, 0, 0], "duration": 1.0})
            b.lose(2, "test")
        greedy_turn(b)
    assert b.finished and keyframes >= 2
    assert {"start", "choice", "arrival", "advance", "add_task", "drop_agent"} <= kinds


def test_snapshot_fields_are_public():
    inst = load_instance(EXAMPLE)
    state = MissionState(inst, seed=1, rules=Rules(max_open=2))
    for _ in range(4):
        state.step(Greedy()(state))
    snap = state.snapshot()
    assert snap["format"] == STATE_FORMAT == "hmrta-state/1"

    def keys(d, prefix=""):
        for k, v in d.items():
            yield prefix + k
            if isinstance(v, dict):
                yield from keys(v, prefix + k + ".")

    assert not [k for k in keys(snap) if k.split(".")[-1].startswith("_")]
    assert snap["decider"] == state.agent and snap["mask"] == state.mask().tolist()
    assert snap["tasks"]["status"][0] in ("empty", "open", "in_progress", "done", "cancelled")
    assert snap["rules"] == Rules(max_open=2).to_dict()


# ---- the reader: clear errors ------------------------------------------------------------------
def _mid_snapshot():
    inst = load_instance(EXAMPLE)
    state = MissionState(inst, seed=1, rules=GREEDY_RULES)
    for _ in range(6):
        state.step(Greedy()(state))
    return inst, as_json(state.snapshot())


def _set(path, value):
    def f(d):
        node = d
        for k in path[:-1]:
            node = node[k]
        if value is KeyError:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return f


BAD_SNAPSHOTS = [  # (mutation, error message, whether the schema alone rejects it too)
    (_set(("format",), KeyError), "missing field 'format'", True),
    (_set(("format",), "hmrta-state/2"), "unsupported version 'hmrta-state/2'", True),
    (_set(("format",), "hmrta-board/2"), "format: expected 'hmrta-state/1', got 'hmrta-board/2'", True),
    (_set(("format",), 1), "format: expected 'hmrta-state/1'", True),
    (_set(("clock",), "soon"), "clock: expected a finite number", True),
    (_set(("decisions",), -1), "decisions: expected an integer >= 0", True),
    (_set(("done",), 0), "done: expected true or false", True),
    (_set(("decider",), 99), "decider: expected an integer in 0..14 or null", False),
    (_set(("mask",), [True]), "mask: expected null or a list of 21 booleans", False),
    (_set(("mask",), None), "mask: expected a list exactly when a decider is named", True),
    (_set(("queue",), [0, "1"]), "queue[1]: expected an integer in 0..14", True),
    (_set(("stall",), {"commitments": True}), "stall.commitments: expected an integer >= 0", True),
    (_set(("events",), [[1.0]]), "events[0]: expected [time, task id in 0..19]", True),
    (_set(("pool",), [1, 2]), "pool: expected 5 finite numbers", False),
    (_set(("tasks",), KeyError), "missing field 'tasks'", True),
    (_set(("tasks", "status", 2), "busy"), "tasks.status[2]: expected one of empty, open", True),
    (_set(("tasks", "remaining", 0), [1, 2]), "tasks.remaining: expected 20 x 5 finite numbers", False),
    (_set(("tasks", "start", 0), "x"), "tasks.start: expected 20 numbers or nulls", True),
    (_set(("tasks", "members"), []), "tasks.members: expected a list of 20 lists of ids", False),
    (_set(("tasks", "members", 0), [15]), "tasks.members[0][0]: expected an integer in 0..14", False),
    (_set(("agents", "mode"), ["free"]), "agents.mode: expected a list of 15 of free", False),
    (_set(("agents", "target", 0), 20), "agents.target[0]: expected an integer in 0..19 or null", False),
    (_set(("agents", "from", 1), [0.5, None]), "agents.from: expected 15 x 2 finite numbers", True),
    (_set(("agents", "depart", 1), float("inf")), "agents.depart: expected 15 finite numbers", False),
    (_set(("agents", "routes", 2), None), "agents.routes[2]: expected a list of integers", True),
    (_set(("agents", "depot_stops", 2), -1), "agents.depot_stops[2]: expected an integer >= 0", True),
    (_set(("agents",), []), "agents: expected a mapping", True),
    (_set(("rules",), KeyError), "missing field 'rules'", True),
    (_set(("rules", "max_open"), "teams"), "rules.max_open: expected a positive integer", True),
    (_set(("rules", "safety"), "yes"), "rules.safety: expected true or false", True),
    (_set(("rules", "horizon"), 3), "rules.horizon: unknown rule", True),
    (_set(("rules", "t_max"), KeyError), "rules: missing rule 't_max'", True),
    (_set(("rng", "version"), 2), "rng.version: expected 3", True),
    (_set(("rng", "state", 3), -5), "rng.state[3]: expected an integer in 0..4294967295", True),
    (_set(("rng", "state"), [1, 2, 3]), "rng: not a state of Python's random.Random", True),
    (_set(("rng", "gauss_next"), "x"), "rng.gauss_next: expected a finite number", True),
]


@pytest.mark.parametrize("mutate,message,schema_rejects", BAD_SNAPSHOTS, ids=[m for _, m, _ in BAD_SNAPSHOTS])
def test_bad_snapshots_are_a_snapshot_error_naming_the_field(mutate, message, schema_rejects):
    inst, snap = _mid_snapshot()
    assert MissionState.from_snapshot(inst, copy.deepcopy(snap)).snapshot() == snap  # the unmutated one restores
    bad = copy.deepcopy(snap)
    mutate(bad)
    with pytest.raises(SnapshotError, match=re.escape(message)):
        MissionState.from_snapshot(inst, bad)
    # lengths that depend on the instance are beyond a JSON Schema; everything else it rejects too
    assert bool(errors("hmrta-state/1", bad)) == schema_rejects


def test_a_snapshot_with_members_on_an_empty_task_is_refused():
    """Commitments make a task open: an empty task with members does not come from the machine."""
    inst, snap = _mid_snapshot()
    empty = snap["tasks"]["status"].index("empty")
    snap["tasks"]["members"][empty] = [4]
    with pytest.raises(SnapshotError, match=rf"^snapshot tasks.members\[{empty}\]: expected no members for a "
                                            rf"task that is empty, got \[4\]"):
        MissionState.from_snapshot(inst, snap)


@pytest.mark.parametrize("bad", [None, [], "state", 3])
def test_a_snapshot_that_is_not_a_mapping_is_a_snapshot_error(bad):
    with pytest.raises(SnapshotError, match="expected a mapping"):
        MissionState.from_snapshot(load_instance(EXAMPLE), bad)


def test_a_snapshot_of_another_instance_is_refused():
    _, snap = _mid_snapshot()
    other = ScenarioGenerator("MA-AT", 6, 3, 8, 3).instance(seed=5, index=0)
    with pytest.raises(SnapshotError, match=r"^snapshot mask: expected null or a list of 9 booleans"):
        MissionState.from_snapshot(other, snap)


def test_unknown_fields_are_ignored_by_the_reader():
    inst, snap = _mid_snapshot()
    assert MissionState.from_snapshot(inst, {**snap, "comment": "extra"}).snapshot() == snap


def test_parse_rules_round_trips_and_names_the_field():
    for r in (Rules(), Rules(max_open="team"), Rules(max_open=3, safety=False, backdate=False, t_max=40.0)):
        assert parse_rules(as_json(r.to_dict())) == r
        assert_valid("hmrta-state/1#/$defs/rules", as_json(r.to_dict()))
    with pytest.raises(ValueError, match=r"^mission\.rules\.backdate: expected true or false"):
        parse_rules({**Rules().to_dict(), "backdate": 1}, "mission.rules")
    with pytest.raises(ValueError, match=r"^rules: expected a mapping"):
        parse_rules(["max_open"])


# ---------------------------------------------------------------------------------------------
# hmrta-keystore/1, hmrta-robot-key/1: files written by hmrta keys create
# ---------------------------------------------------------------------------------------------
def test_keystore_files_validate(tmp_path):
    keys = pytest.importorskip("hmrta.keys")
    keys.create_keystore(tmp_path / "ks", ["robot_0", "robot_1"])
    store = json.loads((tmp_path / "ks" / "keys.json").read_text())
    assert_valid("hmrta-keystore/1", store)
    assert errors("hmrta-keystore/1", {**store, "robots": {"robot_0": "00"}})
    for robot in ("robot_0", "robot_1"):
        assert_valid("hmrta-robot-key/1", json.loads(keys.robot_key_path(tmp_path / "ks", robot).read_text()))


def test_bench_bound_and_mapping_outputs_validate(tmp_path, capsys):
    """hmrta bench's results.json (also with a dynamic row and a paired comparison), hmrta bound
    --json and convert's robot mapping validate; so do the committed results files."""
    from hmrta.cli import main

    ctas = ROOT / "tests" / "policy" / "data" / "ctas_small"
    out = tmp_path / "res"
    assert main(["bench", str(EXAMPLE), "--methods", "greedy,greedy-coalition", "--compare", "greedy-coalition,greedy",
                 "--bounds", "--out", str(out), "--no-progress"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["format"] == "hmrta-bench/1" and results["rows"][0]["comparisons"]
    assert_valid("hmrta-bench/1", results)
    assert errors("hmrta-bench/1", {**results, "format": "hmrta-bench/2"})
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(f"format: hmrta-scenario/1\ninstance: {EXAMPLE}\nevents:\n"
                        "  - {t: 4.0, type: add_task, id: extra, location: [0.3, 0.6], requirements: [1, 0, 1, 0, 0], "
                        "duration: 2}\n  - {t: 6.0, type: lose_robot, robot: 3}\n")
    assert main(["bench", str(scenario), "--methods", "greedy", "--out", str(tmp_path / "dyn"), "--no-progress"]) == 0
    dyn = json.loads((tmp_path / "dyn" / "results.json").read_text())
    assert dyn["rows"][0]["results"]["greedy"].get("dynamic")
    assert_valid("hmrta-bench/1", dyn)
    mixed = tmp_path / "mixed"  # a row of missions of different sizes: each count that differs, as low-high
    assert main(["bench", str(EXAMPLE), str(ctas), "--methods", "greedy", "--out", str(mixed), "--no-progress"]) == 0
    rows = json.loads((mixed / "results.json").read_text())
    assert any(isinstance(x, str) for x in rows["rows"][0]["size"])
    assert_valid("hmrta-bench/1", rows)
    sol = tmp_path / "sol.json"
    assert main(["solve", str(EXAMPLE), "--method", "greedy", "--out", str(sol), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["bound", str(EXAMPLE), str(sol), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["format"] == "hmrta-bound/1" and report["solutions"]
    assert_valid("hmrta-bound/1", report)
    assert main(["convert", str(ctas), "--out", str(tmp_path / "ctas.yaml")]) == 0
    assert_valid("hmrta-robot-mapping/1", json.loads((tmp_path / "ctas.mapping.json").read_text()))
    committed = sorted((ROOT / "docs" / "results").glob("*/results.json"))
    assert len(committed) >= 10
    for p in committed:
        assert not errors("hmrta-bench/1", json.loads(p.read_text())), p
