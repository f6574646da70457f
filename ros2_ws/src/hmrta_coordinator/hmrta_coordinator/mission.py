"""mission: run a whole decentralised mission over ROS 2 and write its result.

Starts the task board, the simulated robots and one agent node per robot (one process each by
default; ``--agents-per-process N`` hosts N robots per process), follows the board with a
progress bar, and when the mission ends writes the ``hmrta-solution/1`` JSON (plus a routes and
Gantt picture), prints the metrics and stops every process it started.

DDS discovery stays on this machine unless ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is already set
(e.g. SUBNET for a real multi-machine fleet); without ``ROS_DOMAIN_ID`` a random domain in
100..199 is used so that missions never meet by accident.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from hmrta_msgs_py.runtime import local_env



def default_instance() -> Path:
    import hmrta

    return Path(hmrta.__file__).resolve().parent / "data" / "example.yaml"


def _die_with_parent() -> None:
    """In the child: get SIGTERM when the launcher dies, however it dies (Linux)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def ros_params(params: dict[str, Any]) -> list[str]:
    """{'seed': 1, 'instance': 'a b.yaml'} -> ['-p', 'seed:=1', '-p', 'instance:="a b.yaml"'] (YAML values)."""
    out: list[str] = []
    for k, v in params.items():
        out += ["-p", f"{k}:={json.dumps(v)}"]
    return out


@dataclass
class Child:
    name: str
    cmd: list[str]
    proc: subprocess.Popen
    log: Path
    _fh: IO | None = None


