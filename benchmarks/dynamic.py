"""Dynamic missions: tasks released over time and robots lost, for each method, beside a
clairvoyant CP-SAT reference.

Missions are MA-AT (25,5,50,5) (``hmrta generate`` rows). Half of the tasks (drawn at random) are
released over time as a Poisson stream (mean gap ``--gap``); 10% of the robots are lost at times
drawn uniformly in [0, the last release]. Every method plans online (it sees a task at its release
and a loss when it happens); the clairvoyant reference is CP-SAT given every task at time 0 and
the whole team (``--cpsat-limit`` seconds per mission, on the same missions unless ``--cpsat``
limits them): a bound on what knowing the future is worth, not a feasible plan for the dynamic
mission. Its response column is the mean finish time (every task released at 0).

    .venv/bin/python benchmarks/dynamic.py --count 10
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import random
import sys

import numpy as np

from hmrta import methods
from hmrta.generators import ScenarioGenerator


def dynamic_mission(inst, seed: int, gap: float, lost: float = 0.1):
    rng = random.Random(seed)
    M, A = inst.n_tasks, inst.n_agents
    late = sorted(rng.sample(range(M), M // 2))
    t, release = 0.0, {}
    for m in late:
        t += rng.expovariate(1.0 / gap)
        release[m] = t
    tasks = tuple(dataclasses.replace(task, release=release.get(m, 0.0)) for m, task in enumerate(inst.tasks))
    horizon = max(release.values(), default=1.0)
    losses = sorted((rng.uniform(0.0, horizon), a) for a in rng.sample(range(A), max(1, round(lost * A))))
    events = tuple({"t": t, "type": "drop_agent", "agent": a} for t, a in losses)
    return dataclasses.replace(inst, tasks=tasks, events=events, _cache={})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--count", type=int, default=10, help="missions")
    ap.add_argument("--seed", type=int, default=2024, help="generator seed")
    ap.add_argument("--gap", type=float, default=1.5, help="mean time between two releases")
    ap.add_argument("--methods", default="greedy,greedy-coalition,rl,rl-s10")
    ap.add_argument("--cpsat", type=int, default=None,
                    help="missions given to the clairvoyant reference (default: all; 0: none)")
    ap.add_argument("--cpsat-limit", type=float, default=5.0, help="CP-SAT seconds per mission")
    args = ap.parse_args(argv)
    if args.cpsat is None:
        args.cpsat = args.count
    gen = ScenarioGenerator("MA-AT", 25, 5, 50, 5)
    base = [gen.instance(args.seed, i) for i in range(args.count)]
    dyn = [dynamic_mission(b, args.seed * 1000 + i, args.gap) for i, b in enumerate(base)]
    rows = []
    for spec in args.methods.split(","):
        sols = [methods.solve(d, spec, seed=i) for i, d in enumerate(dyn)]
        ok = [s for s in sols if s.success]
        lost = [s.extra["dynamic"]["tasks_lost"] for s in sols]
        rows.append((spec, len(ok), float(np.mean([s.makespan for s in ok])) if ok else math.nan,
                     float(np.mean([s.extra["dynamic"]["mean_response"] for s in sols])),
                     float(np.mean([sum(x.values()) for x in lost])),
                     float(np.mean([s.compute_seconds for s in sols]))))
    if args.cpsat:
        n = min(args.cpsat, len(base))
        sols = [methods.solve(b, "cpsat", seed=i, time_limit=args.cpsat_limit) for i, b in enumerate(base[:n])]
        ok = [s for s in sols if s.success]
        resp = [np.mean([t["finish"] for t in s.tasks]) for s in ok]
        what = f"{n} missions, " if n < args.count else ""
        rows.append((f"cpsat clairvoyant ({what}{args.cpsat_limit:g} s)", len(ok),
                     float(np.mean([s.makespan for s in ok])) if ok else math.nan,
                     float(np.mean(resp)) if resp else math.nan, 0.0,
                     float(np.mean([s.compute_seconds for s in sols]))))
    print(f"Dynamic MA-AT (25,5,50,5): {args.count} missions (seed {args.seed}), half of the tasks released as a "
          f"Poisson stream (mean gap {args.gap:g}), 10% of robots lost at random times\n")
    print("| method | success | makespan | mean response | tasks lost | compute s |")
    print("|---|---|---|---|---|---|")
    for name, nok, ms, resp, lost, cs in rows:
        total = args.count if not name.startswith("cpsat") else min(args.cpsat, args.count)
        print(f"| {name} | {nok}/{total} | {ms:.2f} | {resp:.2f} | {lost:.2f} | {cs:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
