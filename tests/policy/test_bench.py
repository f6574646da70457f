"""bench: resumable cache, paired comparisons, provenance, CSV beside JSON and Markdown, titles."""
from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import shutil

from pathlib import Path

import pytest

from hmrta.bench import (Row, comparison_pairs, method_variant, paired_comparison, provenance, run_bench, save,
                         t_cdf, t_quantile, to_markdown)
from hmrta.rl.checkpoint_info import DEFAULT_CHECKPOINT

ROW = Row("MA-AT", 6, 2, 8, 3)  # not a paper row
PAPER_ROW = Row("MA-AT", 9, 3, 20, 3)


def _bench(out, methods=("greedy",), rows=(ROW,), count=2, **kw):
    return run_bench(list(rows), list(methods), count, 5, out, {}, progress=False, log=lambda s: None, **kw)


def _makespans(summary):
    return summary["rows"][0]["results"]["greedy"]["makespan"][0]


def test_cache_is_reused_only_for_the_same_variant(tmp_path):
    first = _bench(tmp_path)
    lines = (tmp_path / "cache.jsonl").read_text().splitlines()
    assert len(lines) == 2
    # tamper with the cached makespans: a resumed run must serve them (it does not recompute) ...
    tampered = [json.loads(x) | {"makespan": 1000.0} for x in lines]
    (tmp_path / "cache.jsonl").write_text("".join(json.dumps(r) + "\n" for r in tampered))
    assert _makespans(_bench(tmp_path)) == 1000.0
    # ... but results of another variant (other options or checkpoint) are never served
    stale = [r | {"variant": "0" * 16} for r in tampered]
    (tmp_path / "cache.jsonl").write_text("".join(json.dumps(r) + "\n" for r in stale))
    assert _makespans(_bench(tmp_path)) == _makespans(first)


@pytest.mark.parametrize("damage,where", [
    (lambda r: r | {"makespan": "x"}, ":1: makespan: expected a number"),
    (lambda r: r | {"makespan": math.nan}, ":1: makespan: expected a finite number >= 0"),
    (lambda r: r | {"success": 1}, ":1: success: expected true or false"),
    (lambda r: {"a": 1}, ":1: row: expected a string"),
    (lambda r: 5, ":1: record: expected a JSON object"),
    (lambda r: r | {"response": {"dynamic": False, "mean": None, "max": None, "lost": {}}},
     ":1: response.lost: expected an object of whole numbers"),
])
def test_a_damaged_cache_is_an_error_naming_its_line_and_field(tmp_path, damage, where):
    """A cache record that is not one a run writes is refused (file, line, field), not served as
    a result nor a crash; a last line cut short by an interruption is solved again."""
    from hmrta.reading import InputError

    first = _bench(tmp_path)
    path = tmp_path / "cache.jsonl"
    lines = path.read_text().splitlines()
    path.write_text(json.dumps(damage(json.loads(lines[0]))) + "\n" + lines[1] + "\n")
    with pytest.raises(InputError, match=f"cache.jsonl{where}.*remove the line"):
        _bench(tmp_path)
    path.write_text(lines[0] + "\n" + lines[1][:20])  # interrupted while writing the second
    assert _makespans(_bench(tmp_path)) == _makespans(first)
    path.write_text(lines[0][:20] + "\n" + lines[1] + "\n")  # not the last line: damaged
    with pytest.raises(InputError, match="cache.jsonl:1: not JSON"):
        _bench(tmp_path)
    path.write_bytes(b"\xff\xfe" + lines[0].encode())
    with pytest.raises(InputError, match="cache.jsonl"):
        _bench(tmp_path)


def test_rl_variant_follows_the_checkpoint_content(tmp_path):
    a = tmp_path / "a.pt"
    shutil.copy(DEFAULT_CHECKPOINT, a)
    v1 = method_variant("rl", {"checkpoint": str(a)})
    assert v1 == method_variant("rl", {"checkpoint": str(a)})
    a.write_bytes(a.read_bytes() + b"\0")  # retrained / replaced weights
    assert method_variant("rl", {"checkpoint": str(a)}) != v1
    assert method_variant("cpsat", {"time_limit": 2.0}) != method_variant("cpsat", {"time_limit": 1.0})
    # a checkpoint named by the spec (rl@FILE, or a portfolio candidate) counts by its content too
    own, portfolio = method_variant(f"rl@{a}", {}), method_variant("portfolio", {"candidates": f"greedy,rl@{a}"})
    a.write_bytes(a.read_bytes() + b"\0")
    assert method_variant(f"rl@{a}", {}) != own
    assert method_variant("portfolio", {"candidates": f"greedy,rl@{a}"}) != portfolio


