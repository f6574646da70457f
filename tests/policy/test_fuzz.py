"""Every file the CLI reads, fuzzed (issue 18, point 1): mutated instance YAML, CTAS-D configs,
routes, solutions, checkpoints and training configs end in success (exit 0/3) or in exit 2 with
one line naming the file, within a time bound; the resource-heavy cases (deep nesting, YAML alias
bombs, FIFOs) in a subprocess under a memory limit. The long run is benchmarks/fuzz_inputs.py."""
from __future__ import annotations

import io
import json
import os
import time

import pytest
import torch

import fuzz_cases as fz
from hmrta.cli import main
from hmrta.reading import InputError, MAX_ALIAS_NODES, parse_json, parse_yaml
from hmrta.rl.checkpoint_info import CheckpointError

IN_PROCESS_CASES = 450
SEED = 18


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    with fz.one_thread():
        yield fz.make_seeds(tmp_path_factory.mktemp("seeds"))


def _bad(outcomes):
    return "\n".join(f"{o.case.describe()}: {o.outcome} rc={o.rc} {o.seconds:.2f}s\n{o.detail[-1500:]}"
                     for o in outcomes if o.outcome not in fz.GOOD)


def test_fuzzed_inputs_in_process(seeds, tmp_path):
    cases = fz.generate(IN_PROCESS_CASES, SEED, seeds)
    assert {c.fmt for c in cases} == set(fz.FORMATS)
    outcomes = [fz.run_case(c, seeds, tmp_path / f"c{c.id}") for c in cases]
    assert not _bad(outcomes), _bad(outcomes)
    counts = {k: sum(o.outcome == k for o in outcomes) for k in fz.GOOD}
    assert counts["ok"] >= 10 and counts["user-error"] >= 200, counts  # both paths are exercised
    named = [o.names_field for o in outcomes if o.names_field is not None]
    assert sum(named) >= 0.9 * len(named), fz.summary(outcomes)  # structural refusals name the field


