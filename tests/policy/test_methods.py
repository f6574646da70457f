"""The method table: every record is truthful (entry points exist and take exactly the declared
options), option errors name the method, shorthands parse in one place, rules are read without
torch, and the core's modules import each other without cycles."""
from __future__ import annotations

import ast
import inspect
import io
import math
import pickle
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from hmrta import methods
from hmrta.baselines import COALITION_RULES, GREEDY_RULES
from hmrta.core import Rules
from hmrta.formats import load_instance
from hmrta.generators import ScenarioGenerator
from hmrta.methods import METHODS, MethodError
from hmrta.sim import simulate

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "policy" / "hmrta" / "data" / "example.yaml"
CHECKPOINTS = sorted((ROOT / "policy" / "hmrta" / "checkpoints").glob("*.pt"))


@pytest.mark.parametrize("name", list(METHODS))
def test_entry_points_take_exactly_the_declared_options(name):
    m = METHODS[name]
    pytest.importorskip(m.needs[0]) if m.needs else None
    params = inspect.signature(methods._resolve(m.solve)).parameters
    assert set(params) - {"inst", "seed", "progress"} == {o.name for o in m.options}
    for o in m.options:  # an option left out runs at the default --help states (None: the entry resolves it)
        assert params[o.name].default in (o.default, None), o.name
    if m.decide is not None:
        live = inspect.signature(methods._resolve(m.decide)).parameters
        assert set(live) - {"seed"} == {o.name for o in m.options if o.live}
        assert all(live[o.name].default in (o.default, None) for o in m.options if o.live)


def test_option_errors_name_the_method():
    inst = load_instance(EXAMPLE)
    with pytest.raises(MethodError, match="method greedy takes no option 'time_limit'"):
        methods.solve(inst, "greedy", time_limit=3)
    with pytest.raises(MethodError, match=r"rl-sample: option samples: expected an integer in \[1, 10000\], got 0"):
        methods.solve(inst, "rl-sample", samples=0)
    with pytest.raises(MethodError, match=r"rl-s10001: option samples: expected an integer in \[1, 10000\]"):
        methods.solve(inst, "rl-s10001")  # (the spec as written)
    for bad in (math.inf, -math.inf, math.nan):
        with pytest.raises(MethodError, match="rl-sample: option temperature: expected a finite number >= 0.01"):
            methods.solve(inst, "rl-sample", temperature=bad)
        with pytest.raises(MethodError, match=r"cpsat: option time_limit \(--time-limit\): expected a finite number >= 0.01"):
            methods.solve(inst, "cpsat", time_limit=bad)
    with pytest.raises(MethodError, match="cpsat: option workers: expected int"):
        methods.solve(inst, "cpsat", workers=1.5)
    with pytest.raises(MethodError, match="unknown method 'greedy2'"):
        methods.solve(inst, "greedy2")
    with pytest.raises(MethodError, match="method rl-sample takes no option 'samples'"):
        methods.decider("rl-sample", samples=4)  # offline-only option
    with pytest.raises(MethodError, match="method cpsat has no per-decision form"):
        methods.decider("cpsat")


def test_shorthand_parses_in_one_place_and_labels_results():
    assert methods.parse("rl-s10") == ("rl-sample", {"samples": 10})
    assert methods.parse("greedy") == ("greedy", {})
    assert methods.label("rl-sample", {"samples": 4}) == "rl-s4"
    assert methods.label("rl-sample") == "rl-s10"
    with pytest.raises(MethodError):
        methods.parse("rl-sx")
    for spec in ("rl-s0", "rl-s10001", "rl-s0@broad"):  # no method, offline or live (ROS agents, boards)
        with pytest.raises(MethodError, match=r"rl-s\d+: option samples: expected an integer in \[1, 10000\]"):
            methods.parse(spec)
    with pytest.raises(MethodError, match="rl-s0"):
        methods.decider("rl-s0")
    with pytest.raises(MethodError, match=r"^@broad: expected a method before '@' \(METHOD@CHECKPOINT"):
        methods.parse("@broad")  # (it said: unknown method '')
    sol = methods.solve(load_instance(EXAMPLE), "random", seed=3)
    assert sol.method == "random"


