"""Mission families (docs/families.md): seeded, feasible, each with its defining property, benchable."""
from __future__ import annotations

import hashlib
import itertools
from pathlib import Path

import numpy as np
import pytest
import yaml
from hmrta import methods
from hmrta.cli import main
from hmrta.families import (
    DEV_SEED,
    FAMILY_NAMES,
    FAMILY_ROWS,
    MAX_SKILLS,
    FamilyGenerator,
    family_suite,
)
from hmrta.generators import ScenarioGenerator, TrainingGenerator
from hmrta.instance import instance_from_dict

TEST_SEED = 1000  # the bench default
ROWS = {g.name: g for g in FAMILY_ROWS}
CONFIGS = sorted((Path(__file__).resolve().parents[2] / "policy" / "configs").glob("*.yaml"))


def _family(name: str) -> list[FamilyGenerator]:
    return [g for g in FAMILY_ROWS if g.family == name]


def _draw(name: str, n: int = 30) -> list:
    return [i for g in _family(name) for i in g.generate(n, TEST_SEED)]


def test_rows_cover_the_axes_within_the_policy_limits():
    from hmrta.rl.features import K_MAX

    assert MAX_SKILLS == K_MAX
    assert len(ROWS) == len(FAMILY_ROWS)  # unique row names
    assert set(FAMILY_NAMES) >= {"homog", "few-large", "many-small", "multi-unit", "binary", "clustered",
                                 "fast-robots", "slow-robots", "long-tasks", "shared-depot"}
    assert all(1 <= g.skills <= K_MAX and g.agents <= 40 for g in FAMILY_ROWS)
    assert min(g.tasks for g in FAMILY_ROWS) == 10 and max(g.tasks for g in FAMILY_ROWS) == 100
    assert {g.skills for g in FAMILY_ROWS} >= {1, 3, 4, 5}


@pytest.mark.parametrize("gen", FAMILY_ROWS, ids=lambda g: g.name)
def test_same_seed_same_instances_other_seed_other_instances(gen):
    a = [i.to_yaml() for i in gen.generate(3, TEST_SEED)]
    assert a == [i.to_yaml() for i in gen.generate(3, TEST_SEED)]
    assert gen.instance(TEST_SEED, 2).to_dict() | {"name": ""} == gen.generate(3, TEST_SEED)[2].to_dict() | {"name": ""}
    b = [i.to_yaml() for i in gen.generate(3, DEV_SEED)]
    assert all(x != y for x, y in zip(a, b))
    assert len(set(a)) == 3  # instances of one set differ


def test_generated_sets_are_pinned():
    """The published tables depend on these exact instances: generation must not drift."""
    h = hashlib.sha256()
    for g in FAMILY_ROWS:
        h.update(g.instance(TEST_SEED, 0).to_yaml().encode())
    assert h.hexdigest() == "1e6a002f99a12ec59ee7c5dfdf395782ccbe5a9c8e7525d55d80ab2e73b4f1ff"


@pytest.mark.parametrize("gen", FAMILY_ROWS, ids=lambda g: g.name)
def test_every_instance_is_valid_and_feasible(gen):
    for inst in gen.generate(250, DEV_SEED):
        again = instance_from_dict(inst.to_dict())  # the loader's validation: unit square, non-zero rows, feasible
        assert again.infeasibility() is None
        assert (inst.n_agents, inst.n_species, inst.n_tasks, inst.skills) == (gen.agents, gen.species, gen.tasks,
                                                                             gen.skills)
        assert np.array_equal(inst.requirements, np.round(inst.requirements))
        assert np.array_equal(inst.species_traits, np.round(inst.species_traits))
        assert gen.duration[0] <= inst.durations.min() and inst.durations.max() < gen.duration[1]


def test_homog_is_one_species_of_identical_one_skill_robots():
    for inst in _draw("homog"):
        assert inst.n_species == 1 and inst.skills == 1 and inst.additive and inst.n_agents >= 20
        assert inst.requirements.min() >= 1 and inst.requirements.max() <= 5
        assert inst.requirements.max() >= 4  # tasks needing several robots


def test_team_composition_families():
    for inst in _draw("few-large"):
        assert inst.n_species == 2 and min(s.count for s in inst.species) >= 8
    for inst in _draw("many-small"):
        assert inst.n_species >= 10 and max(s.count for s in inst.species) <= 2
        assert len({s.traits for s in inst.species}) == inst.n_species  # distinct species


def test_multi_unit_has_capabilities_and_requirements_of_several_units():
    insts = _draw("multi-unit")
    assert all(i.requirements.max() >= 3 for i in insts)
    assert max(i.species_traits.max() for i in insts) == 3
    assert max(i.requirements.max() for i in insts) == 4
    assert all(i.additive for i in insts)
    # the paper rows never exceed 1 (traits) or 2 (requirements)
    assert all(i.species_traits.max() <= 1 and i.requirements.max() <= 2 for i in _draw("clustered"))


