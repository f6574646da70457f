"""Cost of copying a running mission state (``MissionState.clone``: lookahead branches, the
RL-lookahead method, lookahead distillation) against a generic deep copy, mid-mission, at the
paper's 20-task rows and at the live-scale sizes.

    .venv/bin/python benchmarks/clone.py [--repeat 50]
"""
from __future__ import annotations

import argparse
import copy
import json
import time

from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.core import MissionState
from hmrta.generators import ScenarioGenerator


def mid_mission(robots: int, species: int, tasks: int) -> MissionState:
    inst = ScenarioGenerator("MA-AT", robots, species, tasks, 5).instance(1, 0)
    st, pol = MissionState(inst, seed=1, rules=GREEDY_RULES), Greedy()
    while st.n_done < tasks // 2 and not st.done:
        st.step(pol(st))
    return st


def per_call_ms(f, repeat: int) -> float:
    t0 = time.perf_counter()
    for _ in range(repeat):
        f()
    return (time.perf_counter() - t0) / repeat * 1e3


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=50, help="copies timed per size")
    args = p.parse_args(argv)
    rows = []
    for robots, species, tasks in ((9, 3, 20), (25, 5, 50), (150, 10, 500), (600, 10, 2000)):
        st = mid_mission(robots, species, tasks)
        memo = {id(st.inst): st.inst, id(st.rules): st.rules}
        clone = per_call_ms(st.clone, args.repeat)
        deep = per_call_ms(lambda: copy.deepcopy(st, dict(memo)), max(1, args.repeat // 5))
        rows.append({"robots": robots, "tasks": tasks, "clone_ms": round(clone, 4), "deepcopy_ms": round(deep, 4),
                     "speedup": round(deep / clone, 1)})
        print(json.dumps(rows[-1]), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
