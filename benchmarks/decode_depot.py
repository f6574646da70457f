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

DEFAULTS = {"families": (10, 2000), "paper": (20, 4242), "large": (10, 5000)}  # (count, seed)


class Decoded:
    """The policy's traced network with its greedy decoding set to ``rule`` (whatever the
    checkpoint's own), counting the decisions where that rule departs from the argmax; driven by
    ``hmrta.rl.rollout.rollout``, the path RL(g.) itself takes."""

    def __init__(self, model, rule: str):
        import dataclasses

        self.model, self.cfg, self.overridden = model, dataclasses.replace(model.cfg, greedy_depot=rule), 0

    def __call__(self, **obs):
        from hmrta.rl.rollout import greedy_rows

        logits = self.model(**obs)  # [b, T] row 0 = depot
        self.overridden += int((greedy_rows(logits, self.cfg.greedy_depot) != logits.argmax(-1)).sum())
        return logits


def solve(pol, inst, rule: str) -> tuple[float, int, int]:
    """(makespan, decisions, decisions where ``rule`` overrode the argmax) of one greedy rollout."""
    from hmrta.core import MissionState
    from hmrta.rl.rollout import rollout

    st, model = MissionState(inst, seed=0, rules=pol.rules), Decoded(pol.model, rule)
    rollout(model, [st], sample=False)
    if not st.success:
        raise RuntimeError(f"mission {inst.name} failed: {st.failure}")
    return st.makespan, st.decisions, model.overridden


def rows(suite: str, count: int, seed: int):
    from hmrta.bench import paper_suite
    from hmrta.families import family_suite

    if suite == "families":
        return [(r.key, r.generator().generate(count, seed)) for r in family_suite(max_tasks=50)]
    tables = ["MA-AT-large"] if suite == "large" else ["SA-BT", "SA-AT", "MA-AT"]
    return [(f"{r.scenario} {r.agents},{r.species},{r.tasks},{r.skills}", r.generator().generate(count, seed))
            for r in paper_suite(tables)]


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
        a = [solve(pol, i, "argmax") for i in insts]
        b = [solve(pol, i, "majority") for i in insts]
        ma, mb = statistics.mean(x[0] for x in a), statistics.mean(x[0] for x in b)
        ratios.append(mb / ma)
        changed = sum(x[0] != y[0] for x, y in zip(a, b))
        print(f"| {name} | {ma:.3f} | {mb:.3f} | {mb / ma:.4f} | {changed}/{len(insts)} | {sum(y[2] for y in b)} | "
              f"{sum(x[1] for x in a) / len(a):.0f} -> {sum(y[1] for y in b) / len(b):.0f} |", flush=True)
    print(f"\nmean over the rows of two-level / argmax: {statistics.mean(ratios):.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