def test_binary_family_has_binary_tasks():
    for inst in _draw("binary"):
        assert inst.requirement_type == "binary" and set(np.unique(inst.requirements)) <= {0.0, 1.0}


def _mean_nearest_neighbour(locs: np.ndarray) -> float:
    d = np.linalg.norm(locs[:, None] - locs[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(d.min(1).mean())


def test_clustered_locations_are_tighter_than_uniform():
    clustered = np.mean([_mean_nearest_neighbour(i.task_locations) for i in _draw("clustered")])
    uniform = np.mean([_mean_nearest_neighbour(i.task_locations) for i in ROWS["shared-depot-50"].generate(30, 1000)])
    assert clustered < 0.5 * uniform


def test_time_scale_families():
    span = np.sqrt(2)  # the unit square's diagonal
    for inst in _draw("fast-robots"):  # crossing the map is cheaper than a typical task
        assert span / inst.velocity < inst.durations.mean()
    for inst in _draw("slow-robots"):  # crossing the map costs several task durations
        assert span / inst.velocity > 4 * inst.durations.max()
    for inst in _draw("long-tasks"):
        assert inst.durations.min() >= 10 and inst.durations.max() < 30


def test_depots_shared_or_separate():
    for inst in _draw("shared-depot"):
        assert len({s.depot for s in inst.species}) == 1 and inst.n_species > 1
    for inst in _draw("few-large") + _draw("many-small"):
        assert len({s.depot for s in inst.species}) == inst.n_species


def test_family_sets_share_no_instance_with_paper_rows_or_training():
    """Salted streams: same seed as a paper row of the same shape, yet other missions; and no family
    instance appears among the training streams and validation sets of any training config."""
    fam = ROWS["fast-robots-50"]  # same sizes and trait / requirement kinds as MA-AT (25,5,50,5)
    for seed in (TEST_SEED, DEV_SEED):
        paper = ScenarioGenerator("MA-AT", 25, 5, 50, 5).generate(10, seed)
        mine = fam.generate(10, seed)
        assert not {t.location for i in paper for t in i.tasks} & {t.location for i in mine for t in i.tasks}
    seen: set = set()
    cfg_seeds = set()
    for path in CONFIGS:
        cfg = yaml.safe_load(path.read_text())
        cfg_seeds |= {cfg["seed"], cfg["validation"]["seed"]}
        seen |= {t.location for i in itertools.islice(TrainingGenerator().stream(cfg["seed"]), 100) for t in i.tasks}
        v = cfg["validation"]
        for a, s, m, k, n in v["rows"]:
            seen |= {t.location for i in ScenarioGenerator("MA-AT", a, s, m, k).generate(n, v["seed"]) for t in i.tasks}
    assert CONFIGS and not cfg_seeds & {TEST_SEED, DEV_SEED}
    for g in FAMILY_ROWS:
        for seed in (TEST_SEED, DEV_SEED):
            assert not seen & {t.location for i in g.generate(10, seed) for t in i.tasks}, g.name


@pytest.mark.parametrize("gen", FAMILY_ROWS, ids=lambda g: g.name)
def test_greedy_methods_solve_every_family(gen):
    for inst in gen.generate(3, TEST_SEED):
        for m in ("greedy", "greedy-coalition"):
            sol = methods.solve(inst, m, seed=0)
            assert sol.success and sol.makespan > 0, (gen.name, m)


def test_bad_parameters_are_rejected():
    with pytest.raises(ValueError, match="skills"):
        FamilyGenerator("x", 10, (3,), 6)
    with pytest.raises(ValueError, match="counts"):
        FamilyGenerator("x", 10, (3, 3), 3, traits="one-hot")
    with pytest.raises(ValueError, match="unknown family 'nope'"):
        family_suite(["nope"])
    assert [r.key for r in family_suite(["homog"], max_tasks=50)] == ["homog-50"]


def test_bench_suite_families_writes_every_family(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # the suite's default output folder: bench-families (never docs/results/)
    assert main(["bench", "--suite", "families", "--count", "2", "--methods", "greedy", "--no-progress"]) == 0
    md = (tmp_path / "bench-families" / "results.md").read_text()
    assert md.startswith("- command: `hmrta bench --suite families")  # the provenance header comes first
    assert "\n### Families (2 instances per row, seed 1000)\n" in md
    assert "| family | kn, ks, km, kb | method |" in md and "paper" not in md
    for g in FAMILY_ROWS:
        size = ", ".join(map(str, (g.agents, g.species, g.tasks, g.skills)))
        assert f"| {g.name} | {size} | Greedy | 100% |" in md
    capsys.readouterr()
    assert main(["bench", "--suite", "families", "--tables", "homog,nope", "--count", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown family 'nope'" in err[0]
