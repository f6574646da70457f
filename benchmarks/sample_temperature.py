"""RL(s.10) at several sampling temperatures, against greedy-coalition (prints figures; not a test).

On the dev missions (the families at seed 2000 or the paper rows at seed 4242, never a test seed),
each mission is solved by greedy-coalition, by the checkpoint's greedy decoding (RL(g.)) and, for
each temperature T, by ten rollouts sampled from softmax(logits / T) in one batch (mission seeds
0-9, sampling generator seeded with the mission's index), the shortest kept: ``rl-sample``'s
algorithm. Prints, per row, the mean per-mission makespan ratio to greedy-coalition, then the mean
over the rows and the worst row; this chose the default of ``rl-sample``'s ``temperature``
(docs/training.md, "Sampling temperature").

usage: python benchmarks/sample_temperature.py [--checkpoint P] [--suite families|paper]
           [--temperatures 1,0.3,0.15,0.1] [--count 10] [--max-tasks 50]
"""
from __future__ import annotations

import argparse
import statistics

import torch

from hmrta.baselines import solve_greedy_coalition
from hmrta.bench import paper_suite
from hmrta.core import MissionState
from hmrta.families import family_suite
from hmrta.rl.inference import load_policy
from hmrta.rl.rollout import rollout

DEV_SEED = {"families": 2000, "paper": 4242}


def temperatures(text: str) -> list[float]:
    try:
        out = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not out or any(not t > 0 for t in out):
        raise argparse.ArgumentTypeError(f"expected positive temperatures, got {text!r}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=None, help="policy checkpoint (default: the shipped default.pt)")
    p.add_argument("--suite", choices=sorted(DEV_SEED), default="families",
                   help="dev missions: the families (seed 2000) or the paper rows (seed 4242)")
    p.add_argument("--temperatures", type=temperatures, default=[1.0, 0.3, 0.15, 0.1],
                   help="comma list of sampling temperatures (default 1,0.3,0.15,0.1)")
    p.add_argument("--count", type=int, default=10, help="missions per row (default 10)")
    p.add_argument("--samples", type=int, default=10, help="sampled rollouts per mission (default 10)")
    p.add_argument("--max-tasks", type=int, default=50, help="rows up to this many tasks (default 50)")
    args = p.parse_args(argv)
    if args.count < 1 or args.samples < 1:
        p.error("--count and --samples: expected positive integers")

    torch.set_num_threads(1)
    pol = load_policy(args.checkpoint)
    if args.suite == "families":
        rows = [(r.key, r.generator()) for r in family_suite(max_tasks=args.max_tasks)]
    else:
        rows = [(r.key, r.generator()) for r in paper_suite() if r.tasks <= args.max_tasks]
    names = ["rl"] + [f"T={t:g}" for t in args.temperatures]
    means: dict[str, list[float]] = {n: [] for n in names}
    print(f"{'row':28s}" + "".join(f"{n:>10s}" for n in names))
    for key, gen in rows:
        ratios: dict[str, list[float]] = {n: [] for n in names}
        for i, inst in enumerate(gen.generate(args.count, DEV_SEED[args.suite])):
            ref = solve_greedy_coalition(inst, 0).makespan
            g = MissionState(inst, seed=0, rules=pol.rules)
            rollout(pol.model, [g], sample=False)
            ratios["rl"].append(g.makespan / ref)
            for t, name in zip(args.temperatures, names[1:]):
                states = [MissionState(inst, seed=k, rules=pol.rules) for k in range(args.samples)]
                rollout(pol.model, states, sample=True, generator=torch.Generator().manual_seed(i), temperature=t)
                ratios[name].append(min(s.makespan if s.success else float("inf") for s in states) / ref)
        row = {n: statistics.mean(v) for n, v in ratios.items()}
        for n, v in row.items():
            means[n].append(v)
        print(f"{key:28s}" + "".join(f"{row[n]:10.3f}" for n in names), flush=True)
    print(f"{'mean of rows':28s}" + "".join(f"{statistics.mean(means[n]):10.4f}" for n in names))
    print(f"{'worst row':28s}" + "".join(f"{max(means[n]):10.3f}" for n in names))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