def test_options_for_keeps_what_each_method_takes():
    shared = {"checkpoint": "x.pt", "time_limit": 5.0}
    assert methods.options_for("greedy", shared) == {}
    assert methods.options_for("rl-s4", shared) == {"checkpoint": "x.pt"}
    assert methods.options_for("cpsat", shared) == {"time_limit": 5.0}


def test_baseline_rules_and_live_form():
    assert methods.rules("greedy") == GREEDY_RULES
    decide, rules = methods.decider("greedy-coalition")
    assert rules == COALITION_RULES and rules.max_open == "team" and callable(decide)
    # the method's offline solve runs under the same rules as its live form
    inst = ScenarioGenerator("MA-AT", 50, 5, 50, 5).generate(1, 3)[0]
    sol = methods.solve(inst, "greedy-coalition")
    assert sol.makespan == simulate(inst, decide, 0, COALITION_RULES).makespan
    assert sol.makespan != simulate(inst, decide, 0, GREEDY_RULES).makespan


def test_bench_variant_follows_a_baselines_rules(monkeypatch):
    from hmrta import baselines, bench

    before = {m: bench.method_variant(m, {}) for m in ("greedy", "greedy-coalition", "portfolio", "rl")}
    monkeypatch.setattr(baselines, "COALITION_RULES", GREEDY_RULES)
    after = {m: bench.method_variant(m, {}) for m in before}
    assert after["greedy-coalition"] != before["greedy-coalition"]
    assert after["portfolio"] != before["portfolio"]  # greedy-coalition is one of its candidates
    assert after["greedy"] == before["greedy"] and after["rl"] == before["rl"]


@pytest.mark.parametrize("path", CHECKPOINTS, ids=lambda p: p.name)
def test_checkpoint_rules_read_without_torch_equal_the_loaded_ones(path):
    torch = pytest.importorskip("torch")
    from hmrta.rl.checkpoint_info import read_config

    ck = torch.load(path, map_location="cpu", weights_only=True)
    assert read_config(path) == ck["config"]
    assert methods.rules("rl", checkpoint=str(path)) == Rules.from_dict(ck["config"].get("rules", {}))


def test_board_side_never_imports_torch():
    """The task board learns an rl method's rules from the checkpoint without torch."""
    code = ("import sys, hmrta.methods as m, hmrta_coordinator.task_board\n"
            "r = m.rules('rl'); assert 'torch' not in sys.modules, 'torch imported'; print(r.max_open)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]


def _zip_with_pickle(path: Path, payload: bytes) -> None:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("ck/data.pkl", payload)


class _RunsCode:
    def __reduce__(self):
        return (subprocess.call, (["touch", "/tmp/hmrta-pwned"],))


def test_checkpoint_config_reader_refuses_foreign_globals(tmp_path):
    from hmrta.rl.checkpoint_info import DEFAULT_CHECKPOINT, CheckpointError, read_config

    bad = tmp_path / "evil.pt"
    _zip_with_pickle(bad, pickle.dumps({"config": {"rules": {}}, "x": _RunsCode()}))
    with pytest.raises(CheckpointError, match="not allowed"):
        read_config(bad)
    plain = tmp_path / "plain.pt"
    _zip_with_pickle(plain, pickle.dumps({"config": {"rules": {"max_open": "team"}}}, protocol=2))
    assert methods.rules("rl", checkpoint=str(plain)) == Rules(max_open="team")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a zip")
    with pytest.raises(CheckpointError, match=r"not a readable hmrta checkpoint \(not a torch checkpoint file\)"):
        read_config(junk)
    cut = tmp_path / "cut.pt"  # the light reader of a checkpoint's config (a live mission's): the same words
    cut.write_bytes(DEFAULT_CHECKPOINT.read_bytes()[:5000])
    with pytest.raises(CheckpointError, match=r"not a readable hmrta checkpoint \(a zip archive cut short"):
        read_config(cut)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        read_config(tmp_path / "missing.pt")
    wrong = tmp_path / "wrong.pt"
    _zip_with_pickle(wrong, pickle.dumps({"config": {"rules": {"max_open": 0}}}))
    with pytest.raises(CheckpointError, match="rules.max_open"):
        methods.rules("rl", checkpoint=str(wrong))


def test_cli_help_lists_every_method_and_option():
    from hmrta.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "cmd")
    buf = io.StringIO()
    sub.choices["solve"].print_help(buf)
    text = " ".join(buf.getvalue().split()).replace("- ", "-")  # (lines may wrap after a hyphen)
    for name, m in METHODS.items():
        assert f"{name}: {' '.join(m.summary.split())}".replace("- ", "-") in text
        for o in m.options:
            assert o.flag in text


