#!/usr/bin/env python3
"""Offline cost per decision as missions grow (prints figures; not a test).

Rolls out MA-AT missions of 25 robots / 50 tasks up to 1000 robots / 5000 tasks, all offline in
this process with torch on one thread, with greedy (``GREEDY_RULES``) and the learned policy (the
shipped checkpoint, greedy decoding, ``hmrta.rl.rollout.rollout`` as ``hmrta solve --method rl``
runs it), and prints per size the milliseconds per decision and the total time, split into

* greedy: the policy's choice and the state machine's step (commit, then events and masks up to
  the next decision);
* rl: the observation (window selection, features, batch tensors), the network call (its traced
  form, as inference runs it), and the rest (the state machine's step, the greedy choice and
  bookkeeping).

Each cost's growth is fitted as a power of the mission size (the slope of log cost against log
number of tasks): ~0 is flat, 1 linear. The network call is also set against its arithmetic
floor: its FLOPs per decision (counted by torch) over the single-thread matrix-multiply rate of
this CPU. Costs are CPU times of this (single) thread, which other processes on the machine
disturb less than wall times (also printed); the machine load (``os.getloadavg``) is printed
before and after. Greedy keeps the best of ``--repeat`` rollouts of each mission.

``--checkpoint A B ...`` runs the learned policy with each checkpoint, one after the other on
every size of every round, and prints each one's time against the first's, round by round: on a
machine whose speed drifts, a comparison of checkpoints made minutes apart is on the same footing.

usage: python benchmarks/scale_offline.py [--sizes 25,5,50 150,10,500 ...] [--count N ...]
       [--methods greedy rl] [--repeat R] [--rounds N] [--seed S] [--checkpoint CK ...] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import time

import numpy as np

DEFAULT_SIZES = ["25,5,50", "150,10,500", "300,10,1000", "600,10,2000", "1000,10,5000"]
DEFAULT_COUNTS = [10, 2, 1, 1, 1]  # missions per size (about 2000 decisions or more each)


def run_greedy(inst, seed: int) -> dict:
    from hmrta.baselines import GREEDY_RULES, Greedy
    from hmrta.core import MissionState

    cpu = time.thread_time
    w0, t0 = time.perf_counter(), cpu()
    state = MissionState(inst, seed=seed, rules=GREEDY_RULES)
    t_init = cpu() - t0
    policy = Greedy()
    t_pol = t_step = 0.0
    while not state.done:
        t1 = cpu()
        node = policy(state)
        t2 = cpu()
        state.step(node)
        t3 = cpu()
        t_pol += t2 - t1
        t_step += t3 - t2
    return {"decisions": state.decisions, "success": state.success, "makespan": state.makespan,
            "total": cpu() - t0, "wall": time.perf_counter() - w0, "init": t_init,
            "parts": {"policy": t_pol, "core": t_step}}


class _TimedModel:
    """The network, timing its calls (what rollout reads of it: ``cfg`` and the call)."""

    def __init__(self, model):
        self.model, self.cfg, self.seconds = model, model.cfg, 0.0

    def __call__(self, **obs):
        t0 = time.thread_time()
        out = self.model(**obs)
        self.seconds += time.thread_time() - t0
        return out


def run_rl(inst, seed: int, pol) -> dict:
    from hmrta.core import MissionState
    from hmrta.rl import rollout as ro

    observe = ro.batch_observations
    spent = {"obs": 0.0}

    def timed_obs(*a, **kw):
        t0 = time.thread_time()
        out = observe(*a, **kw)
        spent["obs"] += time.thread_time() - t0
        return out

    model = _TimedModel(pol.model)
    ro.batch_observations = timed_obs  # this process only: time the observations of rollout
    try:
        w0, t0 = time.perf_counter(), time.thread_time()
        state = MissionState(inst, seed=seed, rules=pol.rules)
        t_init = time.thread_time() - t0
        ro.rollout(model, [state], sample=False)
        total, wall = time.thread_time() - t0, time.perf_counter() - w0
    finally:
        ro.batch_observations = observe
    rest = total - t_init - spent["obs"] - model.seconds
    return {"decisions": state.decisions, "success": state.success, "makespan": state.makespan,
            "total": total, "wall": wall, "init": t_init,
            "parts": {"observe": spent["obs"], "network": model.seconds, "core": rest}}


def summarise(runs: list[dict], A: int, S: int, M: int, n: int) -> dict:
    """The figures of one size from its runs (``n`` missions' worth: per mission and per decision)."""
    dec = sum(r["decisions"] for r in runs)
    ok = [r["makespan"] for r in runs if r["success"]]
    return {"robots": A, "species": S, "tasks": M, "missions": n, "decisions": dec,
            "success": len(ok), "makespan": statistics.mean(ok) if ok else math.nan,
            "seconds_per_mission": sum(r["total"] for r in runs) / n,
            "wall_seconds_per_mission": sum(r["wall"] for r in runs) / n,
            "wall_ms_per_decision": 1000.0 * sum(r["wall"] for r in runs) / dec,
            "ms_per_decision": 1000.0 * sum(r["total"] - r["init"] for r in runs) / dec,
            "init_ms": 1000.0 * sum(r["init"] for r in runs) / n,
            "parts_ms_per_decision": {k: 1000.0 * sum(r["parts"][k] for r in runs) / dec for k in runs[0]["parts"]}}


def network_floor(pol) -> dict:
    """FLOPs of one network call at the full observation window (counted on the network), the
    single-thread GEMM rate of this CPU, and the call's own time on a fixed observation: of the
    traced form inference runs (``call_s``) and of the network module itself (``module_call_s``)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from hmrta.core import MissionState
    from hmrta.generators import ScenarioGenerator
    from hmrta.rl.features import batch_observations

    inst = ScenarioGenerator("MA-AT", 150, 10, 500, 5).instance(1, 0)
    obs, _ = batch_observations([MissionState(inst, seed=0, rules=pol.rules)], **pol.model.cfg.view())
    with torch.inference_mode():
        counter = FlopCounterMode(display=False)
        with counter:
            pol.net(**obs)
        flops = counter.get_total_flops()

        def per_call(f) -> float:
            for _ in range(20):
                f(**obs)
            calls, t0 = 300, time.thread_time()
            for _ in range(calls):
                f(**obs)
            return (time.thread_time() - t0) / calls

        call, module_call = per_call(pol.model), per_call(pol.net)
        a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
        for _ in range(3):
            a @ b
        reps, t0 = 20, time.thread_time()
        for _ in range(reps):
            a @ b
        rate = 2 * 1024 ** 3 * reps / (time.thread_time() - t0)
    shape = f"{obs['tasks'].shape[1]} task rows x {obs['agents'].shape[1]} agent rows"
    return {"flops": flops, "gemm_flops_per_s": rate, "floor_s": flops / rate, "call_s": call,
            "module_call_s": module_call, "window": shape}


def by_round(a: dict, b: dict) -> list[float]:
    """Round by round, ``b``'s ms per decision over ``a``'s (two rows of :func:`summarise` whose
    rounds ran minutes apart: each pair saw the same machine)."""
    return [y / x for x, y in zip(a["ms_per_decision_by_round"], b["ms_per_decision_by_round"])]


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of log y against log x (nan with fewer than two points)."""
    pts = [(math.log(x), math.log(y)) for x, y in zip(xs, ys) if x > 0 and y > 0]
    if len(pts) < 2:
        return math.nan
    return float(np.polyfit([p[0] for p in pts], [p[1] for p in pts], 1)[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, help="robots,species,tasks (MA-AT, 5 skills)")
    ap.add_argument("--count", nargs="+", type=int, default=None,
                    help="missions per size (one value, or one per size; default 10 2 1 1 1)")
    ap.add_argument("--methods", nargs="+", default=["greedy", "rl"], choices=["greedy", "rl"])
    ap.add_argument("--repeat", type=int, default=3, help="greedy: timed repeats per mission, best kept")
    ap.add_argument("--rounds", type=int, default=1,
                    help="run every size this many times, one round after the other (figures over all "
                         "rounds, and each round's ratio of 600/2000 to 25/50: on a machine whose speed "
                         "drifts, sizes measured in the same round are compared on the same footing)")
    ap.add_argument("--seed", type=int, default=1, help="instance set seed (the missions' own seed is 0)")
    ap.add_argument("--checkpoint", nargs="+", default=None,
                    help="policy checkpoint (default: the shipped one); several: each runs as rl@NAME, "
                         "alternating on every size, and each is compared with the first")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args()
    sizes = [tuple(int(x) for x in s.split(",")) for s in args.sizes]
    counts = args.count or (DEFAULT_COUNTS if len(sizes) == len(DEFAULT_COUNTS) else [1])
    if len(counts) == 1:
        counts = counts * len(sizes)
    if len(counts) != len(sizes) or min(counts) < 1 or args.repeat < 1 or args.rounds < 1:
        ap.error("--count: one positive value or one per size; --repeat, --rounds: at least 1")

    import torch

    from hmrta.bench import code_version, cpu_model
    from hmrta.cli import set_torch_threads
    from hmrta.generators import ScenarioGenerator

    set_torch_threads(torch, 1)
    load0 = [round(x, 2) for x in os.getloadavg()]
    print(f"# offline scale: MA-AT, 5 skills, one process, torch {torch.__version__} on "
          f"{torch.get_num_threads()} thread; {cpu_model()} x{os.cpu_count()}; python "
          f"{platform.python_version()}, numpy {np.__version__}; code {code_version()}")
    print(f"# load average at start {load0}\n")
    pols: dict[str, object] = {}  # rl method name -> loaded policy
    if "rl" in args.methods:
        from hmrta.rl.inference import load_policy

        cks = args.checkpoint or [None]
        for ck in cks:
            pols["rl" if len(cks) == 1 else f"rl@{ck}"] = load_policy(ck)
    methods = [x for m in args.methods for x in (list(pols) if m == "rl" else [m])]
    results: dict[str, list[dict]] = {m: [] for m in methods}
    growth: dict[str, dict[str, float]] = {}
    missions = {size: ScenarioGenerator("MA-AT", *size, 5).generate(n, args.seed) for size, n in zip(sizes, counts)}
    pooled: dict[tuple, list[dict]] = {}  # (method, size) -> the runs of every round
    per_round: dict[tuple, list[float]] = {}  # (method, size) -> ms/decision of each round
    warm: set[str] = set()
    for rnd in range(args.rounds):
        if args.rounds > 1:
            print(f"# round {rnd + 1} of {args.rounds}")
        for (A, S, M), n in zip(sizes, counts):
            for method in methods:
                runs = []
                for inst in missions[(A, S, M)]:
                    if method == "greedy":
                        tries = [run_greedy(inst, 0) for _ in range(args.repeat + 1)][1:]  # first: warm-up
                        runs.append(min(tries, key=lambda r: r["total"]))
                    else:
                        if method not in warm:  # first mission of this policy: warm its network up once
                            run_rl(ScenarioGenerator("MA-AT", 25, 5, 50, 5).instance(args.seed, 99), 0, pols[method])
                            warm.add(method)
                        runs.append(run_rl(inst, 0, pols[method]))
                row = summarise(runs, A, S, M, n)
                pooled.setdefault((method, (A, S, M)), []).extend(runs)
                per_round.setdefault((method, (A, S, M)), []).append(row["ms_per_decision"])
                parts = ", ".join(f"{k} {v:.3f}" for k, v in row["parts_ms_per_decision"].items())
                print(f"  {method} {A}/{M}: {row['ms_per_decision']:.3f} ms/decision ({parts}; wall "
                      f"{row['wall_ms_per_decision']:.3f}), {row['seconds_per_mission']:.2f} s/mission, "
                      f"{row['decisions']} decisions, load {os.getloadavg()[0]:.2f}", flush=True)
    for method in methods:
        for (A, S, M), n in zip(sizes, counts):
            row = summarise(pooled[(method, (A, S, M))], A, S, M, n * args.rounds)
            row["missions"], row["rounds"] = n, args.rounds
            row["ms_per_decision_by_round"] = per_round[(method, (A, S, M))]
            results[method].append(row)
    print()
    for method, rows in results.items():
        part_names = list(rows[0]["parts_ms_per_decision"])
        print(f"## {method}\n")
        print("| robots / tasks | missions | decisions/mission | success | ms/decision | "
              + " | ".join(f"{p} ms" for p in part_names) + " | s/mission | wall ms/decision | wall s/mission |")
        print("|---|---:|---:|---:|---:|" + "---:|" * len(part_names) + "---:|---:|---:|")
        for r in rows:
            runs = r["missions"] * r["rounds"]
            print(f"| {r['robots']} / {r['tasks']} | {r['missions']} | {r['decisions'] / runs:.0f} | "
                  f"{r['success']}/{runs} | {r['ms_per_decision']:.3f} | "
                  + " | ".join(f"{r['parts_ms_per_decision'][p]:.3f}" for p in part_names)
                  + f" | {r['seconds_per_mission']:.2f} | {r['wall_ms_per_decision']:.3f} | "
                  f"{r['wall_seconds_per_mission']:.2f} |")
        xs = [r["tasks"] for r in rows]
        fits = {"ms/decision": slope(xs, [r["ms_per_decision"] for r in rows])}
        fits.update({f"{p} ms": slope(xs, [r["parts_ms_per_decision"][p] for r in rows]) for p in part_names})
        fits["s/mission"] = slope(xs, [r["seconds_per_mission"] for r in rows])
        print("\ngrowth (log-log slope against tasks): " + ", ".join(f"{k} {v:.2f}" for k, v in fits.items()))
        first = {r["tasks"]: r for r in rows}
        if 50 in first and 2000 in first:
            ratio = first[2000]["ms_per_decision"] / first[50]["ms_per_decision"]
            line = f"ms/decision at 600/2000 over 25/50: {ratio:.2f}x"
            if args.rounds > 1:  # each round's sizes ran minutes apart: the pairs see the same machine
                each = by_round(first[50], first[2000])
                line += (f" over all rounds; round by round {', '.join(f'{x:.2f}' for x in each)} "
                         f"(median {statistics.median(each):.2f}x)")
            print(line)
        print()
        growth[method] = fits
    rl = list(pols)
    if len(rl) > 1:  # each checkpoint against the first, on the same missions, round by round
        print(f"## against {rl[0]} (ms/decision; round by round, then the median)\n")
        for method in rl[1:]:
            for ra, rb in zip(results[rl[0]], results[method]):
                each = by_round(ra, rb)
                print(f"  {method} {rb['robots']}/{rb['tasks']}: {', '.join(f'{x:.3f}' for x in each)} "
                      f"(median {statistics.median(each):.3f}); s/mission {rb['seconds_per_mission']:.2f} "
                      f"against {ra['seconds_per_mission']:.2f}")
        print()
    floors = {}
    for method, pol in pols.items():
        floor = floors[method] = network_floor(pol)
        print(f"network call{'' if method == 'rl' else ' of ' + method} ({floor['window']}): "
              f"{floor['flops'] / 1e6:.1f} MFLOP per decision; "
              f"{floor['call_s'] * 1e3:.3f} ms per call against a floor of {floor['floor_s'] * 1e3:.3f} ms "
              f"at {floor['gemm_flops_per_s'] / 1e9:.1f} GFLOP/s (1024^3 matrix product, one thread): "
              f"{floor['call_s'] / floor['floor_s']:.1f}x the floor (the network module itself: "
              f"{floor['module_call_s'] * 1e3:.3f} ms, {floor['module_call_s'] / floor['floor_s']:.1f}x)")
    load1 = [round(x, 2) for x in os.getloadavg()]
    print(f"# load average at end {load1}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"code": code_version(), "cpu": cpu_model(), "cores": os.cpu_count(), "load_start": load0,
                       "load_end": load1, "results": results, "growth": growth,
                       "network": floors[rl[0]] if rl else None, "networks": floors}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
