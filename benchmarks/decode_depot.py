#!/usr/bin/env python3
"""Greedy decoding with the depot decided on its total probability (prints figures; not a test).

RL(g.) decodes by the checkpoint's ``model.greedy_depot``. "argmax" takes the most likely row of
[depot, tasks]; with many admissible tasks of similar value the tasks share the probability and
the depot, one row, can be the argmax while the tasks together are more likely (docs/training.md,
"Deciding the depot on its total probability"). This benchmark compares, mission by mission and
whatever the checkpoint's own setting, the argmax with the two-level rule "majority": go home
only when the depot's probability is at least 1/2, otherwise take the most likely task.
It prints per row the mean makespan of each, the missions whose plan changed, the decisions that
changed, and the number of decisions per mission. Dev seeds only (never the test seed 1000).

usage: python benchmarks/decode_depot.py [--suite families|paper|large] [--count N] [--seed S]
       [--checkpoint PATH]
"""
from __future__ import annotations

import argparse
import statistics

PAPER_ROWS = {"SA-BT": [(9, 3, 20, 3), (25, 5, 20, 5), (25, 5, 50, 5), (50, 5, 50, 5)],
              "SA-AT": [(9, 3, 20, 3), (15, 5, 20, 5), (25, 5, 20, 5), (50, 5, 50, 5)],
              "MA-AT": [(9, 3, 20, 3), (15, 5, 20, 5), (25, 5, 20, 5), (25, 5, 50, 5), (50, 5, 50, 5)]}
LARGE_ROWS = [(50, 5, 200, 5), (150, 10, 500, 5), (150, 5, 500, 5)]
DEFAULTS = {"families": (10, 2000), "paper": (20, 4242), "large": (10, 5000)}  # (count, seed)


def rollout(pol, inst, two_level: bool) -> tuple[float, int, int]:
    """(makespan, decisions, decisions where the two-level rule overrode the argmax), whatever the
    checkpoint's own ``greedy_depot``."""
    import torch

    from hmrta.core import MissionState
    from hmrta.rl.features import batch_observations
    from hmrta.rl.rollout import greedy_rows

    st = MissionState(inst, seed=0, rules=pol.rules)
    overridden = 0
    with torch.inference_mode():
        while not st.done:
            obs, nodes = batch_observations([st], **pol.model.cfg.view())
            logits = pol.model(**obs)  # [1, T] row 0 = depot
            row = int(greedy_rows(logits, "majority" if two_level else "argmax")[0])
            overridden += row != int(logits[0].argmax())
            st.step(int(nodes[0][row]))
    if not st.success:
        raise RuntimeError(f"mission {inst.name} failed: {st.failure}")
    return st.makespan, st.decisions, overridden


def rows(suite: str, count: int, seed: int):
    from hmrta.families import family_suite
    from hmrta.generators import ScenarioGenerator

    if suite == "families":
        return [(r.key, r.generator().generate(count, seed)) for r in family_suite(max_tasks=50)]
    if suite == "paper":
        return [(f"{t} {','.join(map(str, r))}", ScenarioGenerator(t, *r).generate(count, seed))
                for t, rs in PAPER_ROWS.items() for r in rs]
    return [(f"MA-AT {','.join(map(str, r))}", ScenarioGenerator("MA-AT", *r).generate(count, seed))
            for r in LARGE_ROWS]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", choices=sorted(DEFAULTS), default="families",
                    help="families up to 50 tasks, paper rows up to 50 tasks, or the three large MA-AT rows")
    ap.add_argument("--count", type=int, default=None, help="missions per row (default 10, 20, 10 by suite)")
    ap.add_argument("--seed", type=int, default=None, help="instance seed (default: the suite's dev seed)")
    ap.add_argument("--checkpoint", default=None, help="policy checkpoint (default: the shipped one)")
    args = ap.parse_args()
    count, seed = DEFAULTS[args.suite]
    count, seed = args.count or count, args.seed if args.seed is not None else seed
    if count < 1:
        ap.error("--count: expected a positive integer")
    if seed == 1000:
        ap.error("--seed 1000 is the test seed; this benchmark is for dev seeds")

    import torch

    from hmrta.bench import code_version
    from hmrta.cli import set_torch_threads
    from hmrta.rl.inference import load_policy

    set_torch_threads(torch, 1)
    pol = load_policy(args.checkpoint)
    print(f"# {args.suite}, {count} missions per row, seed {seed}, code {code_version()}, torch on 1 thread\n")
    print("| row | argmax | two-level | ratio | missions changed | decisions overridden | decisions per mission (argmax -> two-level) |")
    print("|---|---:|---:|---:|---:|---:|---|")
    ratios = []
    for name, insts in rows(args.suite, count, seed):
        a = [rollout(pol, i, False) for i in insts]
        b = [rollout(pol, i, True) for i in insts]
        ma, mb = statistics.mean(x[0] for x in a), statistics.mean(x[0] for x in b)
        ratios.append(mb / ma)
        changed = sum(x[0] != y[0] for x, y in zip(a, b))
        print(f"| {name} | {ma:.3f} | {mb:.3f} | {mb / ma:.4f} | {changed}/{len(insts)} | {sum(y[2] for y in b)} | "
              f"{sum(x[1] for x in a) / len(a):.0f} -> {sum(y[1] for y in b) / len(b):.0f} |", flush=True)
    print(f"\nmean over the rows of two-level / argmax: {statistics.mean(ratios):.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