def _imports(path: Path, module: str, package: str, known: set[str]) -> set[str]:
    """Every hmrta module ``module`` imports, anywhere in the file (function-level imports too;
    not the annotations-only imports under ``if TYPE_CHECKING:``, which never run)."""
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                   and "TYPE_CHECKING" in ast.unparse(node.test) for n in ast.walk(node)}
    out = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            names = [mod] + [f"{mod}.{a.name}" for a in node.names]
        else:
            continue
        out |= {n for n in names if n in known and n != module}
    return out


def test_no_import_cycles_in_the_core():
    root = ROOT / "policy" / "hmrta"
    files = {}
    for p in root.rglob("*.py"):
        parts = p.relative_to(root.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        files[name] = p
    known = set(files)
    graph = {m: _imports(p, m, m if p.name == "__init__.py" else m.rsplit(".", 1)[0], known)
             for m, p in files.items()}
    graph = {m: {d for d in deps if d != "hmrta"} for m, deps in graph.items()}  # the package itself: __version__
    state: dict[str, int] = {}
    cycles = []

    def visit(stack: list[str]) -> None:
        m = stack[-1]
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d):] + [d]))
            elif d not in state:
                visit(stack + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit([m])
    assert not cycles, "import cycles: " + "; ".join(cycles)


def test_portfolio_is_the_best_candidate_and_resolves_to_a_live_method():
    pytest.importorskip("torch")
    from hmrta.generators import ScenarioGenerator

    chosen_ever = set()
    candidates = ("greedy", "greedy-coalition", "rl", "rl@broad", "rl@coalition-team")
    for inst in ScenarioGenerator("MA-AT", 9, 3, 20, 3).generate(3, 81):  # picks three different policies
        sol = methods.solve(inst, "portfolio", seed=1)
        each = {c: methods.solve(inst, c, seed=1).makespan for c in candidates}
        assert sol.makespan == min(each.values())
        assert sol.extra["portfolio"]["candidates"] == each
        chosen = sol.extra["portfolio"]["chosen"]
        chosen_ever.add(chosen)
        assert each[chosen] == min(each.values())
        live, opts, scores = methods.resolve(inst, "portfolio", 1)
        assert scores == each
        # the agents run the chosen candidate: rl@coalition-team is rl with that shipped checkpoint
        name, _, own = chosen.partition("@")
        assert (live, opts) == ((name, {"checkpoint": own}) if own else (chosen, {}))
    assert chosen_ever == {"greedy-coalition", "rl@coalition-team", "rl"}  # a rule, rl, and rl@ checkpoint
    inst = load_instance(EXAMPLE)
    assert methods.resolve(inst, "greedy", 0) == ("greedy", {}, None)
    only = methods.solve(inst, "portfolio", candidates="greedy,greedy-coalition")
    assert set(only.extra["portfolio"]["candidates"]) == {"greedy", "greedy-coalition"}
    with pytest.raises(MethodError, match="portfolio cannot be a candidate"):
        methods.solve(inst, "portfolio", candidates="greedy,portfolio")
    with pytest.raises(MethodError, match="method cpsat has no per-decision form"):
        methods.resolve(inst, "cpsat")
    # live, rl-sN makes one sampled decision per turn, not the best of N rollouts the choice would
    # simulate: offline it is a candidate, live it is refused
    assert methods.solve(inst, "portfolio", candidates="rl-s2,greedy").extra["portfolio"]["chosen"]
    with pytest.raises(MethodError, match="rl-s2 cannot be a candidate of a live mission"):
        methods.choose_live(inst, "portfolio", candidates="rl-s2,greedy")
    with pytest.raises(MethodError) as e:  # an unknown candidate: the expected values are live methods
        methods.choose_live(inst, "portfolio", candidates="greedy,bogus")
    assert "unknown method 'bogus'" in str(e.value) and "cpsat" not in str(e.value) and "rl-lookahead" in str(e.value)
    assert (methods.live_label("rl", {"checkpoint": "broad"}), methods.live_label("greedy", {})) == ("rl@broad", "greedy")


def test_portfolio_compute_time_leaves_out_model_loading(monkeypatch, tmp_path):
    """As for every method, the portfolio's compute seconds leave out loading its candidates'
    models: here a checkpoint that takes over a second to load."""
    pytest.importorskip("torch")
    import time

    from hmrta.rl import inference
    from hmrta.rl.checkpoint_info import SHIPPED_DIR

    slow = tmp_path / "slow.pt"
    shutil.copyfile(SHIPPED_DIR / "broad.pt", slow)  # a file of its own: not yet loaded in this process
    load = inference.load_policy

    def slow_load(checkpoint=None):
        time.sleep(1.2)
        return load(checkpoint)

    monkeypatch.setattr(inference, "load_policy", slow_load)
    inst = load_instance(EXAMPLE)
    t0 = time.perf_counter()
    sol = methods.solve(inst, "portfolio", candidates=f"greedy,rl@{slow}")
    elapsed = time.perf_counter() - t0
    assert sol.compute_seconds > 0 and elapsed - sol.compute_seconds >= 1.2  # the load's 1.2 s left out
    rl = methods.solve(inst, f"rl@{slow}")
    greedy = methods.solve(inst, "greedy")
    assert sol.extra["portfolio"]["candidates"] == {"greedy": greedy.makespan, f"rl@{slow}": rl.makespan}


def test_portfolio_without_torch_leaves_out_its_default_rl_candidates_but_not_named_ones(monkeypatch, caplog):
    import dataclasses
    import sys

    from hmrta.deps import MissingDependency

    monkeypatch.setitem(sys.modules, "torch", None)  # as if torch were not installed
    inst = load_instance(EXAMPLE)
    sol = methods.solve(inst, "portfolio", seed=0)
    pf = sol.extra["portfolio"]
    assert set(pf["candidates"]) == {"greedy", "greedy-coalition"} and pf["left_out"]
    assert all(c.startswith("rl") and "torch" in why for c, why in pf["left_out"].items())
    assert "left out: rl, rl@broad, rl@coalition-team (method rl needs torch" in sol.summary()
    with pytest.raises(MissingDependency, match="torch"):
        methods.solve(inst, "portfolio", seed=0, candidates="greedy,rl")
    # no task known at time 0: the first listed that can run; live, the left out are logged
    late = dataclasses.replace(inst, tasks=tuple(dataclasses.replace(t, release=1.0) for t in inst.tasks))
    with caplog.at_level("WARNING", logger="hmrta.portfolio"):
        assert methods.resolve(late, "portfolio")[:2] == ("greedy-coalition", {})
    assert "portfolio: left out rl (" in caplog.text and "torch" in caplog.text


def test_portfolio_reports_progress_per_candidate_offline_and_live():
    """A large mission takes seconds to minutes per learned candidate: the choice reports each
    candidate before and after it runs (hmrta solve and hmrta-mission draw a bar from it)."""
    inst = load_instance(EXAMPLE)
    calls = []
    sol = methods.solve(inst, "portfolio", candidates="greedy,greedy-coalition", progress=lambda *a: calls.append(a))
    each = sol.extra["portfolio"]["candidates"]
    assert calls == [(0, 2, "candidate", "simulating greedy"), (1, 2, "candidate", f"greedy {each['greedy']:.2f}"),
                     (1, 2, "candidate", "simulating greedy-coalition"),
                     (2, 2, "candidate", f"greedy-coalition {each['greedy-coalition']:.2f}")]
    live = []
    assert methods.resolve(inst, "portfolio", 0, progress=lambda *a: live.append(a),
                           candidates="greedy,greedy-coalition")[2] == each
    assert live == calls
    live.clear()
    assert methods.resolve(inst, "greedy", 0, progress=lambda *a: live.append(a)) == ("greedy", {}, None)
    assert live == []  # a method that does not choose reports nothing
    # the default candidates left out (more skills than the policy takes) are skipped, the count still of all five
    calls.clear()
    methods.solve(ScenarioGenerator("MA-AT", 6, 3, 5, 7).instance(0, 0), "portfolio",
                  progress=lambda *a: calls.append(a))
    assert [(c[0], c[1], c[3].split()[-1]) for c in calls] == [
        (1, 5, "greedy-coalition"), (2, 5, calls[1][3].split()[-1]), (4, 5, "greedy"), (5, 5, calls[3][3].split()[-1])]
    assert calls[1][3].startswith("greedy-coalition ") and calls[3][3].startswith("greedy ")


def test_portfolio_never_ignores_a_checkpoint_the_user_named(monkeypatch, tmp_path):
    """A checkpoint given to the portfolio (its option, or $HMRTA_CHECKPOINT) that cannot be read is
    an error, not a candidate quietly left out."""
    pytest.importorskip("torch")
    from hmrta.rl.checkpoint_info import CheckpointError

    inst = load_instance(EXAMPLE)
    bad = tmp_path / "bad.pt"
    bad.write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match="bad.pt"):
        methods.solve(inst, "portfolio", seed=0, checkpoint=str(bad))
    monkeypatch.setenv("HMRTA_CHECKPOINT", str(tmp_path / "missing.pt"))
    with pytest.raises(CheckpointError, match="missing.pt .named by .HMRTA_CHECKPOINT.: no such checkpoint"):
        methods.resolve(inst, "portfolio", 0)
    with pytest.raises(CheckpointError, match="missing.pt .named by .HMRTA_CHECKPOINT.: no such checkpoint"):
        methods.solve(inst, "portfolio", 0, candidates="greedy")  # (no candidate reads it: it ran)
    monkeypatch.setenv("HMRTA_CHECKPOINT", str(tmp_path))
    with pytest.raises(CheckpointError, match="named by .HMRTA_CHECKPOINT.: is a folder, expected a checkpoint file"):
        methods.solve(inst, "rl", 0)


