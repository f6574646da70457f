"""Scale benchmark of the ROS 2 mission: 150 robots / 500 tasks (paper row MA-AT 150-10-500-5),
all agents hosted in one process (lean nodes, one executor, one copy of the policy).

Measures the agent process's memory (peak RSS), the decision latency (board publishes a decision
-> board receives the choice, and the agent's own compute), the mission wall time against the
offline rollout of the same policy, and checks that the routes and makespan equal it. The offline
rollout runs before and after the live mission, and the ratio is taken against their mean: on a
shared machine whose speed drifts, one rollout before would bias it.

    .venv/bin/python benchmarks/ros_scale.py [--agents 150 --species 10 --tasks 500 --seed 1]

DDS discovery stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless set) on a
random ROS domain; every process started is stopped at the end.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path


def rss_mb(pid: int) -> tuple[float, float]:
    """(current, peak) resident memory of a process in MB."""
    cur = peak = float("nan")
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                cur = int(line.split()[1]) / 1024
            elif line.startswith("VmHWM:"):
                peak = int(line.split()[1]) / 1024
    except OSError:
        pass
    return cur, peak


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far."""
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=150, help="robots of the MA-AT mission (default 150)")
    p.add_argument("--species", type=int, default=10, help="species (default 10)")
    p.add_argument("--tasks", type=int, default=500, help="tasks (default 500)")
    p.add_argument("--skills", type=int, default=5, help="skills K (default 5)")
    p.add_argument("--seed", type=int, default=1, help="mission seed (default 1)")
    p.add_argument("--policy", default="greedy", choices=("greedy", "rl"), help="the agents' method (default greedy)")
    p.add_argument("--checkpoint", default="", help="rl: policy checkpoint (default: the shipped one)")
    p.add_argument("--out", default=None, help="also write the figures as JSON here")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds before the mission is stopped (default 900)")
    p.add_argument("--keep-logs", action="store_true",
                   help="keep the mission's folder (instance, result, process logs) after a completed run; "
                        "a run that fails always keeps it")
    args = p.parse_args(argv)

    from hmrta.generators import ScenarioGenerator
    from hmrta.methods import solve
    from hmrta_coordinator.mission import MissionProcesses, log_tail
    from hmrta_msgs_py.runtime import local_env

    inst = ScenarioGenerator("MA-AT", args.agents, args.species, args.tasks, args.skills).instance(args.seed, 0)
    opts = {"checkpoint": args.checkpoint} if args.checkpoint else {}
    ref = solve(inst, args.policy, args.seed, **opts)
    work = Path(tempfile.mkdtemp(prefix="hmrta_ros_scale_"))
    path = work / "instance.yaml"
    inst.save(path)
    robots = [f"robot_{a}" for a in range(inst.n_agents)]
    env = local_env()
    env["ROS_LOG_DIR"] = str(work / "ros_logs")
    procs = MissionProcesses(path, robots, work / "result.json", work / "logs", env, seed=args.seed,
                             method=args.policy, method_options=opts, agents_per_process=inst.n_agents,
                             board_params={"progress_period": 10.0, "startup_timeout": 300.0})
    print(f"{inst.name}: {inst.n_agents} robots, {inst.n_tasks} tasks, policy {args.policy}, seed {args.seed}; "
          f"ROS domain {env['ROS_DOMAIN_ID']}; logs in {work}", flush=True)
    t0 = time.monotonic()
    procs.start()
    agent = procs.agents[0]
    peak = {"agents": 0.0, "board": 0.0, "sim": 0.0}
    cpu = {"agents": 0.0, "board": 0.0, "sim": 0.0}
    try:
        while time.monotonic() - t0 < args.timeout and procs.board.proc.poll() is None:
            for k, c in (("agents", agent), ("board", procs.board), ("sim", procs.sim)):
                if c.proc.poll() is None:
                    peak[k] = max(peak[k], rss_mb(c.proc.pid)[1])
                    cpu[k] = max(cpu[k], cpu_s(c.proc.pid))
            time.sleep(0.2)
    finally:
        procs.stop()
    total = time.monotonic() - t0
    if procs.board.proc.returncode != 0 or not (work / "result.json").exists():
        print(f"the mission did not complete; board log:\n{log_tail(procs.board.log, 30)}", file=sys.stderr)
        return 1
    res = json.loads((work / "result.json").read_text())
    after = solve(inst, args.policy, args.seed, **opts)  # the offline rollout again, right after the mission
    offline = (ref.compute_seconds + after.compute_seconds) / 2
    same = res["routes"] == ref.routes and res["makespan"] == ref.makespan
    lat, comp = res["decision_latency_ms"], res["agent_compute_ms"]
    figures = {
        "instance": inst.name, "robots": inst.n_agents, "tasks": inst.n_tasks, "policy": args.policy,
        "success": res["success"], "same_as_offline": same, "makespan": res["makespan"],
        "decisions": lat["n"],
        "decision_latency_ms_median": lat["median"], "decision_latency_ms_p99": lat["p99"],
        "agent_compute_ms_median": comp["median"], "agent_compute_ms_p99": comp["p99"],
        "mission_wall_s": res["mission_wall_seconds"], "offline_rollout_s": round(ref.compute_seconds, 3),
        "offline_rollout_after_s": round(after.compute_seconds, 3),
        "live_over_offline": round(res["mission_wall_seconds"] / offline, 3),
        "total_wall_s_with_startup": round(total, 1),
        "agent_process_peak_rss_mb": round(peak["agents"], 1), "board_peak_rss_mb": round(peak["board"], 1),
        "sim_peak_rss_mb": round(peak["sim"], 1),
        "cpu_s_agents_board_sim": [round(cpu[k], 1) for k in ("agents", "board", "sim")],
    }
    w = max(map(len, figures))
    for k, v in figures.items():
        print(f"{k:>{w}}: {v}")
    ok = res["success"] and same
    if ok and not args.keep_logs:
        shutil.rmtree(work, ignore_errors=True)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(figures, indent=1) + "\n")
    return 0 if ok else 3


if __name__ == "__main__":
    sys.exit(main())