@dataclass
class MissionProcesses:
    """The processes of one mission (board, simulated robots, agent hosts). Usable as a library
    (tests, benchmarks): ``start()``, then ``board``/``agents`` give the Popen handles, ``stop()``
    ends everything still running (SIGINT, then SIGTERM, then SIGKILL)."""

    instance: Path
    robots: list[str]
    out: Path | None
    log_dir: Path
    env: dict[str, str]
    seed: int = 0
    policy: str = "greedy"
    decoding: str = "greedy"
    checkpoint: str = ""
    agents_per_process: int = 1
    time_scale: float = 0.0
    board_params: dict[str, Any] = field(default_factory=dict)
    board_ros_args: list[str] = field(default_factory=list)  # e.g. remaps
    sim_params: dict[str, Any] = field(default_factory=dict)
    sim_ros_args: list[str] = field(default_factory=list)
    external: list[str] = field(default_factory=list)  # robots driven outside (not simulated)
    no_agent: list[str] = field(default_factory=list)  # robots whose agent runs elsewhere
    agent_ros_args: dict[str, list[str]] = field(default_factory=dict)  # robot -> its own process with these
    board: Child | None = None
    sim: Child | None = None
    agents: list[Child] = field(default_factory=list)

    def _spawn(self, name: str, module: str, args: list[str]) -> Child:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log = self.log_dir / f"{name}.log"
        fh = open(log, "w")
        cmd = [sys.executable, "-u", "-m", module, *args]
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=self.env,
                                start_new_session=True, preexec_fn=_die_with_parent if sys.platform == "linux" else None)
        return Child(name, cmd, proc, log, fh)

    def agent_groups(self) -> list[tuple[list[str], list[str]]]:
        """[(robots, extra ros args)] for the agent processes."""
        own = [r for r in self.robots if r in self.agent_ros_args]
        rest = [r for r in self.robots if r not in self.agent_ros_args and r not in self.no_agent]
        n = max(1, self.agents_per_process)
        groups = [(rest[i:i + n], []) for i in range(0, len(rest), n)]
        return groups + [([r], self.agent_ros_args[r]) for r in own]

    def start(self) -> None:
        common = {"seed": self.seed, "policy": self.policy, "decoding": self.decoding, "checkpoint": self.checkpoint}
        bp = {"instance": str(self.instance), "robot_names": self.robots, **common, **self.board_params}
        if self.out is not None:
            bp["output"] = str(self.out)
        self.board = self._spawn("task_board", "hmrta_coordinator.task_board",
                                 ["--ros-args", *ros_params(bp), *self.board_ros_args])
        sp = {"time_scale": self.time_scale, **self.sim_params}
        if self.external:
            sp["external"] = self.external
        self.sim = self._spawn("sim_robot", "hmrta_coordinator.sim_robot", ["--ros-args", *ros_params(sp), *self.sim_ros_args])
        for i, (robots, extra) in enumerate(self.agent_groups()):
            name = f"agents_{robots[0]}" if len(robots) == 1 else f"agents_{i:03d}"
            self.agents.append(self._spawn(name, "hmrta_agent.agent_node",
                                           ["--robots", ",".join(robots), "--ros-args", *ros_params(common), *extra]))

    def children(self) -> list[Child]:
        return [c for c in (self.board, self.sim, *self.agents) if c is not None]

    def agent_of(self, robot: str) -> Child:
        for robots, c in zip((g[0] for g in self.agent_groups()), self.agents):
            if robot in robots:
                return c
        raise KeyError(robot)

    def stop(self, grace: float = 5.0) -> None:
        """Wait up to ``grace`` s for the children to exit, then SIGINT, SIGTERM, SIGKILL."""
        live = [c for c in self.children() if c.proc.poll() is None]
        deadline = time.monotonic() + grace
        for sig in (None, signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if sig is not None:
                for c in live:
                    if c.proc.poll() is None:
                        try:
                            c.proc.send_signal(sig)
                        except ProcessLookupError:
                            pass
                deadline = time.monotonic() + (3.0 if sig != signal.SIGKILL else 10.0)
            while time.monotonic() < deadline and any(c.proc.poll() is None for c in live):
                time.sleep(0.05)
            live = [c for c in live if c.proc.poll() is None]
            if not live:
                break
        for c in self.children():
            if c._fh is not None:
                c._fh.close()
                c._fh = None


def log_tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


# ---------------------------------------------------------------------------------------------
def run_monitor(procs: MissionProcesses, n_tasks: int, timeout: float, quiet: bool) -> str:
    """Follow the board with a progress bar until the board process exits; returns "ok" if it
    exited cleanly within ``timeout``, else what went wrong."""
    import rclpy
    from std_msgs.msg import String
    from tqdm import tqdm

    from hmrta_msgs_py import topics
    from hmrta_msgs_py.codec import DecodeError, board_from_msg
    from hmrta_msgs_py.runtime import LEAN_NODE

    rclpy.init(args=[])
    node = rclpy.create_node("mission_monitor", **LEAN_NODE)
    tty = sys.stderr.isatty()
    bar = tqdm(total=n_tasks, desc="mission", unit="task", disable=quiet or not tty, file=sys.stderr,
               bar_format="{desc}: {n_fmt}/{total_fmt} tasks |{bar}| {elapsed} {postfix}")
    told = [-1]  # without a terminal: one line per quarter of the tasks

    def on_board(msg: String) -> None:
        try:
            b = board_from_msg(msg, legs=False, state=False)
        except DecodeError:
            return
        n = b.n_done + b.n_cancelled
        info = f"t={b.clock:.1f} {b.phase}" + (f" lost={len(b.lost)}" if b.lost else "")
        bar.n = n
        bar.set_postfix_str(info, refresh=False)
        bar.refresh()
        if not tty and not quiet and 4 * n // max(n_tasks, 1) > told[0]:
            told[0] = 4 * n // max(n_tasks, 1)
            print(f"mission: {n}/{n_tasks} tasks, {info}", file=sys.stderr, flush=True)

    node.create_subscription(String, topics.BOARD, on_board, topics.BOARD_QOS)
    deadline = time.monotonic() + timeout
    status = "timed out"
    try:
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
            if procs.board.proc.poll() is not None:
                rc = procs.board.proc.returncode
                status = "ok" if rc == 0 else f"the task board exited with {rc}"
                break
            if procs.sim.proc.poll() not in (None, 0):
                status = f"sim_robot exited with {procs.sim.proc.returncode}"
                break
    finally:
        bar.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return status


def print_metrics(sol, extra: dict[str, Any], inst) -> None:
    print(sol.summary())
    print(f"  robots {inst.n_agents}, tasks {inst.n_tasks}: {inst.n_tasks - len(extra.get('undone_tasks', []))} done"
          + (f", undone {extra['undone_tasks']}" if extra.get("undone_tasks") else ""))
    if extra.get("lost_robots"):
        for r in extra["lost_robots"]:
            print(f"  lost robot {r}: {extra.get('lost_reasons', {}).get(r, '')}")
        if "home_time" in extra:
            print(f"  surviving robots home at t={extra['home_time']:.3f}")
    lat = extra.get("decision_latency_ms", {})
    comp = extra.get("agent_compute_ms", {})
    if lat.get("n"):
        print(f"  decisions {lat['n']}: latency (board update -> choice received) median {lat['median']:.2f} ms, "
              f"p99 {lat['p99']:.2f} ms; agent compute median {comp.get('median', float('nan')):.2f} ms")
    print(f"  mission wall time {extra.get('mission_wall_seconds', float('nan')):.2f} s")
    if extra.get("rejected_messages"):
        print(f"  rejected messages: {extra['rejected_messages']}")


def main(argv: list[str] | None = None) -> int:
    from rclpy.executors import ExternalShutdownException
    from rclpy.utilities import remove_ros_args

    argv = list(sys.argv if argv is None else argv)
    p = argparse.ArgumentParser(prog="hmrta-mission", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("instance", nargs="?", default=None,
                   help="instance YAML (or CTAS-D config.json); default: the built-in example mission")
    p.add_argument("--seed", type=int, default=0, help="episode seed (decision order, sampling)")
    p.add_argument("--out", default="out/mission.json", help="solution JSON to write")
    p.add_argument("--policy", default="greedy", choices=("greedy", "greedy-coalition", "rl", "rl-sample", "rl-lookahead"),
                   help="decision policy every agent runs (greedy-coalition: the task whose coalition can start "
                        "first; rl: learned policy, greedy decoding; rl-lookahead: one-step lookahead over it, "
                        "slower per decision)")
    p.add_argument("--checkpoint", default="", help="policy checkpoint for rl (default: the shipped one)")
    p.add_argument("--agents-per-process", type=int, default=1, metavar="N",
                   help="robots hosted per agent process (lean nodes on one executor)")
    p.add_argument("--time-scale", type=float, default=0.0,
                   help="sim seconds per wall second (0: as fast as possible)")
    p.add_argument("--heartbeat-timeout", type=float, default=5.0, help="wall seconds before a silent robot is lost")
    p.add_argument("--domain-id", type=int, default=None, help="ROS domain (default: $ROS_DOMAIN_ID or random 100-199)")
    p.add_argument("--plot", default=None, help="routes + Gantt picture (default: next to --out, .png)")
    p.add_argument("--no-plot", action="store_true", help="do not draw the picture")
    p.add_argument("--check-offline", action="store_true",
                   help="also run the offline rollout (hmrta solve) and compare routes and makespan")
    p.add_argument("--timeout", type=float, default=600.0, help="give up after this many wall seconds")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(remove_ros_args(argv)[1:])

    from hmrta.instance import InstanceError, load_instance
    from hmrta.solution import Solution

    path = Path(args.instance) if args.instance else default_instance()
    try:
        inst = load_instance(path)
    except InstanceError as e:
        print(f"hmrta-mission: {e}", file=sys.stderr)
        return 2
    if args.agents_per_process < 1:
        print("hmrta-mission: --agents-per-process must be >= 1", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():
        out.unlink()  # never report a previous run's result
    log_dir = out.with_name(out.stem + "_logs")
    env = local_env(domain_id=args.domain_id)
    env.setdefault("ROS_LOG_DIR", str(log_dir / "ros"))
    env.setdefault("PYTHONUNBUFFERED", "1")
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_LOG_DIR")})
    robots = [f"robot_{a}" for a in range(inst.n_agents)]
    decoding = "sample" if args.policy == "rl-sample" else "greedy"
    policy = "rl" if args.policy in ("rl", "rl-sample") else args.policy
    procs = MissionProcesses(path, robots, out, log_dir, env, seed=args.seed, policy=policy, decoding=decoding,
                             checkpoint=args.checkpoint, agents_per_process=args.agents_per_process,
                             time_scale=args.time_scale,
                             board_params={"heartbeat_timeout": args.heartbeat_timeout, "progress_period": 0.0})
    n_proc = 2 + len(procs.agent_groups())
    print(f"mission {inst.name}: {inst.n_agents} robots, {inst.n_tasks} tasks, policy {args.policy}, seed {args.seed}; "
          f"{n_proc} processes on ROS domain {env['ROS_DOMAIN_ID']} "
          f"(discovery {env['ROS_AUTOMATIC_DISCOVERY_RANGE']}); logs in {log_dir}", flush=True)
    t0 = time.monotonic()
    procs.start()
    try:
        status = run_monitor(procs, inst.n_tasks, args.timeout, args.quiet)
    except (KeyboardInterrupt, ExternalShutdownException):
        print("interrupted: stopping the mission", file=sys.stderr)
        procs.stop(grace=0.0)
        return 130
    finally:
        procs.stop()
    wall = time.monotonic() - t0
    if status != "ok" or not out.exists():
        print(f"hmrta-mission: the mission did not complete ({status}); board log tail:\n"
              f"{log_tail(procs.board.log)}", file=sys.stderr)
        return 1
    sol = Solution.from_dict(json.loads(out.read_text()))
    print_metrics(sol, sol.extra, inst)
    print(f"  total wall time {wall:.2f} s (including start-up of {n_proc} processes)")
    print(f"wrote {out}")
    if args.check_offline:
        from hmrta.methods import solve

        ref = solve(inst, args.policy, seed=args.seed, **({"checkpoint": args.checkpoint} if args.checkpoint else {}))
        same = ref.routes == sol.routes and ref.makespan == sol.makespan
        print(f"offline rollout ({args.policy}): makespan {ref.makespan:.3f}; same routes and makespan: "
              f"{'yes' if same else 'NO'}")
    if not args.no_plot:
        plot = Path(args.plot) if args.plot else out.with_suffix(".png")
        try:
            from hmrta.render import render
        except ImportError:
            print("(no picture: hmrta.render is not available)")
        else:
            render(inst, sol, plot)
            print(f"wrote {plot}")
    return 0 if sol.success else 3


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