def test_portfolio_leaves_out_the_learned_policy_on_a_mission_beyond_it():
    pytest.importorskip("torch")
    from hmrta.generators import ScenarioGenerator

    inst = ScenarioGenerator("MA-AT", 6, 3, 5, 7).instance(0, 0)  # 7 skills: the policy takes at most 5
    sol = methods.solve(inst, "portfolio", seed=0)
    pf = sol.extra["portfolio"]
    assert sol.success and set(pf["candidates"]) == {"greedy", "greedy-coalition"}
    assert all("at most 5 skills" in why for why in pf["left_out"].values()) and "chose " in sol.summary()
    with pytest.raises(MethodError, match="at most 5 skills"):
        methods.solve(inst, "portfolio", seed=0, candidates="greedy,rl")


def test_portfolio_on_missions_that_change_and_its_candidates():
    pytest.importorskip("torch")
    import dataclasses

    candidates = methods.get("portfolio").option("candidates").default.split(",")
    assert candidates[:2] == ["rl", "greedy-coalition"] and candidates[-1] == "greedy"  # docs/results.md

    inst = load_instance(EXAMPLE)
    late = dataclasses.replace(inst, tasks=tuple(dataclasses.replace(t, release=3.0) if m % 4 == 0 else t
                                                 for m, t in enumerate(inst.tasks)))
    assert late.dynamic
    sol = methods.solve(late, "portfolio", seed=0)  # chosen on the tasks known at 0, then run online
    chosen = sol.extra["portfolio"]["chosen"]
    assert sol.success and sol.makespan == methods.solve(late, chosen, seed=0).makespan
    everything_late = dataclasses.replace(inst, tasks=tuple(dataclasses.replace(t, release=1.0) for t in inst.tasks))
    # nothing to compare (every makespan 0 on no task): the first listed, the method best on missions that change
    assert methods.resolve(everything_late, "portfolio") == ("rl", {}, dict.fromkeys(candidates, 0.0))
    sol = methods.solve(everything_late, "portfolio", seed=0)
    assert sol.extra["portfolio"]["chosen"] == "rl" and sol.extra["portfolio"]["tasks_known_at_start"] == 0
    assert sol.makespan == methods.solve(everything_late, "rl", seed=0).makespan and "known at time 0" in sol.summary()
    assert methods.resolve(everything_late, "portfolio", candidates="greedy,rl")[:2] == ("greedy", {})
    with pytest.raises(MethodError, match="cpsat cannot be a candidate"):
        methods.solve(inst, "portfolio", candidates="greedy,cpsat")
    # a checkpoint named to the portfolio is a file here, even when no candidate reads it (it was ignored)
    with pytest.raises(MethodError, match="^portfolio: option checkpoint: nosuch: no such checkpoint"):
        methods.solve(inst, "portfolio", candidates="greedy", checkpoint="nosuch")
    with pytest.raises(MethodError, match="^portfolio: option candidates: rl@nosuch: nosuch: no such checkpoint"):
        methods.solve(inst, "portfolio", candidates="greedy,rl@nosuch")


