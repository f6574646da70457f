"""Flood benchmark of the ROS 2 mission: junk on the choice and heartbeat topics during a mission.

Runs one authenticated sim-time mission (greedy, every robot signing with its key from a fresh
keystore) quietly, then the same mission while a separate process publishes junk on
``/hmrta/choice`` and ``/hmrta/agent_status`` at a target rate (default 5,000 messages/s for
20 s): malformed text and JSON, foreign-session and stale choices, forged choices in the current
decider's name for the current board version (wrong key), unsigned and forged heartbeats. Prints
the achieved flood rate, the decision latency (median / p99, board publishes a decision -> board
receives the choice), the board's peak memory (VmHWM) and the mission wall time, quiet against
flooded, and whether the flooded mission equals the quiet one (routes, makespan) and the offline
rollout.

    .venv/bin/python benchmarks/flood.py [--instance FILE | --size 25,5,50,5] [--rate 5000 --seconds 20]

DDS discovery stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless set) on a
random ROS domain; every process started is stopped at the end.
"""
from __future__ import annotations

import argparse
import json
import os
import secrets
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def hwm_mb(pid: int) -> float:
    """Peak resident memory (VmHWM) of a running process in MB (nan once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


# ---------------------------------------------------------------------------------------------
# the flooding process
# ---------------------------------------------------------------------------------------------
def flood(rate: float, seconds: float, robots: list[str], report: Path) -> None:
    """Publish junk at ``rate`` messages/s for ``seconds`` (half choices, half heartbeats);
    write {"sent", "seconds", "rate"} to ``report``."""
    import rclpy
    from std_msgs.msg import String

    from hmrta.keys import Signer
    from hmrta_msgs_py import topics
    from hmrta_msgs_py.codec import Choice, Status, board_from_msg, choice_to_msg, mission_from_msg, status_to_msg
    from hmrta_msgs_py.runtime import LEAN_NODE

    rclpy.init(args=[])
    node = rclpy.create_node("flooder", **LEAN_NODE)
    pub_c = node.create_publisher(String, topics.CHOICE, topics.CHOICE_QOS)
    pub_s = node.create_publisher(String, topics.STATUS, topics.STATUS_QOS)
    seen = {"session": "", "version": 0, "decider": robots[0]}

    def on_mission(msg: String) -> None:
        seen["session"] = mission_from_msg(msg).session

    def on_board(msg: String) -> None:
        b = board_from_msg(msg, legs=False, state=False)
        seen["version"] = b.version
        if b.decider is not None:
            seen["decider"] = robots[b.decider]

    node.create_subscription(String, topics.MISSION, on_mission, topics.MISSION_QOS)
    node.create_subscription(String, topics.BOARD, on_board, topics.BOARD_QOS)
    thief = Signer({r: secrets.token_bytes(32) for r in robots})  # right names, wrong keys
    static = ["garbage", "", "{", '{"format": "hmrta-choice/1"}', "[1, 2, 3]", '{"format": "hmrta-choice/2"}',
              json.dumps({"format": "hmrta-choice/1", "robot": robots[0], "session": "x", "version": "1", "node": 1}),
              "\x00\xff" * 40, '{"format": "hmrta-status/1", "robots": "x"}']
    static_msgs = [String(data=t) for t in static]

    def junk(i: int) -> tuple:
        k = i % 8
        s, v, r = seen["session"], seen["version"], seen["decider"]
        if k == 0:
            return pub_c, static_msgs[(i // 8) % len(static_msgs)]
        if k == 1:
            return pub_c, choice_to_msg(Choice(r, "foreign-run", v, 1))
        if k == 2:
            return pub_c, choice_to_msg(Choice(r, s, max(0, v - 1), 1))  # stale
        if k == 3:
            return pub_c, choice_to_msg(Choice(r, s, v, 1 + i % 5), thief)  # forged: the decider's name, now
        if k == 4:
            return pub_c, choice_to_msg(Choice(r, s, v, 1))  # unsigned
        if k == 5:
            return pub_s, status_to_msg(Status(tuple(robots), s, i))  # unsigned heartbeat of everybody
        if k == 6:
            return pub_s, status_to_msg(Status((r,), s, i), thief)  # forged heartbeat
        return pub_s, static_msgs[(i // 8) % len(static_msgs)]

    deadline = time.monotonic() + 10.0
    while not seen["session"] and time.monotonic() < deadline:  # junk that needs the session waits for it
        rclpy.spin_once(node, timeout_sec=0.05)
    sent, t0 = 0, time.monotonic()
    batch = max(1, int(rate / 200))  # publish in slices of 5 ms
    while (now := time.monotonic()) - t0 < seconds:
        due = int((now - t0) * rate)
        n = min(batch, due - sent)
        for _ in range(n):
            pub, msg = junk(sent)
            pub.publish(msg)
            sent += 1
        rclpy.spin_once(node, timeout_sec=0.0)  # follow the board version and decider
        if sent >= due:
            time.sleep(0.002)
    elapsed = time.monotonic() - t0
    report.write_text(json.dumps({"sent": sent, "seconds": round(elapsed, 3), "rate": round(sent / elapsed, 1)}))
    node.destroy_node()
    rclpy.try_shutdown()


# ---------------------------------------------------------------------------------------------
# one mission
# ---------------------------------------------------------------------------------------------
def run_mission(inst_path: Path, robots: list[str], seed: int, keystore: Path, work: Path, env: dict[str, str],
                time_scale: float, per_process: int, flood_args: dict | None, timeout: float) -> dict:
    from hmrta_coordinator.mission import MissionProcesses

    work.mkdir(parents=True, exist_ok=True)
    out = work / "result.json"
    flooder = None
    report = work / "flood.json"
    if flood_args is not None:  # the flood starts first and runs through the mission
        with open(work / "flooder.log", "w") as log:
            flooder = subprocess.Popen([sys.executable, __file__, "--flooder", "--rate", str(flood_args["rate"]),
                                        "--seconds", str(flood_args["seconds"]), "--robots", ",".join(robots),
                                        "--report", str(report)], env=env, stdout=subprocess.DEVNULL, stderr=log,
                                       start_new_session=True)
        time.sleep(2.0)
    procs = MissionProcesses(inst_path, robots, out, work / "logs", env, seed=seed, keystore=keystore,
                             time_scale=time_scale, agents_per_process=per_process,
                             board_params={"progress_period": 0.0})
    t0 = time.monotonic()
    procs.start()
    peak = float("nan")
    try:
        pid = procs.board.proc.pid
        deadline = t0 + timeout
        while procs.board.proc.poll() is None and time.monotonic() < deadline:
            m = hwm_mb(pid)
            if m == m:
                peak = m  # VmHWM only grows; the last reading before exit is the peak
            time.sleep(0.2)
        rc = procs.board.proc.poll()
    finally:
        procs.stop(grace=3.0)
        if flooder is not None:
            try:
                flooder.wait(timeout=flood_args["seconds"] + 30)
            except subprocess.TimeoutExpired:
                flooder.kill()
                flooder.wait()
    wall = time.monotonic() - t0
    res = {"rc": rc, "board_peak_mb": peak, "wall_s": wall, "result": None, "flood": None}
    if out.exists():
        res["result"] = json.loads(out.read_text())
    if report.exists():
        res["flood"] = json.loads(report.read_text())
    if rc != 0 or res["result"] is None:
        tail = "\n".join((work / "logs" / "task_board.log").read_text(errors="replace").splitlines()[-15:])
        res["error"] = f"board exit {rc}; log tail:\n{tail}"
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--instance", default=None, help="instance YAML (default: the built-in example, 15 robots)")
    p.add_argument("--size", default=None, help="generate an MA-AT instance A,S,M,K instead (e.g. 25,5,50,5)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--rate", type=float, default=5000.0, help="junk messages per second (target)")
    p.add_argument("--seconds", type=float, default=20.0, help="flood duration")
    p.add_argument("--time-scale", type=float, default=3.0,
                   help="sim seconds per wall second (the mission should last a good part of the flood)")
    p.add_argument("--agents-per-process", type=int, default=0, help="default: every robot in one process")
    p.add_argument("--timeout", type=float, default=180.0)
    p.add_argument("--out", default=None, help="also write the figures as JSON here")
    # the flooding process (internal)
    p.add_argument("--flooder", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--robots", default="", help=argparse.SUPPRESS)
    p.add_argument("--report", default="", help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.flooder:
        flood(args.rate, args.seconds, args.robots.split(","), Path(args.report))
        return 0

    from hmrta.formats import load_instance
    from hmrta.generators import ScenarioGenerator
    from hmrta.keys import create_keystore
    from hmrta.methods import solve
    from hmrta_coordinator.mission import default_instance
    from hmrta_msgs_py.runtime import local_env

    work = Path(tempfile.mkdtemp(prefix="hmrta-flood-"))
    if args.size:
        A, S, M, K = (int(x) for x in args.size.split(","))
        inst = ScenarioGenerator("MA-AT", A, S, M, K).instance(args.seed, 0)
        inst_path = work / "instance.yaml"
        inst.save(inst_path)
    else:
        inst_path = Path(args.instance) if args.instance else default_instance()
        inst = load_instance(inst_path)
    robots = [f"robot_{a}" for a in range(inst.n_agents)]
    keystore = work / "keys"
    create_keystore(keystore, robots)
    env = local_env()
    env.setdefault("PYTHONUNBUFFERED", "1")
    env["ROS_LOG_DIR"] = str(work / "ros")
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID")})
    per = args.agents_per_process or len(robots)
    print(f"flood benchmark: {inst.name} ({inst.n_agents} robots, {inst.n_tasks} tasks), greedy, seed {args.seed}, "
          f"authenticated, time scale {args.time_scale:g}; ROS domain {env['ROS_DOMAIN_ID']}; work {work}", flush=True)
    runs = {}
    for name, fl in (("quiet", None), ("flooded", {"rate": args.rate, "seconds": args.seconds})):
        runs[name] = r = run_mission(inst_path, robots, args.seed, keystore, work / name, env, args.time_scale, per, fl,
                                     args.timeout)
        if r.get("error"):
            print(f"{name}: the mission did not complete: {r['error']}", flush=True)
    ref = solve(inst, "greedy", args.seed)
    rows = []
    for name, r in runs.items():
        x = (r["result"] or {}).get("extra", r["result"] or {})
        lat = x.get("decision_latency_ms", {}) if r["result"] else {}
        rows.append((name, lat.get("median"), lat.get("p99"), lat.get("n"), r["board_peak_mb"],
                     x.get("mission_wall_seconds"), sum((x.get("rejected_messages") or {}).values())))
    fl = runs["flooded"]["flood"] or {}
    print(f"flood: {fl.get('sent', 0)} junk messages in {fl.get('seconds', 0)} s = {fl.get('rate', 0):.0f}/s "
          f"(target {args.rate:g}/s)")
    print(f"{'run':8} {'latency median ms':>18} {'p99 ms':>8} {'decisions':>9} {'board peak MB':>13} "
          f"{'mission wall s':>14} {'rejected':>9}")
    for name, med, p99, n, mb, wall, rej in rows:
        f = lambda v, w, d=2: f"{v:>{w}.{d}f}" if isinstance(v, (int, float)) and v == v else f"{'-':>{w}}"
        print(f"{name:8} {f(med, 18)} {f(p99, 8)} {f(n, 9, 0)} {f(mb, 13, 1)} {f(wall, 14)} {f(rej, 9, 0)}")
    q, fr = runs["quiet"]["result"], runs["flooded"]["result"]
    same = bool(q and fr and q["routes"] == fr["routes"] and q["makespan"] == fr["makespan"])
    offline = bool(fr and fr["routes"] == json.loads(json.dumps(ref.to_dict()))["routes"]
                   and fr["makespan"] == ref.makespan)
    print(f"flooded mission complete: {'yes' if fr and fr.get('success') else 'NO'}; equals the quiet one (routes, "
          f"makespan): {'yes' if same else 'NO'}; equals the offline rollout: {'yes' if offline else 'NO'}")
    if fr:
        x = fr.get("extra", fr)
        print(f"flooded board rejections: {x.get('rejected_messages')}; ignored heartbeats: "
              f"{x.get('auth_rejections', {}).get('status')}")
    if args.out:
        Path(args.out).write_text(json.dumps({"runs": {k: {kk: vv for kk, vv in v.items() if kk != "result"}
                                                       for k, v in runs.items()}, "same": same,
                                              "offline": offline}, indent=1, default=str))
    return 0 if same and offline else 1


if __name__ == "__main__":
    sys.exit(main())
