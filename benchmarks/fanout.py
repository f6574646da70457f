"""Solves per second through hmrta.fanout: in process, and as Ray tasks on a local Ray with 1 and
with 2 CPUs (or --workers LIST). Ray start-up is timed apart (a warm-up map) from the solves.

    .venv/bin/python benchmarks/fanout.py [--method greedy-coalition] [--count 40] [--workers 1,2]
"""
from __future__ import annotations

import argparse
import functools
import os
import time

from hmrta import methods as M
from hmrta.fanout import Fanout
from hmrta.generators import ScenarioGenerator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", default="greedy-coalition")
    ap.add_argument("--row", default="MA-AT,9,3,20,3", help="scenario,agents,species,tasks,skills")
    ap.add_argument("--count", type=int, default=40, help="missions solved per measurement")
    ap.add_argument("--workers", default="1,2", help="comma list of Ray CPU counts")
    a = ap.parse_args()
    scen, *size = a.row.split(",")
    insts = ScenarioGenerator(scen, *map(int, size)).generate(a.count, 2024)
    solve = functools.partial(M.solve, method=a.method, seed=0)
    print(f"{a.count} x {a.method} on {a.row}; {os.cpu_count()} cores, load average before "
          f"{' / '.join(f'{x:.2f}' for x in os.getloadavg())} (1 / 5 / 15 min)")
    solve(insts[0])  # imports and caches, as in every worker's first task
    t = time.perf_counter()
    ref = Fanout(1).map(solve, insts)
    dt = time.perf_counter() - t
    print(f"in process        : {a.count / dt:7.1f} solves/s")
    for n in map(int, a.workers.split(",")):
        t0 = time.perf_counter()
        with Fanout(n, use_ray=True) as fan:
            fan.map(solve, insts[: 2 * n])  # start-up and warm workers
            up = time.perf_counter() - t0
            t = time.perf_counter()
            sols = fan.map(solve, insts)
            dt = time.perf_counter() - t
        assert [s.makespan for s in sols] == [s.makespan for s in ref]  # the same answers
        print(f"Ray, {n} CPU{'s' if n > 1 else ' '}       : {a.count / dt:7.1f} solves/s  (start-up and warm-up {up:.1f} s)")
    print(f"load average after {' / '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