def test_a_changed_option_default_changes_the_variant(monkeypatch):
    """A result cached under one default of an option left out (rl-sample's temperature) is not
    reused once the default changes."""
    import dataclasses

    from hmrta import methods

    m = methods.METHODS["rl-sample"]
    before = method_variant("rl-s10", {})
    hotter = tuple(dataclasses.replace(o, default=1.0) if o.name == "temperature" else o for o in m.options)
    monkeypatch.setitem(methods.METHODS, "rl-sample", dataclasses.replace(m, options=hotter))
    assert method_variant("rl-s10", {}) != before


def test_t_quantiles_match_the_tables():
    # two-sided 95% critical values of Student's t (any statistics table)
    for df, t in ((1, 12.7062), (2, 4.3027), (3, 3.1824), (9, 2.2622), (10, 2.2281), (49, 2.0096)):
        assert t_quantile(0.975, df) == pytest.approx(t, abs=1e-4)
    assert t_cdf(0.0, 7) == 0.5 and t_cdf(-1.5, 4) == pytest.approx(1 - t_cdf(1.5, 4))
    assert t_cdf(1.0, 1) == pytest.approx(0.75)  # Cauchy: 1/2 + atan(1)/pi


def _res(ms):
    return [{"success": m is not None, "makespan": m if m is not None else math.nan} for m in ms]


def test_paired_comparison_by_hand():
    a = _res([10.0, 12.0, 9.0, 15.0, 20.0, None, None])
    b = _res([11.0, 12.0, 10.0, 13.0, None, 5.0, None])
    c = paired_comparison(a, b, "x", "y")
    # per instance: win, tie, win, loss, win (only x solved), loss (only y solved), tie (both failed)
    assert (c["wins"], c["ties"], c["losses"]) == (3, 2, 2)
    assert (c["a"], c["b"], c["n"], c["n_paired"]) == ("x", "y", 7, 4)
    # differences over the 4 instances both solved: -1, 0, -1, +2 -> mean 0, sample sd sqrt(2)
    assert c["mean_diff"] == pytest.approx(0.0)
    half = 3.182446305 * math.sqrt(2.0) / 2.0  # t(0.975, 3) * sd / sqrt(n)
    assert c["ci95"] == pytest.approx([-half, half], abs=1e-6)
    assert c["relative"] == pytest.approx(0.0)
    assert c["ratio"] == pytest.approx((10 / 11 * 1.0 * 9 / 10 * 15 / 13) ** 0.25)  # each mission alike
    d = paired_comparison(_res([10.0, 11.0]), _res([12.0, 12.0]))
    assert d["mean_diff"] == pytest.approx(-1.5) and d["relative"] == pytest.approx(-1.5 / 12.0)
    # differences -2, -1: sample sd sqrt(0.5), half width t(0.975, 1) * sqrt(0.5) / sqrt(2) = 12.7062 / 2
    assert d["ci95"] == pytest.approx([-1.5 - 6.3531, -1.5 + 6.3531], abs=1e-3)
    assert paired_comparison(_res([1.0]), _res([2.0]))["ci95"] is None  # one pair: no interval
    # a long mission dominates the relative difference, not the ratio: 10% worse on a short one,
    # 1% better on a long one
    e = paired_comparison(_res([1.1, 99.0]), _res([1.0, 100.0]))
    assert e["relative"] < 0 < math.log(e["ratio"]) and e["ratio"] == pytest.approx((1.1 * 0.99) ** 0.5)
    assert paired_comparison(_res([None]), _res([2.0]))["ratio"] is None  # no pair


def test_default_and_explicit_comparison_pairs():
    assert comparison_pairs(["greedy", "rl", "greedy-coalition"], None) == [("rl", "greedy"),
                                                                            ("rl", "greedy-coalition")]
    assert comparison_pairs(["greedy", "greedy-coalition"], None) == []
    assert comparison_pairs(["greedy", "greedy-coalition", "portfolio"], None) == [("portfolio", "greedy"),
                                                                                  ("portfolio", "greedy-coalition")]
    assert comparison_pairs(["greedy", "random"], [("random", "greedy")]) == [("random", "greedy")]
    with pytest.raises(ValueError, match="'rl' is not one of the benchmarked methods"):
        comparison_pairs(["greedy"], [("rl", "greedy")])


