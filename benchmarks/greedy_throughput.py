#!/usr/bin/env python3
"""Greedy rollout throughput (issue 2, point 10): prints rollouts per second and policy decisions
per second of the greedy baseline on seeded MA-AT sets. A script, not a test.

    .venv/bin/python benchmarks/greedy_throughput.py [--count N] [--seed S] [--rows 25,5,50,5 ...]

Instance generation is excluded from the timing; each row's set is rolled out once to warm up,
then ``--repeat`` times timed (the best repeat is reported, as is usual for throughput).
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.generators import ScenarioGenerator, row_name
from hmrta.sim import run

DEFAULT_ROWS = ["25,5,50,5", "150,10,500,5"]


def bench(row: tuple[int, int, int, int], count: int, seed: int, repeat: int) -> dict:
    insts = ScenarioGenerator("MA-AT", *row).generate(count, seed)
    policy = Greedy()
    best = None
    for r in range(repeat + 1):  # r = 0: warm-up
        t0 = time.perf_counter()
        decisions = successes = 0
        for inst in insts:
            state = run(inst, policy, seed, GREEDY_RULES)
            decisions += state.decisions
            successes += state.success
        dt = time.perf_counter() - t0
        if r and (best is None or dt < best[0]):
            best = (dt, decisions, successes)
    dt, decisions, successes = best
    return {"row": row_name("MA-AT", *row), "count": count, "seconds": dt, "success": successes,
            "rollouts_per_s": count / dt, "decisions_per_s": decisions / dt,
            "decisions_per_rollout": decisions / count}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--rows", nargs="+", default=DEFAULT_ROWS, help="agents,species,tasks,skills (MA-AT)")
    ap.add_argument("--count", type=int, default=20, help="instances per row (default 20)")
    ap.add_argument("--seed", type=int, default=1, help="set seed (default 1)")
    ap.add_argument("--repeat", type=int, default=3, help="timed repeats, best kept (default 3)")
    args = ap.parse_args()
    print(f"# greedy throughput: python {platform.python_version()}, numpy {np.__version__}, "
          f"{platform.machine()} x{os.cpu_count()} ({platform.processor() or 'cpu'}), single process, "
          f"seed {args.seed}, {args.count} instances/row, best of {args.repeat}")
    print("| row | instances | success | decisions/rollout | rollouts/s | decisions/s |")
    print("|---|---:|---:|---:|---:|---:|")
    for spec in args.rows:
        row = tuple(int(x) for x in spec.split(","))
        r = bench(row, args.count, args.seed, args.repeat)  # type: ignore[arg-type]
        print(f"| {r['row']} | {r['count']} | {r['success']}/{r['count']} | {r['decisions_per_rollout']:.0f} | "
              f"{r['rollouts_per_s']:.1f} | {r['decisions_per_s']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