HEAVY = [  # (format, kind, data builder)
    ("instance", "deep-nesting", lambda s: b"[" * 100_000 + b"]" * 100_000),
    ("instance", "deep-nesting", lambda s: b"".join(b"  " * i + b"- \n" for i in range(3000))),
    ("instance", "alias-bomb", lambda s: fz._alias_bomb(_Pick("whole"), s)),
    ("instance", "alias-bomb", lambda s: fz._alias_bomb(_Pick("name"), s)),
    ("instance", "alias-bomb", lambda s: fz._alias_bomb(_Pick("recursive"), s)),
    ("ctas", "deep-nesting", lambda s: b'{"a":' * 100_000 + b"1" + b"}" * 100_000),
    ("routes", "deep-nesting", lambda s: b'{"routes": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"),
    ("solution", "deep-nesting", lambda s: b"[" * 100_000 + b"]" * 100_000),
    ("train-config", "alias-bomb", lambda s: fz._alias_bomb(_Pick("whole"), s)),
    ("train-config", "deep-nesting", lambda s: b"train: " + b"[" * 100_000 + b"]" * 100_000),
    ("instance", "fifo", None),
    ("solution", "fifo", None),
    ("checkpoint", "fifo", None),
]


class _Pick:
    """A stand-in for random.Random whose choice() returns a fixed value (the builders above)."""

    def __init__(self, value):
        self.value = value

    def choice(self, options):
        return self.value if self.value in options else options[0]


@pytest.mark.parametrize("fmt,kind,build", HEAVY, ids=[f"{f}-{k}-{i}" for i, (f, k, _) in enumerate(HEAVY)])
def test_heavy_inputs_in_a_subprocess(seeds, tmp_path, fmt, kind, build):
    """Deep nesting, alias bombs and FIFOs: exit 2 naming the file, under 2 GB and 10 s."""
    data = None if build is None else build(seeds.of(fmt)[0])
    case = fz.Case(0, fmt, kind, data, heavy=True)
    o = fz.run_case(case, seeds, tmp_path / "case")
    assert o.outcome == "user-error", f"{o.outcome} rc={o.rc} {o.seconds:.1f}s\n{o.detail}"


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy-pickle"])
def test_checkpoint_that_would_run_a_command_is_refused(tmp_path, legacy):
    from hmrta.rl.inference import load_policy
    from hmrta.rl.train import DEFAULTS, Trainer, deep_update

    marker = tmp_path / "PWNED"
    ck = tmp_path / "evil.pt"
    ck.write_bytes(fz.malicious_checkpoint(marker, legacy=legacy))
    with pytest.raises(CheckpointError, match="refused: its pickle asks for posix.system" if not legacy
                       else "not a readable hmrta checkpoint|refused"):
        load_policy(ck)
    cfg = deep_update(DEFAULTS, {"model": {"d_model": 16, "heads": 2, "ff_hidden": 16},
                                 "validation": {"rows": [[2, 1, 2, 1, 1]]}})
    tr = Trainer(cfg, tmp_path / "run", device="cpu", log=lambda s: None)
    with pytest.raises(CheckpointError):
        tr.load(ck)
    err = io.StringIO()
    import contextlib

    inst = fz.ROOT / "policy" / "hmrta" / "data" / "example.yaml"
    with contextlib.redirect_stderr(err):
        assert main(["solve", str(inst), "--method", "rl", "--checkpoint", str(ck)]) == 2
    assert err.getvalue().count("\n") == 1 and str(ck) in err.getvalue()
    assert not marker.exists()  # the command never ran


@pytest.mark.parametrize("fmt", ["instance", "ctas", "routes", "solution", "train-config"])
def test_non_utf8_text_names_the_byte_offset(seeds, tmp_path, fmt):
    data = seeds.of(fmt)[0]
    data = data[:37] + b"\xff" + data[37:]
    case = fz.Case(0, fmt, "non-utf8", data)
    argv, target = fz.materialise(case, seeds, tmp_path)
    rc, _, err, _ = fz.run_in_process(argv)
    assert rc == 2 and err == f"hmrta: error: {target}: not UTF-8 text (byte offset 37)\n", err


def test_yaml_alias_bomb_is_refused_before_it_is_expanded():
    bomb = fz._alias_bomb(_Pick("whole"), b"").decode()
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=f"aliases expand the document by .* at most {MAX_ALIAS_NODES}"):
        parse_yaml(bomb, "b.yaml")
    assert time.perf_counter() - t0 < 1.0
    with pytest.raises(InputError, match="an alias refers to a node that contains it"):
        parse_yaml("a: &x [1, *x]\n", "r.yaml")
    # a few aliases (a config reusing a value) are fine
    assert parse_yaml("a: &x [1, 2]\nb: *x\n", "ok.yaml") == {"a": [1, 2], "b": [1, 2]}


@pytest.mark.parametrize("text,expect", [
    ("[" * 40 + "]" * 40, "nested more than 32 levels deep"),
    ("[" * 100_000 + "]" * 100_000, "nested more than 32 levels deep"),
    ('{"a": ' + "1" * 5000 + "}", "invalid JSON (an integer of more than 4300 digits"),
    ("[1, 2", "x.json:1: invalid JSON"),
])
def test_json_limits(text, expect):
    with pytest.raises(InputError, match=expect.replace("(", r"\(")):
        parse_json(text, "x.json")
    assert parse_json("[" * 30 + "]" * 30, "ok.json") is not None


def test_yaml_limits():
    with pytest.raises(InputError, match=r"y.yaml:1: invalid YAML \(nested more than 32 levels deep\)"):
        parse_yaml("[" * 100_000 + "]" * 100_000, "y.yaml")
    with pytest.raises(InputError, match=r"^y.yaml: invalid YAML \(an integer of more than 4300 digits\)$"):
        parse_yaml("a: " + "1" * 5000 + "\n", "y.yaml")
    with pytest.raises(InputError, match="could not determine a constructor"):
        parse_yaml("a: !!python/object/apply:os.system ['true']\n", "y.yaml")
    with pytest.raises(InputError, match="a mapping key must be a scalar"):
        parse_yaml("{[1]: 2}\n", "y.yaml")


