"""Benchmarks in the paper's table layout (Tables I-IV), our methods beside the paper's numbers.

Results are cached per (row, method, instance index) in ``<out>/cache.jsonl`` so an interrupted
run resumes where it stopped; tables are written as Markdown and JSON.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import yaml

from .generators import PAPER_ROWS, ScenarioGenerator, row_name
from .instance import atomic_write_text

PAPER_NAME = {"greedy": "Greedy", "rl": "RL(g.)", "rl-s10": "RL(s.10)", "cpsat": "CTAS-D"}  # paper counterpart
DISPLAY_NAME = {"greedy": "Greedy", "greedy-coalition": "Greedy-coalition", "rl": "RL(g.)", "rl-s10": "RL(s.10)",
                "rl-lookahead": "RL-lookahead",
                "cpsat": "CP-SAT (vs paper CTAS-D)"}
TABLE_TITLES = {"SA-BT": "Table I: SA-BT", "SA-AT": "Table II: SA-AT", "MA-AT": "Table III: MA-AT",
                "MA-AT-large": "Table IV: MA-AT, large"}
DEFAULT_BENCH_SEED = 1000  # never used by training (stream seed 0) or validation (990001)


@functools.lru_cache(maxsize=1)
def paper_tables() -> dict:
    return yaml.safe_load(resources.files("hmrta").joinpath("data/paper_tables.yaml").read_text())


@dataclass(frozen=True)
class Row:
    table: str  # SA-BT, SA-AT, MA-AT, MA-AT-large
    agents: int
    species: int
    tasks: int
    skills: int

    @property
    def scenario(self) -> str:
        return "MA-AT" if self.table == "MA-AT-large" else self.table

    @property
    def key(self) -> str:
        return row_name(self.table, self.agents, self.species, self.tasks, self.skills)

    def generator(self) -> ScenarioGenerator:
        return ScenarioGenerator(self.scenario, self.agents, self.species, self.tasks, self.skills)

    def paper(self) -> dict | None:
        for r in paper_tables().get(self.table, []):
            if (r["kn"], r["ks"], r["km"], r["kb"]) == (self.agents, self.species, self.tasks, self.skills):
                return r
        return None


def paper_suite(tables: Iterable[str] | None = None) -> list[Row]:
    tables = list(tables or PAPER_ROWS)
    return [Row(t, *r) for t in tables for r in PAPER_ROWS[t]]


def summarise(results: list[dict]) -> dict:
    """mean/std over solved instances, plus success rate and mean compute seconds."""
    ok = [r for r in results if r["success"]]
    def ms(key):
        v = np.array([r[key] for r in ok], dtype=float)
        return (float(v.mean()), float(v.std())) if len(v) else (math.nan, math.nan)
    return {
        "n": len(results), "success": len(ok) / len(results) if results else math.nan,
        "makespan": ms("makespan"), "awt": ms("awt"), "redundancy": ms("redundancy"),
        "compute_seconds": float(np.mean([r["compute_seconds"] for r in results])) if results else math.nan,
        "gap_to_bound": ms("gap") if ok and all("gap" in r for r in ok) else None,
    }


def method_variant(method: str, solve_opts: dict[str, Any]) -> str:
    """What a cached result depends on besides (row, method, instance, seed): the solve options and,
    for the learned policy, the checkpoint's content. A retrained checkpoint or another time limit
    therefore never reuses stale cached results."""
    parts: dict[str, Any] = {"opts": {k: solve_opts[k] for k in sorted(solve_opts)}}
    if method.startswith("rl"):
        from .rl.inference import checkpoint_path

        path = checkpoint_path(solve_opts.get("checkpoint"))
        parts["checkpoint"] = hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.exists() else None
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_bench(rows: list[Row], methods: list[str], count: int, seed: int, out_dir: Path | None,
              solve_opts: dict[str, Any], progress: bool = True, with_bounds: bool = False,
              log: Callable[[str], None] = print) -> dict:
    from tqdm import tqdm

    from . import methods as M

    cache: dict[tuple, dict] = {}
    cache_path = out_dir / "cache.jsonl" if out_dir else None
    if cache_path and cache_path.exists():
        for line in cache_path.read_text().splitlines():
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short by an interruption
            cache[(r["row"], r["method"], r["index"], r["seed"], r.get("variant"))] = r
        log(f"resuming: {len(cache)} results cached in {cache_path}")
    if out_dir:
        out_dir.mkdir(parents=True, exist_ok=True)
    total = len(rows) * len(methods) * count
    bar = tqdm(total=total, desc="bench", disable=not progress, unit="solve")
    fh = open(cache_path, "a") if cache_path else None
    summary: dict[str, Any] = {"seed": seed, "count": count, "methods": methods, "rows": []}
    variants = {m: method_variant(m, solve_opts) for m in methods}
    try:
        for row in rows:
            insts = row.generator().generate(count, seed)
            bounds = None
            if with_bounds:
                from .bounds import lower_bounds

                bounds = [lower_bounds(i)["best"] for i in insts]
            per_method: dict[str, list[dict]] = {}
            for method in methods:
                res = []
                for i, inst in enumerate(insts):
                    key = (row.key, method, i, seed, variants[method])
                    if key not in cache:
                        sol = M.solve(inst, method, seed=0, **solve_opts)
                        r = {"row": row.key, "method": method, "index": i, "seed": seed,
                             "variant": variants[method], "success": sol.success,
                             "makespan": sol.makespan, "awt": sol.awt, "redundancy": sol.redundancy,
                             "compute_seconds": sol.compute_seconds}
                        lb = sol.extra.get("lower_bound")
                        if lb is not None:
                            r["solver_bound"] = lb
                        cache[key] = r
                        if fh:
                            fh.write(json.dumps(r) + "\n")
                            fh.flush()
                    res.append(dict(cache[key]))
                    bar.update(1)
                    bar.set_postfix(row=row.key, method=method)
                per_method[method] = res
            if bounds is not None:  # best bound per instance: cheap bounds and every solver's proven bound
                for i, b in enumerate(bounds):
                    b = max([b] + [res[i].get("solver_bound") or 0.0 for res in per_method.values()])
                    for res in per_method.values():
                        if res[i]["success"]:
                            res[i]["gap"] = (res[i]["makespan"] - b) / b if b > 0 else 0.0
            summary["rows"].append({"row": row.key, "table": row.table, "size": [row.agents, row.species, row.tasks,
                                                                                 row.skills],
                                    "results": {m: summarise(r) for m, r in per_method.items()}})
    finally:
        bar.close()
        if fh:
            fh.close()
    return summary


def _pm(v: tuple[float, float] | None, nd: int = 2) -> str:
    if v is None or v[0] is None or (isinstance(v[0], float) and math.isnan(v[0])):
        return "—"
    return f"{v[0]:.{nd}f} ± {v[1]:.{nd}f}"


def _paper_vals(p: dict | None, method: str) -> dict | None:
    if not p:
        return None
    name = PAPER_NAME.get(method)
    vals = p.get(name) if name else None
    if not vals:
        return None
    red = (p.get("redundancy") or {}).get(name)
    return {"success": vals[0], "makespan": (vals[1], vals[2]) if vals[1] is not None else None,
            "awt": (vals[3], vals[4]) if vals[3] is not None else None, "compute_seconds": vals[5],
            "redundancy": tuple(red) if red else None}


def to_markdown(summary: dict, hardware: str = "") -> str:
    out = []
    rows_by_table: dict[str, list[dict]] = {}
    for r in summary["rows"]:
        rows_by_table.setdefault(r["table"], []).append(r)
    for table, rows in rows_by_table.items():
        show_red = table.startswith("MA-AT")
        show_gap = any(res.get("gap_to_bound") for r in rows for res in r["results"].values())
        out.append(f"### {TABLE_TITLES.get(table, table)} ({summary['count']} instances per row, seed {summary['seed']})")
        out.append("")
        head = ["kn, ks, km, kb", "method", "success", "makespan", "AWT"]
        if show_red:
            head.append("redundancy")
        head.append("compute s")
        if show_gap:
            head.append("gap to bound")
        head += ["paper success", "paper makespan", "paper AWT"] + (["paper redundancy"] if show_red else []) + ["paper compute s"]
        out.append("| " + " | ".join(head) + " |")
        out.append("|" + "---|" * len(head))
        for r in rows:
            size = ", ".join(map(str, r["size"]))
            paper = Row(table, *r["size"]).paper()
            for method, res in r["results"].items():
                pv = _paper_vals(paper, method)
                cells = [size, DISPLAY_NAME.get(method, method),
                         f"{res['success'] * 100:.0f}%", _pm(res["makespan"]), _pm(res["awt"])]
                if show_red:
                    cells.append(_pm(res["redundancy"], 3))
                cells.append(f"{res['compute_seconds']:.3f}")
                if show_gap:
                    g = res.get("gap_to_bound")
                    cells.append(f"{g[0] * 100:.1f}%" if g else "—")
                if pv:
                    cells += [f"{pv['success'] * 100:.0f}%", _pm(pv["makespan"]), _pm(pv["awt"])]
                    if show_red:
                        cells.append(_pm(pv["redundancy"], 3))
                    cells.append(f"{pv['compute_seconds']}" if pv["compute_seconds"] is not None else "—")
                else:
                    cells += ["—"] * (4 + show_red)
                out.append("| " + " | ".join(cells) + " |")
        out.append("")
    if hardware:
        out.append(hardware)
    return "\n".join(out) + "\n"


def save(summary: dict, markdown: str, json_path: Path | None, md_path: Path | None) -> None:
    if json_path:
        atomic_write_text(json_path, json.dumps(clean(summary), indent=1) + "\n")
    if md_path:
        atomic_write_text(md_path, markdown)


def clean(o: Any) -> Any:
    """NaN/inf -> None, tuples -> lists (strict JSON)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    return o