def test_comparisons_in_the_summary_match_the_per_instance_results(tmp_path):
    s = _bench(None, methods=("greedy", "random"), count=4, compare=[("random", "greedy")])
    row = s["rows"][0]
    (c,) = row["comparisons"]
    ms = row["makespans"]
    diffs = [r - g for r, g in zip(ms["random"], ms["greedy"])]
    assert c["mean_diff"] == pytest.approx(sum(diffs) / 4)
    assert c["wins"] == sum(d < 0 for d in diffs) and c["losses"] == sum(d > 0 for d in diffs)
    md = to_markdown(s)
    assert f"| random vs Greedy | {c['wins']} / {c['ties']} / {c['losses']} | {c['mean_diff']:+.2f} |" in md


def test_provenance_keys_and_checkpoint_hash():
    p = provenance(["greedy", "rl"], {}, command="hmrta bench x")
    assert p["checkpoint"]["name"] == DEFAULT_CHECKPOINT.name and p["checkpoint"]["shipped"] is True
    assert p["checkpoint"]["sha256"] == hashlib.sha256(DEFAULT_CHECKPOINT.read_bytes()).hexdigest()
    assert p["code_version"] and p["command"] == "hmrta bench x"
    assert set(p["versions"]) >= {"hmrta", "torch", "ortools", "numpy"} and p["versions"]["numpy"]
    assert p["cpu"]["model"] and p["cpu"]["cores"] >= 1 and len(p["load_average"]) == 3
    assert "torch_threads" in p and p["date"].endswith("Z")
    assert provenance(["greedy"], {})["checkpoint"] is None  # no rl method: no checkpoint
    own = provenance(["portfolio"], {"candidates": "rl,rl@broad"})["own_checkpoints"]
    broad = DEFAULT_CHECKPOINT.parent / "broad.pt"
    assert own == {"rl@broad": {"name": "broad.pt", "sha256": hashlib.sha256(broad.read_bytes()).hexdigest(),
                                "shipped": True}}


def test_results_files_csv_agrees_with_json_and_markdown_shows_provenance(tmp_path):
    s = _bench(tmp_path, methods=("greedy", "greedy-coalition"), rows=(ROW, PAPER_ROW), command="hmrta bench t")
    paths = save(s, tmp_path)
    assert [p.name for p in paths] == ["results.json", "results.md", "results.csv"]
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["provenance"]["command"] == "hmrta bench t" and data["provenance"]["code_version"]
    lines = list(csv.DictReader(io.StringIO((tmp_path / "results.csv").read_text())))
    assert len(lines) == 2 * 2  # one line per row x method
    for line in lines:
        row = next(r for r in data["rows"] if r["row"] == line["row"])
        res = row["results"][line["method"]]
        assert [int(line[k]) for k in ("kn", "ks", "km", "kb")] == row["size"]
        assert float(line["makespan_mean"]) == res["makespan"][0]
        assert float(line["awt_std"]) == res["awt"][1]
        assert float(line["success"]) == res["success"] and int(line["n"]) == res["n"] == 2
    md = (tmp_path / "results.md").read_text()
    assert md.startswith("- command: `hmrta bench t`")
    assert f"- code: {data['provenance']['code_version']}" in md and "- machine: " in md


def test_only_paper_rows_get_the_paper_title():
    generated = to_markdown(_bench(None, count=1))
    assert "Table III" not in generated and "### MA-AT scenario, generated rows (1 instances per row" in generated
    assert "paper makespan" not in generated
    paper = to_markdown(_bench(None, rows=(PAPER_ROW,), count=1))
    assert "### Table III: MA-AT (1 instances per row, seed 5)" in paper and "paper makespan" in paper


MISSION = (Path(__file__).parent / "data" / "two_species.yaml").read_text()  # shared with test_scenario
SCENARIO = """format: hmrta-scenario/1
instance: mission.yaml
events:
  - {t: 3.0, type: add_task, id: a, location: [0.3, 0.6], requirements: [1, 1], duration: 2}
  - {t: 4.0, type: add_task, id: b, location: [0.6, 0.6], requirements: [2, 0], duration: 1}
  - {t: 5.0, type: cancel_task, id: b}
  - {t: 6.0, type: add_task, id: c, location: [0.6, 0.6], requirements: [0, 9], duration: 1}
"""


