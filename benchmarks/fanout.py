"""Solves per second through hmrta.fanout: in process, and as Ray tasks on a local Ray with 1 and
with 2 CPUs (or --workers LIST). Ray start-up is timed apart (a warm-up map) from the solves.

    .venv/bin/python benchmarks/fanout.py [--method greedy-coalition] [--count 40] [--workers 1,2]
    .venv/bin/python benchmarks/fanout.py --labels [--count 64] [--workers 1,2]
    .venv/bin/python benchmarks/fanout.py --schedules [--time-limit 0.5] [--count 8] [--workers 1,2,16]

``--labels``: labelled decisions per second of behaviour cloning's work item (``hmrta train
--jobs N``: one mission of the committed schedules dataset driven by its routes, greedy-coalition
where they have nothing admissible, every decision observed and labelled).

``--schedules``: teacher schedules per second instead (the work item of ``hmrta schedules``: one
broad-distribution mission solved by cpsat within ``--time-limit`` seconds, routes pruned).
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
    ap.add_argument("--schedules", action="store_true", help="teacher schedules/s (hmrta schedules' work item)")
    ap.add_argument("--labels", action="store_true", help="behaviour-cloning labels/s (hmrta train's work item)")
    ap.add_argument("--time-limit", type=float, default=0.5, help="--schedules: solver seconds per mission")
    a = ap.parse_args()
    count = lambda results: a.count  # noqa: E731  (work done by a map: missions, or labels with --labels)
    if a.labels:
        from pathlib import Path

        from hmrta.core import Rules
        from hmrta.rl.imitation import LabelJob, teacher_labels
        from hmrta.rl.schedules import ScheduleSet

        ss = ScheduleSet(Path(__file__).resolve().parents[1] / "policy/datasets/schedules-broad-10-30-s1.jsonl")
        rules = Rules(max_open=None)
        insts = [LabelJob(*ss.item(i)[:2], i, rules, "greedy-coalition", 0.0, {"scale": "mission"})
                 for i in ss.indices()[:a.count]]
        solve, what = teacher_labels, "labelled missions (schedules dataset, routes + greedy-coalition)"
        count = lambda results: sum(len(r.labels.acts) for r in results)  # noqa: E731
    elif a.schedules:
        from hmrta.rl.schedules import _solve_one

        spec = {"kind": "broad", "min_tasks": 10, "max_tasks": 30}
        insts = [(spec, 2024, i, a.time_limit, 1) for i in range(a.count)]
        solve, what = _solve_one, f"schedules (cpsat {a.time_limit:g} s, broad 10-30 tasks)"
    else:
        scen, *size = a.row.split(",")
        insts = ScenarioGenerator(scen, *map(int, size)).generate(a.count, 2024)
        solve, what = functools.partial(M.solve, method=a.method, seed=0), f"{a.method} on {a.row}"
    print(f"{a.count} x {what}; {os.cpu_count()} cores, load average before "
          f"{' / '.join(f'{x:.2f}' for x in os.getloadavg())} (1 / 5 / 15 min)")
    solve(insts[0])  # imports and caches, as in every worker's first task
    t = time.perf_counter()
    ref = Fanout(1).map(solve, insts)
    dt = time.perf_counter() - t
    unit = "labels/s" if a.labels else "solves/s"
    print(f"in process        : {count(ref) / dt:7.2f} {unit}")
    for n in map(int, a.workers.split(",")):
        t0 = time.perf_counter()
        with Fanout(n, use_ray=True) as fan:
            fan.map(solve, insts[: 2 * n])  # start-up and warm workers
            up = time.perf_counter() - t0
            t = time.perf_counter()
            sols = fan.map(solve, insts)
            dt = time.perf_counter() - t
        if a.labels:
            assert [r.labels.acts for r in sols] == [r.labels.acts for r in ref]  # the same labels
        elif not a.schedules:  # (an anytime solver on the clock may differ between runs)
            assert [s.makespan for s in sols] == [s.makespan for s in ref]  # the same answers
        print(f"{f'Ray, {n} CPU' + ('s' if n > 1 else ''):<18}: {count(sols) / dt:7.2f} {unit}  "
              f"(start-up and warm-up {up:.1f} s)")
    print(f"load average after {' / '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
