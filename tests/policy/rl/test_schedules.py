"""The solver as teacher: schedules datasets (generation, resume, validation), the route-following
labeller and behaviour cloning on a dataset."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from hmrta.baselines import BASELINES
from hmrta.core import MissionState, Rules
from hmrta.families import BroadGenerator
from hmrta.rl.schedules import (FORMAT, RouteTeacher, ScheduleError, ScheduleSet, SingleSkillTraining, generate,
                                 make_generator, read_schedules)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from test_schemas import assert_valid, errors  # noqa: E402

SPEC = {"kind": "broad", "min_tasks": 6, "max_tasks": 10}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("sched") / "s.jsonl"
    assert generate(p, SPEC, 3, 4, time_limit=0.3, progress=False) == 4
    return p


def test_broad_generator_is_seeded_and_spans_the_axes():
    g = BroadGenerator(max_tasks=30)
    a, b = g.generate(60, 5), g.generate(60, 5)
    assert [x.to_dict() for x in a] == [x.to_dict() for x in b]
    assert a[0].to_dict() != g.instance(6, 0).to_dict()
    assert {i.skills for i in a} >= {1, 5} and {i.n_species for i in a} >= {1, 3}
    assert all(10 <= i.n_tasks <= 30 and i.infeasibility() is None for i in a)
    assert len({round(i.velocity, 6) for i in a}) > 10


def test_broad_team_scale_grows_every_species_and_leaves_the_default_stream_alone():
    base, grown = BroadGenerator(max_tasks=30), BroadGenerator(max_tasks=30, team_scale=(3.0, 3.0))
    assert BroadGenerator(max_tasks=30, team_scale=(1.0, 1.0)) == base
    for k in range(20):  # the family is drawn first: a factor of 3 triples every species' count
        f0, f1 = base.family(np.random.default_rng(k)), grown.family(np.random.default_rng(k))
        assert f1.counts == tuple(3 * c for c in f0.counts) and f1.tasks == f0.tasks
    a = BroadGenerator(max_tasks=200, min_tasks=40, team_scale=(1.0, 6.0)).generate(30, 7)
    assert max(i.n_agents for i in a) > 25 and all(40 <= i.n_tasks <= 200 for i in a)
    assert [i.to_dict() for i in a[:3]] == [i.to_dict() for i in BroadGenerator(
        max_tasks=200, min_tasks=40, team_scale=(1.0, 6.0)).generate(3, 7)]
    with pytest.raises(ValueError, match="team_scale"):
        BroadGenerator(team_scale=(0.5, 2.0))


def test_single_skill_generator_is_seeded_and_spans_sa_teams():
    g = SingleSkillTraining(max_tasks=30)
    a = [g.instance(5, i) for i in range(40)]
    assert [x.to_dict() for x in a] == [x.to_dict() for x in g.generate(40, 5)]
    assert a[0].to_dict() != g.instance(6, 0).to_dict()
    for i in a:
        assert (i.traits.sum(1) == 1).all() and i.skills == i.n_species in (3, 4, 5)  # one skill per species
        assert 10 <= i.n_tasks <= 30 and i.infeasibility() is None
    assert {bool(i.additive) for i in a} == {True, False}  # SA-AT and SA-BT
    assert make_generator({"kind": "single-skill", "min_tasks": 10, "max_tasks": 30}) == g


def test_routes_replay_exactly_without_a_cap(dataset):
    ss = ScheduleSet(dataset)
    assert len(ss) == 4
    for _, inst, routes, mk in ss.items():
        st = MissionState(inst, seed=0, rules=Rules(max_open=None))
        t = RouteTeacher(routes, BASELINES["greedy-coalition"]())
        while not st.done:
            st.step(t(st))
        assert st.success and t.misses == 0 and math.isclose(st.makespan, mk, rel_tol=1e-6)
        gc = MissionState(inst, seed=0, rules=Rules(max_open=None))
        coalition = BASELINES["greedy-coalition"]()
        while not gc.done:
            gc.step(coalition(gc))
        assert mk <= gc.makespan + 1e-6  # never worse than its greedy incumbent


def test_generation_resumes_and_drops_a_torn_line(dataset, tmp_path):
    p = tmp_path / "r.jsonl"
    p.write_bytes(dataset.read_bytes())
    lines = p.read_text().splitlines()
    p.write_text("\n".join(lines[:3]) + "\n" + lines[3][:17])  # header, 2 rows, a torn third
    h, rows, torn = read_schedules(p)
    assert torn and len(rows) == 2
    assert generate(p, SPEC, 3, 5, time_limit=0.3, progress=False) == 3
    h, rows, torn = read_schedules(p)
    assert not torn and sorted(rows) == [0, 1, 2, 3, 4]
    with pytest.raises(ScheduleError, match="another generator, seed or solver"):
        generate(p, SPEC, 4, 5, time_limit=0.3, progress=False)


def test_dataset_lines_validate_against_the_schema(dataset):
    lines = [json.loads(x) for x in dataset.read_text().splitlines()]
    assert lines[0]["format"] == FORMAT
    assert_valid("hmrta-schedules/1", lines[0])
    for r in lines[1:]:
        assert_valid("hmrta-schedules/1#/$defs/row", r)
    assert errors("hmrta-schedules/1", {**lines[0], "format": "hmrta-schedules/2"})


@pytest.mark.parametrize("text, message", [
    ("", "bad.jsonl: empty; expected a hmrta-schedules/1 header line"),
    ("not json at all {", r"no complete line \(a dataset's lines end with a newline\)"),
    ('{"format": "hmrta-schedules/2"}\n', ":1: expected a header with format"),
    ('{"format": "hmrta-schedules/1", "generator": {"kind": "x", "min_tasks": 1, "max_tasks": 2}, "seed": 1, '
     '"solver": {"time_limit": 1}}\n', ":1: generator.kind"),
    ('{"format": "hmrta-schedules/1", "generator": {"kind": "broad", "min_tasks": 1, "max_tasks": 2}, "seed": 1, '
     '"solver": {"time_limit": 1}}\n{"index": -1, "makespan": 1, "routes": []}\n', ":2: index"),
    ('{"format": "hmrta-schedules/1", "generator": {"kind": "broad", "min_tasks": 1, "max_tasks": 2}, "seed": 1, '
     '"solver": {"time_limit": 1}}\nnot json\n', ":2: not a JSON line"),
    ('{"format": "hmrta-schedules/1", "generator": {"kind": "paper", "min_tasks": 1, "max_tasks": 2, '
     '"team_scale": [2, 3]}, "seed": 1, "solver": {"time_limit": 1}}\n', ":1: generator.team_scale"),
    ('{"format": "hmrta-schedules/1", "generator": {"kind": "broad", "min_tasks": 1, "max_tasks": 2, '
     '"team_scale": [3, 2]}, "seed": 1, "solver": {"time_limit": 1}}\n', ":1: generator.team_scale"),
])
def test_bad_files_are_one_line_errors(tmp_path, text, message):
    p = tmp_path / "bad.jsonl"
    p.write_text(text)
    with pytest.raises(ScheduleError, match=message):
        ScheduleSet(p)


def test_cli_writes_and_resumes(tmp_path, capsys):
    from hmrta.cli import main

    out = tmp_path / "c.jsonl"
    args = ["schedules", "--out", str(out), "--count", "2", "--min-tasks", "5", "--max-tasks", "6",
            "--time-limit", "0.2", "--no-progress"]
    assert main(args) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["solved_now"] == 2 and first["schedules"] == 2
    assert main(args[:4] + ["3"] + args[5:]) == 0
    assert json.loads(capsys.readouterr().out)["solved_now"] == 1
    assert main(args[:-2] + ["0.5", "--no-progress"]) == 2  # another solver setting: refused
    assert "another generator" in capsys.readouterr().err


def test_cli_grows_broad_teams_and_keeps_the_plain_header_at_scale_one(tmp_path, capsys):
    """--team-scale: the header names the factor range (schema-valid), the missions regenerate with
    the grown teams; 1 1 writes the plain broad header; a bad range or another generator exits 2."""
    from hmrta.cli import main

    out = tmp_path / "big.jsonl"
    assert main(["schedules", "--out", str(out), "--count", "2", "--min-tasks", "6", "--max-tasks", "8",
                 "--team-scale", "3", "4", "--time-limit", "0.2", "--no-progress"]) == 0
    capsys.readouterr()
    head = json.loads(out.read_text().splitlines()[0])
    assert head["generator"] == {"kind": "broad", "min_tasks": 6, "max_tasks": 8, "team_scale": [3.0, 4.0]}
    assert_valid("hmrta-schedules/1", head)
    ss = ScheduleSet(out)
    plain = BroadGenerator(max_tasks=8, min_tasks=6)
    for i in ss.indices():
        inst, routes, _ = ss.item(i)
        assert inst.n_agents >= 3 * plain.instance(1, i).n_agents and len(routes) == inst.n_agents
    one = tmp_path / "one.jsonl"
    assert main(["schedules", "--out", str(one), "--count", "1", "--min-tasks", "6", "--max-tasks", "8",
                 "--team-scale", "1", "1", "--time-limit", "0.2", "--no-progress"]) == 0
    capsys.readouterr()
    assert "team_scale" not in json.loads(one.read_text().splitlines()[0])["generator"]
    for bad in (["--team-scale", "4", "3"], ["--team-scale", "2", "3", "--generator", "paper"]):
        assert main(["schedules", "--out", str(tmp_path / "x.jsonl"), "--count", "1", *bad]) == 2
        assert "--team-scale" in capsys.readouterr().err


def test_labels_fanned_out_on_ray_train_exactly_as_in_process(dataset, tmp_path):
    """hmrta train --jobs 2: the teachers' missions are labelled as Ray tasks; the rows (loss,
    labels, route share) and the weights after two iterations equal a run labelling them in its own
    process: on schedules with DAgger, and on greedy-coalition with soft targets; so does the
    validation score, rolled out in parts as Ray tasks. The run shuts its local Ray down."""
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'hmrta[ray]')")
    import ray
    import torch

    from hmrta.rl.train import Trainer

    base = {"name": "fan", "seed": 3, "model": {"d_model": 32, "heads": 4, "ff_hidden": 32, "scale": "mission"},
            "rules": {"max_open": None, "safety": True}, "train": {"iterations": 0},
            "validation": {"every": 100, "seed": 5, "rows": [[6, 2, 8, 3, 3]], "broad": 3, "metric": "ratio"}}
    pre = {"iterations": 2, "instances_per_iter": 4, "lr": 2e-3, "epochs": 1, "batch": 64,
           "teacher": "greedy-coalition"}
    for extra in ({"schedules": str(dataset), "dagger": 0.3}, {"tau": 0.5},
                  {"schedules": str(dataset), "dagger": 0.5, "dagger_teacher": "solver", "dagger_evals": 100}):
        cfg = {**base, "pretrain": {**pre, **extra}}
        runs = []
        for jobs in (1, 2):
            torch.manual_seed(0)
            tr = Trainer(cfg, tmp_path / f"run{jobs}{len(extra)}", device="cpu", log=lambda s: None, jobs=jobs)
            assert tr.fanout.distributed == (jobs > 1)
            rows = [tr.pretrain_step() for _ in range(2)]
            val = tr.validate()
            tr.close()
            assert not ray.is_initialized()
            runs.append((rows, tr.model.state_dict(), val))
        (rows1, w1, v1), (rows2, w2, v2) = runs
        assert rows1 == rows2 and all(r["labels"] > 0 for r in rows1), extra
        assert ("dagger_teacher" in extra) == any("dagger_plan_ratio" in r for r in rows1)  # plans made on Ray
        assert all(torch.equal(w1[k], w2[k]) for k in w1), extra
        assert v1 == v2 and v1["val_success"] == 1.0, extra  # validation rolled out in parts on Ray


def test_labelling_in_process_leaves_the_runs_torch_threads_alone(dataset, tmp_path):
    """hmrta train --jobs 1 (the default) labels in the training process without setting its
    torch threads (a fan-out worker's one thread would slow a run given several)."""
    import torch

    from hmrta.rl.train import Trainer

    cfg = {"name": "threads", "seed": 3, "model": {"d_model": 32, "heads": 4, "ff_hidden": 32, "scale": "mission"},
           "rules": {"max_open": None, "safety": True}, "train": {"iterations": 0},
           "pretrain": {"iterations": 1, "instances_per_iter": 2, "teacher": "greedy-coalition",
                        "schedules": str(dataset)},
           "validation": {"seed": 5, "rows": [[6, 2, 8, 3, 1]]}}
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        Trainer(cfg, tmp_path / "run", device="cpu", log=lambda s: None).pretrain_step()
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_cloning_the_schedules_follows_the_routes(dataset, tmp_path):
    """BC on a schedules dataset labels teacher-driven missions by their routes (route share 1 without
    a cap) and lowers the loss."""
    import torch

    from hmrta.rl.train import Trainer

    torch.manual_seed(0)
    cfg = {"name": "sched", "seed": 1, "model": {"d_model": 32, "heads": 4, "ff_hidden": 32, "scale": "mission"},
           "rules": {"max_open": None, "safety": True},
           "pretrain": {"iterations": 12, "instances_per_iter": 4, "lr": 2e-3, "epochs": 2, "batch": 64,
                        "teacher": "greedy-coalition", "schedules": str(dataset)},
           "train": {"iterations": 0},
           "validation": {"every": 100, "seed": 5, "rows": [[6, 2, 8, 3, 2]], "broad": 2, "metric": "ratio"}}
    tr = Trainer(cfg, tmp_path / "run", device="cpu", log=lambda s: None)
    rows = [tr.pretrain_step() for _ in range(12)]
    assert all(r["route_share"] == 1.0 for r in rows)
    assert np.mean([r["bc_loss"] for r in rows[-3:]]) < np.mean([r["bc_loss"] for r in rows[:3]])
    v = tr.validate()
    assert v["val_makespan"] == v["val_ratio"] and v["val_ratio"] > 0.5


def test_several_schedule_datasets_are_drawn_from_as_one(dataset, tmp_path):
    """pretrain.schedules as a list: the missions come from every file (a single file in a list
    draws exactly as the file alone), and a validation set can hold single-skill missions."""
    from hmrta.rl.train import Trainer, validation_set

    other = tmp_path / "sa.jsonl"
    assert generate(other, {"kind": "single-skill", "min_tasks": 6, "max_tasks": 8}, 2, 3, time_limit=0.2,
                    progress=False) == 3
    cfg = {"name": "two", "seed": 1, "model": {"d_model": 32, "heads": 4, "ff_hidden": 32, "scale": "mission"},
           "rules": {"max_open": None, "safety": True},
           "pretrain": {"iterations": 1, "instances_per_iter": 4, "teacher": "greedy-coalition",
                        "schedules": [str(dataset), str(other)]},
           "train": {"iterations": 0},
           "validation": {"seed": 5, "rows": [[6, 2, 8, 3, 1]], "single_skill": 2}}
    tr = Trainer(cfg, tmp_path / "run", device="cpu", log=lambda s: None)
    names = {inst.name.split("_")[0] for inst, _ in tr.schedule_items(40)}
    assert any(n.startswith("single-skill") for n in names) and any(n.startswith("broad") for n in names)
    assert [i.name.split("_")[0] for i in validation_set(tr.cfg)] == ["MA-AT", "single-skill", "single-skill"]
    one = [Trainer({**cfg, "pretrain": {**cfg["pretrain"], "schedules": x}}, tmp_path / f"r{k}", device="cpu",
                   log=lambda s: None).schedule_items(6) for k, x in enumerate((str(dataset), [str(dataset)]))]
    assert [i.to_dict() for i, _ in one[0]] == [i.to_dict() for i, _ in one[1]]


def test_validation_set_can_hold_every_mission_family():
    """validation.families: that many missions of every family row up to 50 tasks, drawn at the
    validation seed (the same missions each time, none of the suite's test missions)."""
    from hmrta.families import family_suite
    from hmrta.rl.config import TrainConfig
    from hmrta.rl.train import validation_set

    cfg = TrainConfig.from_dict({"validation": {"seed": 7, "rows": [[6, 2, 8, 3, 1]], "families": 2}})
    rows = family_suite(max_tasks=50)
    got = validation_set(cfg)[1:]  # after the MA-AT row's mission
    assert len(rows) == 12 and len(got) == 2 * len(rows)
    assert [i.name for i in got] == [f"{r.key}_s7_{k:03d}" for r in rows for k in range(2)]
    assert [i.to_dict() for i in got] == [i.to_dict() for i in validation_set(cfg)[1:]]
    test = [i.to_dict() for r in rows for i in r.generator().generate(2, 1000)]
    assert not any(i.to_dict() in test for i in got)
    with pytest.raises(ValueError, match="validation.families"):
        TrainConfig.from_dict({"validation": {"families": -1}})


def test_generated_missions_join_the_schedules_labelled_by_the_teacher(dataset, tmp_path):
    """pretrain.generated: each iteration also clones that many missions of train.distribution (here
    larger than the dataset's), labelled by the teacher; without schedules the key is an error."""
    from hmrta.rl.config import TrainConfig
    from hmrta.rl.train import Trainer

    cfg = {"name": "gen", "seed": 1, "model": {"d_model": 32, "heads": 4, "ff_hidden": 32, "scale": "mission"},
           "rules": {"max_open": None, "safety": True},
           "pretrain": {"iterations": 1, "instances_per_iter": 2, "teacher": "greedy-coalition",
                        "schedules": str(dataset), "generated": 2},
           "train": {"iterations": 0, "distribution": {"generator": "broad", "tasks": [30, 40],
                                                       "team_scale": [2, 3]}},
           "validation": {"seed": 5, "rows": [[6, 2, 8, 3, 1]]}}
    tr = Trainer(cfg, tmp_path / "run", device="cpu", log=lambda s: None)
    alone = Trainer({**cfg, "pretrain": {**cfg["pretrain"], "generated": 0}}, tmp_path / "r0", device="cpu",
                    log=lambda s: None)
    with_gen, without = tr.pretrain_step(), alone.pretrain_step()
    # the same dataset missions (no DAgger: their labels are their routes), plus two of 30-40 tasks
    assert with_gen["route_share"] == without["route_share"] == 1.0
    assert with_gen["labels"] >= without["labels"] + 2 * 30
    bad = {**cfg, "pretrain": {k: v for k, v in cfg["pretrain"].items() if k != "schedules"}}
    with pytest.raises(ValueError, match="pretrain.generated"):
        TrainConfig.from_dict(bad)
    with pytest.raises(ValueError, match="team_scale"):
        TrainConfig.from_dict({**cfg, "train": {"distribution": {"generator": "broad", "team_scale": [3, 2]}}})


def test_label_weight_mission_gives_every_mission_one_unit_of_the_loss(dataset, tmp_path):
    """pretrain.label_weight: mission weighs each label 1 / its mission's labels (weights averaging
    1), so a mission of hundreds of decisions counts as much as a small one: the same labels (the
    same missions, routes and DAgger states) enter the loss with other weights."""
    from hmrta.rl.config import TrainConfig
    from hmrta.rl.imitation import mission_weights
    from hmrta.rl.train import Trainer

    w = mission_weights([0, 1, 1, 1, 2, 2])
    assert np.allclose(w, [2.0, 2 / 3, 2 / 3, 2 / 3, 1.0, 1.0]) and math.isclose(w.mean(), 1.0)
    assert len(mission_weights([])) == 0
    cfg = {"name": "w", "seed": 1, "model": {"d_model": 32, "heads": 4, "ff_hidden": 32, "scale": "mission"},
           "rules": {"max_open": None, "safety": True},
           "pretrain": {"iterations": 1, "instances_per_iter": 3, "teacher": "greedy-coalition", "dagger": 0.5,
                        "schedules": str(dataset), "generated": 1},
           "train": {"iterations": 0, "distribution": {"generator": "broad", "tasks": [30, 40]}},
           "validation": {"seed": 5, "rows": [[6, 2, 8, 3, 1]]}}
    rows = {}
    for how in ("label", "mission"):
        tr = Trainer({**cfg, "pretrain": {**cfg["pretrain"], "label_weight": how}}, tmp_path / how, device="cpu",
                     log=lambda s: None)
        rows[how] = tr.pretrain_step()
    assert rows["label"]["labels"] == rows["mission"]["labels"] > 0
    assert rows["label"]["bc_loss"] != rows["mission"]["bc_loss"]
    for bad in ({"label_weight": "task"}, {"label_weight": "mission", "samples": 2}):
        with pytest.raises(ValueError, match="pretrain.label_weight"):
            TrainConfig.from_dict({**cfg, "pretrain": {**cfg["pretrain"], **bad}})


def test_solver_dagger_labels_the_rest_of_a_mission_by_a_plan_from_the_state_the_policy_reached(dataset, tmp_path):
    """pretrain.dagger_teacher: solver: each DAgger mission is driven by the policy to a decision, then
    labelled to its end by a plan from that state (plan_labels): the plan's routes, followed,
    give its makespan, never worse than greedy-coalition's continuation; the run logs the ratio."""
    from hmrta.rl.config import TrainConfig
    from hmrta.rl.imitation import PlanJob, plan_labels
    from hmrta.rl.train import Trainer
    from hmrta.solvers.fromstate import greedy_coalition_continuation

    inst = BroadGenerator(max_tasks=20, min_tasks=15).sample(np.random.default_rng(8))
    st = MissionState(inst, seed=1, rules=Rules(max_open=None))
    gc = BASELINES["greedy"]()  # a weaker driver, so that the plan has room to improve
    for _ in range(6):
        st.step(gc(st))
    before = st.decisions
    done = plan_labels(PlanJob(st, 300, 0, "greedy-coalition", 0.0, {"scale": "mission"}))
    assert st.decisions == before  # the job's state is left as it was
    assert len(done.labels.acts) == done.state.decisions - before > 0  # every decision from there, labelled
    assert done.misses == 0 and done.plan_ratio < 1.0
    assert math.isclose(done.state.makespan / greedy_coalition_continuation(st)[0], done.plan_ratio, rel_tol=1e-12)

    cfg = {"name": "sdag", "seed": 1, "model": {"d_model": 32, "heads": 4, "ff_hidden": 32, "scale": "mission"},
           "rules": {"max_open": None, "safety": True},
           "pretrain": {"iterations": 1, "instances_per_iter": 4, "teacher": "greedy-coalition", "dagger": 1.0,
                        "dagger_teacher": "solver", "dagger_evals": 100, "schedules": str(dataset)},
           "train": {"iterations": 0}, "validation": {"seed": 5, "rows": [[6, 2, 8, 3, 1]]}}
    row = Trainer(cfg, tmp_path / "run", device="cpu", log=lambda s: None).pretrain_step()
    assert row["labels"] > 0 and 0.5 < row["dagger_plan_ratio"] <= 1.0
    with pytest.raises(ValueError, match="pretrain.dagger_teacher: expected teacher or solver"):
        TrainConfig.from_dict({**cfg, "pretrain": {**cfg["pretrain"], "dagger_teacher": "cpsat"}})