def test_gap_to_bound_is_the_one_hmrta_bound_reports():
    """bench --bounds and hmrta bound give each solution the same gap: (makespan - best lower
    bound) / makespan, the share of the makespan that the bound does not yet prove."""
    from hmrta.bounds import bound_report
    from hmrta.methods import solve

    s = _bench(None, count=3, with_bounds=True)
    gaps = []
    for _, inst in ROW.instances(3, 5):
        (rep,) = bound_report(inst, [solve(inst, "greedy", seed=0)])["solutions"]  # bench solves with seed 0
        gaps.append(rep["gap"])
    assert s["rows"][0]["results"]["greedy"]["gap_to_bound"][0] == pytest.approx(sum(gaps) / 3)
    assert all(0 < g < 1 for g in gaps)


def test_given_missions_claim_no_test_set_and_no_paper_counterpart(tmp_path):
    """A user's missions are given, not drawn: their summary holds no test-set seed or count, and
    CP-SAT is not labelled against the paper's CTAS-D where no paper numbers stand beside it. A
    paper row keeps both."""
    from hmrta.bench import MissionSet

    (tmp_path / "mission.yaml").write_text(MISSION)
    mine = MissionSet.load("mine", [tmp_path / "mission.yaml"])

    def bench(row, count, seed):
        return run_bench([row], ["greedy", "cpsat"], count, seed, None, {"time_limit": 0.2}, progress=False,
                         log=lambda s: None, compare=[("cpsat", "greedy")])

    s = bench(mine, 3, 7)
    assert "seed" not in s and "count" not in s and s["rows"][0]["results"]["cpsat"]["n"] == 1
    md = to_markdown(s)
    assert "| mine | 4, 2, 3, 2 | CP-SAT | 100% |" in md and "| mine | CP-SAT vs Greedy |" in md
    assert "paper" not in md
    paper = bench(PAPER_ROW, 1, 5)
    assert (paper["seed"], paper["count"]) == (5, 1)
    md = to_markdown(paper)
    assert "| 9, 3, 20, 3 | CP-SAT (vs paper CTAS-D) | 100% |" in md and "| CP-SAT (vs paper CTAS-D) vs Greedy |" in md


def test_dynamic_columns_only_for_rows_with_dynamic_missions(tmp_path):
    """A row of scenario files and instances with released tasks gets mean / max response and
    tasks lost (by kind) in Markdown, JSON and CSV, equal to the solutions' own figures; a static
    row in the same summary has none (dashes / empty cells) and a static-only summary no columns."""
    from hmrta import methods
    from hmrta.bench import MissionSet

    (tmp_path / "mission.yaml").write_text(MISSION)
    (tmp_path / "scen.yaml").write_text(SCENARIO)
    (tmp_path / "released.yaml").write_text(MISSION.replace("duration: 1}", "duration: 1, release: 2.5}"))
    dyn = MissionSet.load("dyn", [tmp_path / "scen.yaml", tmp_path / "released.yaml"])
    static = MissionSet.load("static", [tmp_path / "mission.yaml"])
    out = tmp_path / "out"
    s = _bench(out, methods=("greedy",), rows=(dyn, static), count=1)
    sols = [methods.solve(i, "greedy", seed=0).extra["dynamic"] for i in dyn.loaded]
    assert [d["tasks_lost"] for d in sols] == [{"cancelled": 1, "unsatisfiable": 0, "rejected": 1},
                                               {"cancelled": 0, "unsatisfiable": 0, "rejected": 0}]
    d = s["rows"][0]["results"]["greedy"]["dynamic"]
    assert d["n"] == d["n_dynamic"] == 2
    assert d["mean_response"][0] == pytest.approx((sols[0]["mean_response"] + sols[1]["mean_response"]) / 2)
    assert d["max_response"][0] == pytest.approx((sols[0]["max_response"] + sols[1]["max_response"]) / 2)
    assert d["tasks_lost"] == {"cancelled": 0.5, "unsatisfiable": 0.0, "rejected": 0.5}
    assert "dynamic" not in s["rows"][1]["results"]["greedy"]
    save(s, out)
    data = json.loads((out / "results.json").read_text())
    assert data["rows"][0]["results"]["greedy"]["dynamic"]["tasks_lost"]["rejected"] == 0.5
    md = (out / "results.md").read_text()
    assert "| mean response | max response | tasks lost (cancelled / unsatisfiable / rejected) |" in md
    assert "| 0.50 / 0.00 / 0.50 |" in md and "| — | — | — |" in md
    lines = list(csv.DictReader(io.StringIO((out / "results.csv").read_text())))
    assert [x["row"] for x in lines] == ["missions:dyn", "missions:static"]
    assert float(lines[0]["mean_response_mean"]) == d["mean_response"][0]
    assert float(lines[0]["lost_cancelled_mean"]) == 0.5 and lines[1]["lost_cancelled_mean"] == ""
    # a static summary keeps the static columns only
    st = _bench(None, methods=("greedy",), rows=(static,), count=1)
    assert "mean response" not in to_markdown(st)
    from hmrta.bench import to_csv
    assert "mean_response_mean" not in to_csv(st)