def test_shorthand_live_and_in_conflict():
    pytest.importorskip("torch")
    inst = load_instance(EXAMPLE)
    assert methods.resolve(inst, "rl-s10")[:2] == ("rl-sample", {})  # live rl-sN decodes by sampling
    decide, _ = methods.decider("rl-s10")
    assert callable(decide)
    with pytest.raises(MethodError, match="rl-s3 means samples=3, but samples=5 was given too"):
        methods.solve(inst, "rl-s3", samples=5)
    assert methods.solve(inst, "rl-s3", samples=3).method == "rl-s3"


def test_checkpoint_reader_refuses_oversized_pickles_before_reading_them(tmp_path):
    import resource

    from hmrta.rl.checkpoint_info import MAX_PICKLE_BYTES, CheckpointError, read_config

    bomb = tmp_path / "bomb.pt"
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("ck/data.pkl", b"(" * (MAX_PICKLE_BYTES + 1))
    assert bomb.stat().st_size < 100_000
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(CheckpointError, match="unpacks to"):
        read_config(bomb)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 64 * 1024  # KiB: nothing unpacked


def test_bench_keys_portfolio_results_on_the_checkpoint():
    from hmrta.bench import uses_checkpoint

    assert uses_checkpoint("portfolio") and uses_checkpoint("rl-s10") and not uses_checkpoint("greedy")