def test_the_fuzzer_is_seeded(seeds):
    a = fz.generate(40, 5, seeds, heavy_share=0.2)
    b = fz.generate(40, 5, seeds, heavy_share=0.2)
    c = fz.generate(40, 6, seeds, heavy_share=0.2)
    assert [(x.fmt, x.kind, x.data) for x in a] == [(x.fmt, x.kind, x.data) for x in b]
    assert [x.data for x in a] != [x.data for x in c]


def test_classification_catches_what_the_fuzzer_must_find(tmp_path):
    """The harness itself: a traceback, a second stderr line, a message without the file name or a
    slow case are failures."""
    case, target = fz.Case(0, "instance", "x", b""), tmp_path / "f.yaml"
    assert fz.classify(case, 0, "", 0.1, target).outcome == "ok"
    assert fz.classify(case, 2, f"hmrta: error: {target}: bad\n", 0.1, target).outcome == "user-error"
    assert fz.classify(case, 2, f"warning\nhmrta: error: {target}: bad\n", 0.1, target).outcome == "bad-message"
    assert fz.classify(case, 2, "hmrta: error: something: bad\n", 0.1, target).outcome == "bad-message"
    assert fz.classify(case, 1, "Traceback ...\nhmrta: internal error: X\n", 0.1, target).outcome == "internal"
    assert fz.classify(case, "crash", "Traceback", 0.1, target).outcome == "internal"
    assert fz.classify(case, "timeout", "", 10.0, target).outcome == "hang"
    assert fz.classify(case, 0, "", fz.TIME_LIMIT + 1, target).outcome == "slow"


def test_shipped_checkpoints_load_weights_only():
    """The shipped checkpoints hold only weights and plain data (nothing else may be unpickled)."""
    names = sorted(p.name for p in (fz.ROOT / "policy" / "hmrta" / "checkpoints").glob("*.pt"))
    assert {"default.pt", "coalition-open.pt", "broad.pt", "coalition-team.pt", "compact.pt"} <= set(names)
    for name in names:
        p = fz.ROOT / "policy" / "hmrta" / "checkpoints" / name
        ck = torch.load(p, weights_only=True)
        assert isinstance(ck["model"], dict) and all(isinstance(v, torch.Tensor) for v in ck["model"].values())
        assert isinstance(ck["config"], dict) and os.path.getsize(p) > 0
        json.dumps(ck["config"])  # plain data


def test_fuzzed_training_checkpoints_resume_or_are_refused(tmp_path):
    """`hmrta train --resume` on a mutated training checkpoint (weights, optimiser state, counters,
    random streams): it resumes and trains, or it is a CheckpointError that leaves the trainer as
    it was."""
    import copy
    import random

    from hmrta.rl.train import DEFAULTS, Trainer, deep_update

    cfg = deep_update(DEFAULTS, {"model": {"d_model": 16, "heads": 2, "ff_hidden": 16},
                                 "train": {"instances_per_iter": 1, "rollouts": 2, "amp": False,
                                           "distribution": {"tasks": [2, 3], "species": [1, 2],
                                                            "per_species": [1, 2]}},
                                 "validation": {"rows": [[2, 1, 2, 1, 1]]}})
    with fz.one_thread():
        tr = Trainer(cfg, tmp_path / "run", device="cpu", log=lambda s: None)
        tr.train_step()
        tr.save(tmp_path / "last.pt")
        ck = torch.load(tmp_path / "last.pt", weights_only=True)
        r = random.Random(11)
        loaded = refused = 0
        for i in range(30):
            c = copy.deepcopy(ck)
            nodes = [n for n in fz._nodes(c) if n[0] in ("optimizer", "np_rng", "iteration", "episodes", "best_val",
                                                         "ema", "model", "torch_gen")]
            kind, path = fz.mutate_structure(r, c, nodes) if i else ("none", ())  # case 0: the file itself
            f = tmp_path / f"m{i}.pt"
            torch.save(c, f)
            before = {k: v.clone() for k, v in tr.model.state_dict().items()}
            try:
                tr.load(f)
            except CheckpointError as e:
                refused += 1
                assert str(f) in str(e) and "\n" not in str(e)
                assert all(torch.equal(before[k], v) for k, v in tr.model.state_dict().items()), (kind, path)
                continue
            loaded += 1
            tr.train_step()  # what loaded, trains
    assert refused >= 10 and loaded >= 1, (refused, loaded)