def test_scenario_cache_identity_follows_the_events(tmp_path):
    from hmrta.bench import MissionSet

    (tmp_path / "mission.yaml").write_text(MISSION)
    (tmp_path / "scen.yaml").write_text(SCENARIO)
    (ident_a, _), = MissionSet.load("x", [tmp_path / "scen.yaml"]).instances(1, 0)
    (tmp_path / "scen.yaml").write_text(SCENARIO.replace("t: 3.0", "t: 3.5"))
    (ident_b, _), = MissionSet.load("x", [tmp_path / "scen.yaml"]).instances(1, 0)
    assert ident_a != ident_b


def test_missions_with_events_have_no_gap_to_bound(tmp_path):
    """A cancelled task or a lost robot can undercut any bound of the mission known at time 0:
    bench --bounds gives such missions no gap (it gave one, and 0% for a mission whose tasks were
    all cancelled)."""
    from hmrta.bench import MissionSet

    (tmp_path / "mission.yaml").write_text(MISSION)
    (tmp_path / "scen.yaml").write_text(SCENARIO)
    rows = [MissionSet.load("scen", [tmp_path / "scen.yaml"]), MissionSet.load("plain", [tmp_path / "mission.yaml"])]
    s = run_bench(rows, ["greedy"], 1, 0, None, {}, progress=False, log=lambda s: None, with_bounds=True)
    scen, plain = (r["results"]["greedy"]["gap_to_bound"] for r in s["rows"])
    assert scen is None and plain is not None and plain[0] > 0


def test_a_portfolio_names_the_candidates_it_left_out(tmp_path):
    """On 6-skill missions the learned candidates cannot run: the portfolio row says which were
    left out, on how many missions and why, and the provenance lists no checkpoint none of them read."""
    from hmrta.bench import MissionSet
    from hmrta.generators import ScenarioGenerator

    files = []
    for i in range(2):
        files.append(tmp_path / f"six-{i}.yaml")
        ScenarioGenerator("MA-AT", 6, 3, 8, 6).instance(3, i).save(files[-1])
    logged: list[str] = []
    s = run_bench([MissionSet.load("six", files)], ["greedy", "portfolio"], 1, 0, tmp_path / "out", {},
                  progress=False, log=logged.append)
    res = s["rows"][0]["results"]["portfolio"]
    assert set(res["left_out"]) == {"rl", "rl@broad", "rl@coalition-team"}
    assert all(x["missions"] == 2 and "at most 5 skills" in x["reason"] for x in res["left_out"].values())
    assert any(line.startswith("portfolio: left out rl, rl@broad, rl@coalition-team on 2 of 2 mission(s) (method rl: "
                               "the learned policy handles at most 5 skills") for line in logged), logged
    md = to_markdown(s)
    assert "- Portfolio (six): left out rl, rl@broad, rl@coalition-team on 2 of 2 mission(s): method rl: " in md, md
    assert s["provenance"]["checkpoint"] is None and "own_checkpoints" not in s["provenance"]
    assert "checkpoint" not in md.split("###")[0]
    # where the learned candidates do run, they are listed as before
    assert provenance(["portfolio"], {}, ran=["rl", "rl@coalition-team"])["own_checkpoints"].keys() == {
        "rl@coalition-team"}
    # beside a mission they run on, and with a method of their own: counted per method, listed
    three = tmp_path / "three.yaml"
    ScenarioGenerator("MA-AT", 6, 3, 8, 3).instance(3, 0).save(three)
    logged.clear()
    s = run_bench([MissionSet.load("mixed", [files[0], three])], ["greedy", "portfolio"], 1, 0, None, {},
                  progress=False, log=logged.append)
    assert any(line.startswith("portfolio: left out rl, rl@broad, rl@coalition-team on 1 of 2 mission(s)")
               for line in logged), logged
    assert s["provenance"]["checkpoint"] is not None and set(s["provenance"]["own_checkpoints"]) == {
        "rl@broad", "rl@coalition-team"}


def test_sampled_rollouts_are_named_alike_whatever_their_number():
    from hmrta.bench import _method_name

    assert [_method_name(m) for m in ("rl-s10", "rl-s3", "rl-s3@broad", "rl")] == \
        ["RL(s.10)", "RL(s.3)", "RL(s.3)@broad", "RL(g.)"]