def test_a_method_spec_can_name_its_own_checkpoint(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    from hmrta.rl.checkpoint_info import SHIPPED_DIR, CheckpointError, checkpoint_path, shipped_checkpoints

    assert {"default", "broad"} <= set(shipped_checkpoints())
    assert methods.parse("rl@broad") == ("rl", {"checkpoint": "broad"})
    assert methods.parse("rl-s10@my/run.pt") == ("rl-sample", {"samples": 10, "checkpoint": "my/run.pt"})
    with pytest.raises(MethodError, match="greedy@broad: method greedy takes no checkpoint"):
        methods.parse("greedy@broad")
    with pytest.raises(MethodError, match="expected a checkpoint after '@'"):
        methods.parse("rl@")
    # a bare shipped name is the shipped file, even with a file of that name here (below); a path stays a path
    assert checkpoint_path("broad") == SHIPPED_DIR / "broad.pt"
    with pytest.raises(CheckpointError, match="no such checkpoint .shipped: .*broad.*default"):
        methods.solve(load_instance(EXAMPLE), "rl", checkpoint="nope")

    inst = ScenarioGenerator("MA-AT", 9, 3, 20, 3).instance(77, 0)
    own = methods.solve(inst, "rl@broad", seed=1)
    assert own.method == "rl@broad"
    assert own.makespan == methods.solve(inst, "rl", seed=1, checkpoint=str(SHIPPED_DIR / "broad.pt")).makespan
    assert own.makespan != methods.solve(inst, "rl", seed=1).makespan  # another policy than default.pt here
    assert methods.rules("rl", checkpoint="broad") == methods.rules("rl", checkpoint=str(SHIPPED_DIR / "broad.pt"))
    with pytest.raises(MethodError, match="rl@broad means checkpoint=broad, but checkpoint=x.pt was given too"):
        methods.solve(inst, "rl@broad", checkpoint="x.pt")
    # in a portfolio the shared checkpoint goes to the candidates without one of their own
    coalition = str(SHIPPED_DIR / "coalition-open.pt")
    sol = methods.solve(inst, "portfolio", seed=1, candidates="rl,rl@broad", checkpoint=coalition)
    assert sol.extra["portfolio"]["candidates"] == {
        "rl": methods.solve(inst, "rl", seed=1, checkpoint=coalition).makespan, "rl@broad": own.makespan}
    assert methods.options_for("rl@broad", {"checkpoint": coalition, "samples": 3}) == {}  # a bench's shared options
    assert methods.options_for("rl-s10@broad", {"checkpoint": coalition, "samples": 3}) == {"samples": 3}
    assert methods.live_spec("rl@broad", {"checkpoint": coalition}) == ("rl", {"checkpoint": "broad"})
    assert methods.live_spec("rl-s10", {"checkpoint": coalition}) == ("rl-sample", {"checkpoint": coalition})
    monkeypatch.chdir(tmp_path)
    (tmp_path / "broad").write_bytes(b"mine")  # a stray file cannot change what rl@broad (a portfolio candidate) runs
    assert checkpoint_path("broad") == SHIPPED_DIR / "broad.pt"
    assert methods.solve(inst, "rl@broad", seed=1).makespan == own.makespan
    assert checkpoint_path("./broad") == tmp_path / "broad"  # the file here, whatever reads the path again
    assert checkpoint_path(checkpoint_path("./broad")) == tmp_path / "broad"
    assert checkpoint_path("elsewhere/broad") == Path("elsewhere/broad")
    with pytest.raises(CheckpointError, match="broad"):  # the stray file is read, and refused
        methods.solve(inst, "rl", seed=1, checkpoint="./broad")
    shutil.copyfile(coalition, tmp_path / "broad")  # ./broad runs the file here and names it
    sol = methods.solve(inst, "rl", seed=1, checkpoint="./broad")
    assert sol.makespan == methods.solve(inst, "rl", seed=1, checkpoint=coalition).makespan
    assert sol.extra["checkpoint"]["path"] == str(tmp_path / "broad")
