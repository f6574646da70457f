"""Learned-policy benchmarks (prints figures; not a test).

1. Training throughput: REINFORCE iterations at fixed sizes (episodes/s, decisions/s for collection
   and for the whole iteration including the re-scoring backward pass).
2. Inference seconds per instance, RL(g.) and RL(s.10), for every paper row, next to the paper's
   reported compute time (target: RL(g.) ten times faster than the paper for the same row).

usage: python benchmarks/rl_throughput.py [--checkpoint P] [--count N] [--large-count N] [--threads T]
                                         [--train-iters N] [--device cpu|cuda]

``--count 0`` skips the inference table; ``--device cuda`` trains on a GPU (inference stays on the CPU).
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import torch

from hmrta.bench import paper_suite
from hmrta.generators import ScenarioGenerator
from hmrta.methods import solve
from hmrta.rl.train import DEFAULTS, Trainer, deep_update


def training_throughput(iters: int, device: str = "cpu") -> None:
    print(f"## Training throughput (REINFORCE, 8 instances x 10 rollouts per iteration, network on {device})")
    print("| size (agents, species, tasks) | episodes/s | collection decisions/s | iteration decisions/s |")
    print("|---|---|---|---|")
    for s, per, m in [(3, 3, 20), (5, 5, 50)]:
        cfg = deep_update(DEFAULTS, {"validation": {"rows": [[4, 2, 5, 2, 1]]}})
        with tempfile.TemporaryDirectory() as d:
            tr = Trainer(cfg, d, device=device, log=lambda *_: None)
            gen = ScenarioGenerator("MA-AT", s * per, s, m, 5)
            tr._instances = lambda n, task_range=None: [gen.sample(tr.np_rng) for _ in range(n)]  # fixed size
            rows = [tr.train_step() for _ in range(iters)]
        secs = sum(r["seconds"] for r in rows)
        eps = tr.episodes / secs
        dec = statistics.mean(r["decisions_per_s"] for r in rows)
        tot = tr.decisions / secs
        print(f"| {s * per}, {s}, {m} | {eps:.2f} | {dec:.0f} | {tot:.0f} |")


def inference(checkpoint: str | None, count: int, large_count: int) -> None:
    print("\n## Inference seconds per instance (mean), seed 1000 test sets")
    print("| row | n | greedy s | RL(g.) s | RL(s.10) s | paper RL(g.) s | paper RL(s.10) s | RL(g.) speed-up vs paper |")
    print("|---|---|---|---|---|---|---|---|")
    opts = {"checkpoint": checkpoint} if checkpoint else {}
    for row in paper_suite():
        n = count if row.tasks <= 50 else large_count
        insts = row.generator().generate(n, 1000)
        t = {m: statistics.mean(solve(i, m, 0, **(opts if m != "greedy" else {})).compute_seconds for i in insts)
             for m in ("greedy", "rl", "rl-s10")}
        p = row.paper() or {}
        pg = (p.get("RL(g.)") or [None] * 6)[5]
        ps = (p.get("RL(s.10)") or [None] * 6)[5]
        speed = f"{pg / t['rl']:.1f}x" if pg else "—"
        print(f"| {row.key} | {n} | {t['greedy']:.3f} | {t['rl']:.3f} | {t['rl-s10']:.3f} | {pg} | {ps} | {speed} |",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=None, help="policy checkpoint (default: shipped)")
    ap.add_argument("--count", type=int, default=5, help="instances per row up to 50 tasks (0: no inference table)")
    ap.add_argument("--large-count", type=int, default=2, help="instances per row above 50 tasks")
    ap.add_argument("--train-iters", type=int, default=3, help="training iterations per size (0: skip)")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--device", default="cpu", help="where training runs the network: cpu, cuda or cuda:N")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    t0 = time.time()
    if a.train_iters:
        training_throughput(a.train_iters, a.device)
    if a.count:
        inference(a.checkpoint, a.count, a.large_count)
    print(f"\n(total {time.time() - t0:.0f} s, torch threads {a.threads})")


if __name__ == "__main__":
    main()
