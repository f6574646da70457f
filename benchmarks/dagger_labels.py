"""How good are the DAgger teachers on the states a policy reaches? (prints figures; not a test)

For each dev mission (the families at seed 2000 and the paper rows at seed 4242, never a test
seed), the checkpoint drives the mission (greedy decoding, its own rules) to a decision drawn
uniformly over its decisions; from that state three continuations finish the mission:

* the policy itself (what it would do),
* greedy-coalition (the DAgger teacher ``pretrain.dagger_teacher: teacher``),
* the plan from the state (``pretrain.dagger_teacher: solver``: hmrta.solvers.fromstate,
  ``--evals`` annealing decodes), followed by its routes.

Prints, per row, the mean makespan ratio of the policy's and the plan's continuation to
greedy-coalition's, and the plan's seconds per state. A teacher whose continuation is shorter
labels the policy's states with better choices.

usage: python benchmarks/dagger_labels.py [--checkpoint P] [--count N] [--evals E] [--max-tasks M]
"""
from __future__ import annotations

import argparse
import random
import statistics
import time

import torch

from hmrta.bench import paper_suite
from hmrta.core import MissionState
from hmrta.families import family_suite
from hmrta.rl.inference import load_policy, rl_decider
from hmrta.rl.schedules import RouteTeacher
from hmrta.baselines import CoalitionGreedy
from hmrta.solvers.fromstate import plan_from_state


def finish(st: MissionState, decide) -> float:
    c = st.clone()
    while not c.done:
        c.step(decide(c))
    return c.makespan if c.success else float("nan")


def row_figures(insts, checkpoint: str, evals: int, seed: int) -> dict:
    pol = load_policy(checkpoint)
    policy, plan, secs, improved = [], [], [], 0
    for k, inst in enumerate(insts):
        full = MissionState(inst, seed=k, rules=pol.rules)
        decide = rl_decider(k, checkpoint)
        while not full.done:
            full.step(decide(full))
        cut = random.Random(seed * 7919 + k).randrange(max(1, full.decisions))
        st = MissionState(inst, seed=k, rules=pol.rules)
        for _ in range(cut):
            st.step(decide(st))
        if st.done:
            continue
        t0 = time.perf_counter()
        p = plan_from_state(st, evals, seed=k)
        secs.append(time.perf_counter() - t0)
        followed = p.makespan if p.routes is None else finish(st, RouteTeacher(p.routes, CoalitionGreedy()))
        improved += p.routes is not None
        policy.append(finish(st, decide) / p.greedy_coalition)
        plan.append(followed / p.greedy_coalition)
    return {"states": len(plan), "policy": statistics.mean(policy), "plan": statistics.mean(plan),
            "improved": improved, "seconds": statistics.mean(secs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default="policy/hmrta/checkpoints/broad.pt", help="the policy that drives")
    ap.add_argument("--count", type=int, default=10, help="missions per row (default 10)")
    ap.add_argument("--evals", type=int, default=2000, help="annealing decodes per plan (default 2000)")
    ap.add_argument("--max-tasks", type=int, default=50, help="rows up to this many tasks (default 50)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    print(f"checkpoint {a.checkpoint}, {a.count} missions per row, plans of {a.evals} decodes")
    print("| row | states | policy / gc | plan / gc | plans better than gc | plan s |")
    print("|---|---|---|---|---|---|")
    rows = [(r.key, r.generator().generate(a.count, 2000)) for r in family_suite(max_tasks=a.max_tasks)]
    rows += [(f"{r.table} {r.agents},{r.species},{r.tasks},{r.skills}", r.generator().generate(a.count, 4242))
             for r in paper_suite() if r.tasks <= a.max_tasks]
    allp, allq = [], []
    for name, insts in rows:
        f = row_figures(insts, a.checkpoint, a.evals, 1)
        allp.append(f["policy"])
        allq.append(f["plan"])
        print(f"| {name} | {f['states']} | {f['policy']:.3f} | {f['plan']:.3f} | {f['improved']} | {f['seconds']:.2f} |",
              flush=True)
    print(f"| mean of rows | | {statistics.mean(allp):.3f} | {statistics.mean(allq):.3f} | | |")


if __name__ == "__main__":
    main()
