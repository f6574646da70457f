#!/usr/bin/env python3
"""CP-SAT vs greedy on seeded instances of a paper row, next to the paper's CTAS-D / Greedy numbers.

    .venv/bin/python benchmarks/cpsat_vs_paper.py                       # MA-AT (15,5,20,5), 5 x 60 s
    .venv/bin/python benchmarks/cpsat_vs_paper.py --row SA-AT:9,3,20,3 --n 3 --time-limit 30 --json out.json

Instances: ``ScenarioGenerator(row).generate(n, seed)`` (the same sets as ``hmrta generate``).
Per instance it prints greedy, the heuristic phase of the CP-SAT method (list scheduler +
annealing, the model's hint), the CP-SAT result, its proven lower bound and status. The paper's
numbers are means over its own 50 instances (CTAS-D: over the instances it solved), so compare
means and the ratio to greedy, not single instances.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from importlib import resources

import yaml

from hmrta.generators import ScenarioGenerator
from hmrta.methods import solve


def paper_row(scenario: str, agents: int, species: int, tasks: int, skills: int) -> dict | None:
    data = yaml.safe_load(resources.files("hmrta").joinpath("data/paper_tables.yaml").read_text())
    for r in data.get(scenario, []):
        if (r["kn"], r["ks"], r["km"], r["kb"]) == (agents, species, tasks, skills):
            return r
    return None


def _ms(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _mean_std(xs: list[float]) -> str:
    if not xs:
        return "n/a"
    return f"{statistics.mean(xs):.3f} ± {statistics.pstdev(xs):.3f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--row", default="MA-AT:15,5,20,5", help="SCENARIO:agents,species,tasks,skills")
    ap.add_argument("--n", type=int, default=5, help="number of instances")
    ap.add_argument("--seed", type=int, default=1, help="instance-set seed")
    ap.add_argument("--time-limit", type=float, default=60.0, help="CP-SAT seconds per instance")
    ap.add_argument("--workers", type=int, default=2, help="CP-SAT workers (cores)")
    ap.add_argument("--json", help="also write the per-instance results here")
    a = ap.parse_args(argv)
    scen, sizes = a.row.split(":")
    row = tuple(int(v) for v in sizes.split(","))
    gen = ScenarioGenerator(scen, *row)
    insts = gen.generate(a.n, a.seed)
    print(f"# {gen.name}: {a.n} instances (seed {a.seed}), CP-SAT {a.time_limit:g} s x {a.workers} workers")
    print(f"# host: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, "
          f"load average {os.getloadavg()[0]:.1f} at start, python {platform.python_version()}")
    hdr = f"{'instance':<28} {'greedy':>8} {'heur.':>8} {'cpsat':>8} {'bound':>8} {'gap%':>6} {'status':>9} {'secs':>6}"
    print(hdr)
    rows = []
    for inst in insts:
        g = solve(inst, "greedy", seed=0)
        t = time.perf_counter()
        c = solve(inst, "cpsat", seed=0, time_limit=a.time_limit, workers=a.workers)
        dt = time.perf_counter() - t
        e = c.extra
        gap = 100 * (c.makespan - e["lower_bound"]) / c.makespan
        rows.append({"instance": inst.name, "greedy": g.makespan, "heuristic": e.get("hint_makespan"),
                     "cpsat": c.makespan, "lower_bound": e["lower_bound"], "status": e["status"],
                     "seconds": dt, "awt": c.awt, "redundancy": c.redundancy, "source": e.get("source")})
        print(f"{inst.name:<28} {g.makespan:8.3f} {_ms(e.get('hint_makespan')):>8} {c.makespan:8.3f} "
              f"{e['lower_bound']:8.3f} {gap:6.1f} {e['status']:>9} {dt:6.1f}", flush=True)
    gm = [r["greedy"] for r in rows]
    cm = [r["cpsat"] for r in rows]
    print()
    print(f"{'mean ± std (ours)':<28} greedy {_mean_std(gm)}   cpsat {_mean_std(cm)}   "
          f"cpsat/greedy {statistics.mean(c / g for c, g in zip(cm, gm)):.3f}   "
          f"optimal {sum(r['status'] == 'optimal' for r in rows)}/{len(rows)}   "
          f"mean gap to bound {statistics.mean(100 * (r['cpsat'] - r['lower_bound']) / r['cpsat'] for r in rows):.1f}%")
    p = paper_row(scen, *row)
    if p:
        ct, gr = p.get("CTAS-D"), p.get("Greedy")
        if ct and ct[1] is not None:
            print(f"{'paper CTAS-D (Gurobi)':<28} {ct[1]:.3f} ± {ct[2]:.3f} over its solved instances "
                  f"(success {ct[0]:.0%}, {ct[5]:g} s)")
        if gr:
            print(f"{'paper Greedy':<28} {gr[1]:.3f} ± {gr[2]:.3f}")
        if ct and ct[1] is not None and gr:
            print(f"{'paper CTAS-D/Greedy':<28} {ct[1] / gr[1]:.3f}")
            print(f"ours vs paper CTAS-D: mean makespan {100 * (statistics.mean(cm) / ct[1] - 1):+.1f}%  "
                  f"(ratio to greedy {statistics.mean(c / g for c, g in zip(cm, gm)):.3f} vs {ct[1] / gr[1]:.3f})")
    else:
        print("(no paper row with these sizes)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"row": gen.name, "seed": a.seed, "time_limit": a.time_limit, "workers": a.workers,
                       "results": rows, "paper": p}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
