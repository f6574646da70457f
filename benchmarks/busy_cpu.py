"""The learned policy on a busy CPU (prints figures; not a test).

Runs the 150-robot / 500-task MA-AT rl solve (``ScenarioGenerator("MA-AT", 150, 5, 500, 5)``,
greedy decoding, one mission at a time) alone and then beside busy processes (pure-Python spin
loops, started as subprocesses and killed by PID at the end), with torch on one thread (what
``hmrta solve/bench/demo`` and the ROS agents do) and with torch's own thread count (a thread per
core, every forward pass on it), and prints the milliseconds per decision and the slowdown of each.
The acceptance is a slowdown within about the fair share (<= 4x) with one thread.

Each measurement runs in a fresh interpreter (thread settings meet torch before any work). A
measurement stops after ``--seconds`` per mission; alone and busy are compared over the same first
decisions of each mission (the cost of a decision changes along a mission).

usage: python benchmarks/busy_cpu.py [--instances N] [--seconds S] [--busy B] [--seed SEED]
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import time

WARMUP = 3  # first decisions of a mission left out (first calls: allocations, caches)
SPIN = "while True:\n    pass\n"


class _Stop(Exception):
    pass


def worker(threads: str, instances: int, seed: int, seconds: float, checkpoint: str | None) -> dict:
    """Per-decision milliseconds of the rl solve of each mission (in this process)."""
    import torch
    from hmrta.cli import set_torch_threads
    from hmrta.core import MissionState
    from hmrta.generators import ScenarioGenerator
    from hmrta.rl import rollout as ro
    from hmrta.rl.inference import load_policy

    own = torch.get_num_threads()
    if threads == "default":
        ro.SINGLE_THREAD_STATES = 0  # every forward pass on torch's own threads
    else:
        set_torch_threads(torch, int(threads))
    pol = load_policy(checkpoint)
    out = {"threads": torch.get_num_threads(), "torch_default": own, "missions": []}
    for inst in ScenarioGenerator("MA-AT", 150, 5, 500, 5).generate(instances, seed):
        state = MissionState(inst, seed=0, rules=pol.rules)
        stamps: list[float] = []
        t_end = time.perf_counter() + seconds

        def tick(*_, stamps=stamps, t_end=t_end):  # once per decision, after its forward pass
            now = time.perf_counter()
            stamps.append(now)
            if now > t_end:
                raise _Stop

        try:
            ro.rollout(pol.model, [state], sample=False, before_step=tick)
        except _Stop:
            pass
        ms = [(b - a) * 1000.0 for a, b in itertools.pairwise(stamps)]
        out["missions"].append({"name": inst.name, "ms": ms, "done": bool(state.done)})
    return out


def measure(threads: str, args, busy: int) -> dict:
    """Run a worker in a fresh interpreter beside ``busy`` spinning processes."""
    spinners = []
    try:
        for _ in range(busy):
            spinners.append(subprocess.Popen([sys.executable, "-c", SPIN], stdin=subprocess.DEVNULL))
        if spinners:
            time.sleep(0.5)  # let them take the cores
        cmd = [sys.executable, __file__, "--worker", threads, "--instances", str(args.instances),
               "--seed", str(args.seed), "--seconds", str(args.seconds)]
        if args.checkpoint:
            cmd += ["--checkpoint", args.checkpoint]
        limit = 120.0 + args.instances * (args.seconds + 60.0)
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=limit, check=False)
        if p.returncode != 0:
            raise RuntimeError(f"worker ({threads} threads, {busy} busy) failed:\n{p.stderr[-3000:]}")
        res = json.loads(p.stdout.strip().splitlines()[-1])
        res["load"] = [round(x, 2) for x in os.getloadavg()]
        return res
    finally:
        for s in spinners:  # by PID, the processes started here
            s.kill()
        for s in spinners:
            s.wait(timeout=10)


def compare(alone: dict, busy: dict) -> tuple[float, float, int]:
    """Mean ms per decision alone and busy over the decisions both made, and how many."""
    a_ms, b_ms = [], []
    for ma, mb in zip(alone["missions"], busy["missions"]):
        k = min(len(ma["ms"]), len(mb["ms"]))
        a_ms += ma["ms"][WARMUP:k]
        b_ms += mb["ms"][WARMUP:k]
    if not a_ms:
        raise RuntimeError("no decisions to compare: raise --seconds")
    return statistics.mean(a_ms), statistics.mean(b_ms), len(a_ms)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--instances", type=int, default=2, help="missions (seeded test set)")
    ap.add_argument("--seed", type=int, default=1000, help="test-set seed")
    ap.add_argument("--seconds", type=float, default=20.0, help="measuring time per mission and run")
    ap.add_argument("--busy", type=int, default=2, help="busy processes beside the solve")
    ap.add_argument("--checkpoint", default=None, help="policy checkpoint (default: the shipped one)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.instances, args.seed, args.seconds, args.checkpoint)))
        return 0
    if args.instances < 1 or args.seconds <= 0 or args.busy < 0:
        ap.error("--instances, --seconds: expected positive values; --busy: at least 0")
    print(f"# rl on a busy CPU: MA-AT 150 robots / 500 tasks, {args.instances} mission(s) (seed {args.seed}), "
          f"{os.cpu_count()} cores, up to {args.seconds:g} s per mission, beside {args.busy} busy processes\n")
    start_load = [round(x, 2) for x in os.getloadavg()]
    print(f"| torch threads | alone ms/decision | beside {args.busy} busy ms/decision | slowdown | "
          f"busy vs one thread alone | decisions |")
    print("|---|---|---|---|---|---|")
    slow, vs_base, one_alone, loads = {}, {}, None, []
    for threads in ("1", "default"):
        alone = measure(threads, args, 0)
        busy = measure(threads, args, args.busy)
        a, b, n = compare(alone, busy)
        slow[threads] = b / a
        one_alone = one_alone or alone  # one thread alone: the machine's own figure, over the same decisions
        base = compare(one_alone, busy)[0]
        vs_base[threads] = b / base
        label = "1" if threads == "1" else f"torch's own ({alone['threads']})"
        print(f"| {label} | {a:.2f} | {b:.2f} | {b / a:.1f}x | {b / base:.1f}x | {n} |", flush=True)
        loads.append(f"{label} thread(s): after alone {alone['load']}, after busy {busy['load']}")
    ok = slow["1"] <= 4.0
    print(f"\none thread: slowdown {slow['1']:.1f}x beside {args.busy} busy processes "
          f"({'within' if ok else 'above'} the 4x target); torch's own threads: {slow['default']:.1f}x "
          f"(and {vs_base['default']:.0f}x the one-thread figure alone)")
    print(f"load average (1, 5, 15 min): at the start {start_load}; " + "; ".join(loads)
          + " (alone: no busy process of this benchmark; anything else running on the machine counts)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
