"""mission: run a whole decentralised mission over ROS 2 and write its result.

Starts the task board, the simulated robots and one agent node per robot (one process each by
default; ``--agents-per-process N`` hosts N robots per process), follows the board with a
progress bar, and when the mission ends writes the ``hmrta-solution/1`` JSON (plus a routes and
Gantt picture), prints the metrics and stops every process it started.

Any process may die. A simulated-robot or agent process that dies (a crash, any signal) is
restarted, at most 3 times each, with the reason printed and kept in the result's ``incidents``;
the new process resynchronises from the latched mission and board and the mission goes on. The
board journals every version it publishes (``<out>_logs/journal.jsonl``; ``--no-journal``: off):
when it dies it is restarted on its journal (at most 3 times), replays it and goes on under the
same session, and agents and robots resynchronise from its latched board. Without a journal, or
once it has been restarted too often, a dying board (or a mission that times out, or is
interrupted) ends the mission: the launcher
stops the rest at once and writes a partial result (``success`` false, ``partial`` true, the
``failure`` reason, and the routes and completed tasks of the latest board it saw). Exit status:
0 mission completed, 3 completed without success (e.g. lost robots left tasks undone), 4 completed
but differs from the offline rollout (``--check-offline``; when operators, joining or dropped
robots changed the mission: a decision in the journal differs from the method's on the same
state), 1 did not complete (partial result), 130 interrupted (Ctrl-C or SIGTERM; partial result), 2 user error.

DDS discovery stays on this machine unless ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is already set
(e.g. SUBNET for a real multi-machine fleet); without ``ROS_DOMAIN_ID`` a random domain in
100..199 is used so that missions never meet by accident.
"""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Callable

from hmrta import methods
from hmrta_msgs_py.runtime import local_env



def default_instance() -> Path:
    import hmrta

    return Path(hmrta.__file__).resolve().parent / "data" / "example.yaml"


def _die_with_parent() -> None:
    """In the child: get SIGTERM when the launcher dies, however it dies (Linux). SIGINT is
    ignored until the child's first line (:mod:`hmrta_msgs_py.run_node`) takes it over: a Ctrl-C
    while the interpreter itself starts (its site packages) left a traceback in the child's log;
    one lost there is followed by the launcher's SIGTERM."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
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
    restarts: int = 0
    given_up: bool = False  # died once more than it may be restarted


def journal_clock(path: Path) -> float:
    """The mission clock of the last version a board journaled (NaN when there is none)."""
    from hmrta.board import JournalError, read_journal

    try:
        _, records, _, _ = read_journal(path)
    except (OSError, JournalError):
        return math.nan
    t = records[-1].get("clock") if records else None
    return float(t) if isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) else math.nan


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
    method: str = "greedy"
    method_options: dict[str, Any] = field(default_factory=dict)  # e.g. {"checkpoint": "my.pt"}
    agents_per_process: int = 1
    time_scale: float = 0.0
    board_params: dict[str, Any] = field(default_factory=dict)
    board_ros_args: list[str] = field(default_factory=list)  # e.g. remaps
    sim_params: dict[str, Any] = field(default_factory=dict)
    sim_ros_args: list[str] = field(default_factory=list)
    external: list[str] = field(default_factory=list)  # robots driven outside (not simulated)
    no_agent: list[str] = field(default_factory=list)  # robots whose agent runs elsewhere
    added: list[str] = field(default_factory=list)  # robots a scenario adds later: their agents wait to be added
    agent_ros_args: dict[str, list[str]] = field(default_factory=dict)  # robot -> its own process with these
    keystore: Path | None = None  # mission keystore (hmrta keys create): board and agents authenticate
    board: Child | None = None
    sim: Child | None = None
    agents: list[Child] = field(default_factory=list)
    max_restarts: int = 3  # per process (the board only when it has a journal to resume from)
    journal: Path | None = None  # the board's journal: a board that dies is restarted on it
    incidents: list[str] = field(default_factory=list)  # what died and what was done about it
    last_board: str | None = None  # the latest keyframe seen by run_monitor (its text)
    board_tail: list[str] = field(default_factory=list)  # the latest stream headers seen (a partial result
    # applies those after the keyframe to its state)
    record: Path | None = None  # record the mission to this MCAP file (the recorder node)
    recorder: Child | None = None  # started first, stopped last (not among children())
    mission_namespace: str = "/"  # every node's mission_namespace (topics <ns>/hmrta/..., <ns>/<robot>/...)

    def _spawn(self, name: str, module: str, args: list[str]) -> Child:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log = self.log_dir / f"{name}.log"
        fh = open(log, "w")
        # through console.run, as the node's console script: a signal in its first second is one line
        cmd = [sys.executable, "-u", "-m", "hmrta_msgs_py.run_node", module.rsplit(".", 1)[1], module, *args]
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=self.env,
                                start_new_session=True, preexec_fn=_die_with_parent if sys.platform == "linux" else None)
        return Child(name, cmd, proc, log, fh)

    def agent_groups(self) -> list[tuple[list[str], list[str]]]:
        """[(robots, extra ros args)] for the agent processes."""
        everyone = self.robots + [r for r in self.added if r not in self.robots]
        own = [r for r in everyone if r in self.agent_ros_args]
        rest = [r for r in everyone if r not in self.agent_ros_args and r not in self.no_agent]
        n = max(1, self.agents_per_process)
        groups = [(rest[i:i + n], []) for i in range(0, len(rest), n)]
        return groups + [([r], self.agent_ros_args[r]) for r in own]

    def start_recorder(self, timeout: float = 30.0) -> None:
        """Start the recorder and wait (at most ``timeout`` s) until it has subscribed (its
        ``.part`` file exists), so that it hears the mission from its first message."""
        from hmrta_coordinator.recorder import part_path

        out = Path(self.record).absolute()
        part = part_path(out)
        part.unlink(missing_ok=True)
        self.recorder = self._spawn("recorder", "hmrta_coordinator.recorder",
                                    ["--ros-args", *ros_params({"output": str(out), "robots": self.robots,
                                                                **self._namespace()})])
        deadline = time.monotonic() + timeout
        while not part.exists() and self.recorder.proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)

    def wait_recorder_heard_board(self, timeout: float = 30.0) -> bool:
        """Wait (at most ``timeout`` s) until the recorder has received the board's latched mission
        message, so that it has discovered the board before the robots start: a fast mission
        otherwise ends before a busy machine's DDS discovery matches the recorder, and the
        recording holds nothing. False (and a warning) when it did not within ``timeout``."""
        from hmrta_coordinator.recorder import HEARD

        c = self.recorder
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and c.proc.poll() is None and (self.board.proc.poll() is None):
            try:
                if HEARD in c.log.read_text(errors="replace"):
                    return True
            except OSError:
                pass
            time.sleep(0.05)
        why = ("the recorder exited" if c.proc.poll() is not None else "the task board exited"
               if self.board.proc.poll() is not None else f"the recorder did not hear the board within {timeout:g} s")
        print(f"hmrta-mission: warning: {why}; the recording may miss the mission's start (see {c.log})",
              file=sys.stderr, flush=True)
        return False

    def stop_recorder(self, timeout: float = 10.0) -> None:
        """Stop the recorder (SIGINT: it finishes and renames its file), SIGKILL after ``timeout`` s."""
        c = self.recorder
        if c is None:
            return
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGKILL, 5.0)):
            if c.proc.poll() is not None:
                break
            try:
                c.proc.send_signal(sig)
            except ProcessLookupError:
                break
            try:
                c.proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                pass
        if c._fh is not None:
            c._fh.close()
            c._fh = None

    def _namespace(self) -> dict[str, str]:
        """The mission_namespace parameter of every node, when not the default."""
        return {"mission_namespace": self.mission_namespace} if self.mission_namespace != "/" else {}

    def start(self) -> None:
        if self.record is not None and self.recorder is None:
            self.start_recorder()
        common = {"seed": self.seed, "method": self.method, **self.method_options, **self._namespace()}
        if self.keystore is not None:
            common["keystore"] = str(self.keystore)
        bp = {"instance": str(self.instance), "robot_names": self.robots, **common, **self.board_params}
        if self.out is not None:
            bp["output"] = str(self.out)
        if self.journal is not None:
            bp["journal"] = str(self.journal)
        self.board = self._spawn("task_board", "hmrta_coordinator.task_board",
                                 ["--ros-args", *ros_params(bp), *self.board_ros_args])
        if self.recorder is not None:
            self.wait_recorder_heard_board()
        sp = {"time_scale": self.time_scale, **self._namespace(), **self.sim_params}
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

    def supervise(self, clock: float = math.nan, log: IO | None = None) -> str | None:
        """Restart the simulated-robot or agent process that died (non-zero exit: a crash, a
        signal) while the board runs, at most ``max_restarts`` times each (they resynchronise
        from the latched mission and board). Returns why the mission cannot go on, or None.
        The board itself is not restarted (its exit is the caller's to judge)."""
        at = f" at t={clock:.3f}" if clock == clock else ""
        for c in ([self.sim] if self.sim is not None else []) + self.agents:
            rc = c.proc.poll()
            if rc is None or rc == 0 or c.given_up:  # running, or finished its part (done, or its robots lost)
                continue
            if rc == 2:  # it refused its configuration or the mission (see its log): a restart would refuse again
                c.given_up = True
                self.incidents.append(f"{c.name} exited with status 2{at}: it refused its parameters or the "
                                      f"mission (see {c.log}); not restarted")
                if c is self.sim:
                    return self.incidents[-1]
                continue
            what = f"{c.name} process died ({exit_text(rc)}){at}"
            if c.restarts >= self.max_restarts:
                self.incidents.append(f"{what}; not restarted (already restarted {c.restarts} times)")
                c.given_up = True
                if c is self.sim:  # nobody drives the mission clock
                    return f"{what} after {c.restarts} restarts"
                continue  # the board declares its robots lost and goes on
            c.restarts += 1
            self.incidents.append(f"{what}; restarted ({c.restarts}/{self.max_restarts})")
            print(f"hmrta-mission: {self.incidents[-1]}", file=log or sys.stderr, flush=True)
            self._respawn(c, what)
        return None

    def _respawn(self, c: Child, why: str) -> None:
        if c._fh is not None:
            c._fh.close()
        fh = open(c.log, "a")
        fh.write(f"\n==== {why}; restarted by hmrta-mission ====\n")
        fh.flush()
        c.proc = subprocess.Popen(c.cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=self.env,
                                  start_new_session=True,
                                  preexec_fn=_die_with_parent if sys.platform == "linux" else None)
        c._fh = fh

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
        self.stop_recorder()  # last: it has heard everything, the result included


def exit_text(rc: int) -> str:
    """Popen return code -> 'SIGKILL' / 'exit code 1'."""
    if rc < 0:
        try:
            return signal.Signals(-rc).name
        except ValueError:
            return f"signal {-rc}"
    return f"exit code {rc}"


def log_tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


# ---------------------------------------------------------------------------------------------
def run_monitor(procs: MissionProcesses, n_tasks: int, timeout: float, quiet: bool,
                on_board: Callable[[Any], None] | None = None) -> str:
    """Follow the board with a progress bar until the board process exits, restarting the
    simulated-robot and agent processes that die (``MissionProcesses.supervise``); returns "ok"
    if the board exited cleanly within ``timeout``, else what went wrong. The latest keyframe
    seen stays in ``procs.last_board`` and the stream headers since in ``procs.board_tail``;
    ``on_board`` (if given) is called with each board header."""
    import rclpy
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String
    from tqdm import tqdm

    from hmrta_msgs_py import topics
    from hmrta_msgs_py.codec import DecodeError, board_from_msg, clock_from_msg
    from hmrta_msgs_py.runtime import LEAN_NODE

    from rclpy.executors import SingleThreadedExecutor

    rclpy.init(args=[])
    node = rclpy.create_node("mission_monitor", **LEAN_NODE)
    executor = SingleThreadedExecutor()  # one executor for the whole run: every ready subscription gets its turn
    executor.add_node(node)
    tty = sys.stderr.isatty()
    bar = tqdm(total=n_tasks, desc="mission", unit="task", disable=quiet or not tty, file=sys.stderr,
               bar_format="{desc}: {n_fmt}/{total_fmt} tasks |{bar}| {elapsed} {postfix}")
    told = [-1]  # without a terminal: one line per quarter of the tasks

    seen = {"clock": math.nan, "phase": ""}  # mission clock (its clock topic or the board's), board phase

    def finished() -> bool:
        """The board ended the mission: its last board was seen, or its result is written (the
        stream is not latched, and a short mission's last board can end before it is heard)."""
        return seen["phase"] == "done" or (procs.out is not None and procs.out.exists())

    def when() -> str:
        t = seen["clock"]
        if t != t and procs.journal is not None:  # not heard (yet) over DDS: the board's journal knows
            t = journal_clock(procs.journal)
        return f" at t={t:.3f}" if t == t else " before the mission clock started"

    def clock_cb(msg: Clock) -> None:
        t = clock_from_msg(msg)
        if not t <= seen["clock"]:
            seen["clock"] = t

    def board_cb(msg: String) -> None:
        try:
            b = board_from_msg(msg, legs=False, state=False)
        except DecodeError:
            return
        procs.board_tail.append(msg.data)
        del procs.board_tail[:-20000]  # bounded (a partial result then holds the keyframe's state)
        seen["phase"] = b.phase
        if not b.clock <= seen["clock"]:  # the board's mission time, when the clock topic is not heard yet
            seen["clock"] = b.clock
        if on_board is not None:
            on_board(b)
        n = b.n_done + b.n_cancelled
        info = f"t={b.clock:.1f} {b.phase}" + (f" lost={len(b.lost)}" if b.lost else "")
        if b.n_tasks > bar.total:  # tasks added during the mission
            bar.total = b.n_tasks
        bar.n = n
        bar.set_postfix_str(info, refresh=False)
        bar.refresh()
        total = max(n_tasks, b.n_tasks)
        if not tty and not quiet and 4 * n // max(total, 1) > told[0]:
            told[0] = 4 * n // max(total, 1)
            print(f"mission: {n}/{total} tasks, {info}", file=sys.stderr, flush=True)

    def keyframe_cb(msg: String) -> None:
        procs.last_board = msg.data

    T = topics.MissionTopics(procs.mission_namespace)
    node.create_subscription(Clock, T.clock, clock_cb, topics.CLOCK_QOS)
    node.create_subscription(String, T.board, board_cb, topics.BOARD_QOS)
    node.create_subscription(String, T.keyframe, keyframe_cb, topics.KEYFRAME_QOS)
    deadline = time.monotonic() + timeout
    status = f"timed out after {timeout:g} s"
    try:
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
            rc = procs.board.proc.poll()
            if rc == 0 and not finished():
                for _ in range(10):  # its final version may still be on its way
                    executor.spin_once(timeout_sec=0.02)
            # exit code 0 before the end: stopped by a signal from outside (a plain kill), the mission unfinished;
            # 2: the board refused its parameters (a user error): a restart would refuse them again;
            # 3: the mission finished and failed (the result is written)
            early = rc == 0 and not finished()
            if (rc is not None and (rc not in (0, 2, 3) or early) and procs.journal is not None
                    and procs.board.restarts < procs.max_restarts):
                procs.board.restarts += 1
                what = "stopped before the mission finished (exit status 0)" if early else f"died ({exit_text(rc)})"
                procs.incidents.append(f"board process {what}{when()}; restarted on its journal "
                                       f"({procs.board.restarts}/{procs.max_restarts})")
                print(f"hmrta-mission: {procs.incidents[-1]}", file=sys.stderr, flush=True)
                procs._respawn(procs.board, procs.incidents[-1])
                continue
            if rc is not None:
                for _ in range(10):  # boards already received but not yet taken
                    executor.spin_once(timeout_sec=0.02)
                status = "ok" if rc in (0, 3) else f"board process died ({exit_text(rc)}){when()}"
                if status != "ok":
                    procs.incidents.append(status + ("; not restarted (the board's state lives in that process)"
                                                     if procs.journal is None else
                                                     "; not restarted: it refused its parameters (see its log)"
                                                     if rc == 2 else
                                                     f"; not restarted: it was restarted {procs.board.restarts} "
                                                     f"time(s) already (at most {procs.max_restarts})"))
                    status = procs.incidents[-1]  # what the console and the partial result say: why, too
                break
            if not finished():  # after the end everybody exits on their own
                failure = procs.supervise(seen["clock"])
                if failure is not None:
                    status = failure
                    break
        else:
            status = f"{status}{when()}"
            procs.incidents.append(status)
    finally:
        bar.close()
        executor.remove_node(node)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return status


def partial_result(inst, procs: MissionProcesses, method: str, seed: int, wall: float, reason: str):
    """The ``hmrta-solution/1`` of a mission that did not complete: ``success`` false, the
    ``failure`` reason, and what was done according to the latest board seen (routes committed,
    tasks completed with their times), or to the board's journal where it holds later versions."""
    from std_msgs.msg import String

    from hmrta.core import MissionState
    from hmrta.replica import Replica
    from hmrta.solution import solution_from_state
    from hmrta_msgs_py.codec import DecodeError, board_from_msg

    state, b = None, None
    try:  # the latest keyframe and the versions streamed after it; with no keyframe heard (its latched
        # topic matched after the board died), the mission's initial state and the stream from version 1
        kf = board_from_msg(String(data=procs.last_board)) if procs.last_board is not None else None
        heads = [board_from_msg(String(data=text), legs=False, state=False) for text in procs.board_tail]
        rep = Replica()
        if kf is not None:
            rep.receive(kf, lambda: (kf.legs, kf.state), inst)
        elif heads and heads[0].version == 1:
            rep.genesis(heads[0].session, inst, seed, methods.rules(procs.method, **procs.method_options))
        for h in heads:
            rep.receive(h)
        if rep.synced and rep.version >= 1:
            state, b = rep.state, rep.head
        elif kf is not None:
            state, b = MissionState.from_snapshot(inst, kf.state), kf
    except (DecodeError, KeyError, TypeError, ValueError):  # (MethodError is a ValueError)
        state, b = None, None
    lost = list(b.lost) if b is not None else []
    version, clock = (b.version, b.clock) if b is not None else (None, None)
    if procs.journal is not None and procs.journal.exists():  # the board's own record, where it went further
        # than what the launcher heard (it stops the board at once: the last versions may still be on the way)
        from hmrta.board import JournalError, replay_journal

        try:
            core, v, t = replay_journal(inst, procs.journal, seed, methods.rules(procs.method, **procs.method_options))
        except (JournalError, KeyError, TypeError, ValueError, IndexError):
            v = 0
        if v > (version or 0):
            state, lost, version, clock = core.state, sorted(core.lost), v, t
    if state is None:  # no board seen: nothing was done
        state = MissionState(inst, seed=seed)
    sol = solution_from_state(state, method, seed, 0.0)  # the agents' compute is the board's to know
    sol.success = False
    sol.makespan = math.nan
    for ag in sol.agents:
        ag["return_time"] = math.nan
    n_done = sum(t["finish"] == t["finish"] for t in sol.tasks)
    sol.extra.update({
        "failure": reason,
        "partial": True,
        "transport": "ros2",
        "robots": procs.robots,
        "tasks_done": n_done,
        "undone_tasks": [m for m, t in enumerate(sol.tasks) if t["finish"] != t["finish"]],
        "lost_robots": [(procs.robots + procs.added)[a] if a < len(procs.robots) + len(procs.added) else f"robot_{a}"
                        for a in lost],
        "board_version": version,
        "board_clock": clock,
        "incidents": list(procs.incidents),
        "mission_wall_seconds": round(wall, 3),
        # a task_board started with -p journal:=<it> (and the same instance, seed and method) resumes it
        "journal": str(procs.journal) if procs.journal is not None and procs.journal.exists() else None,
    })
    return sol


def print_metrics(sol, extra: dict[str, Any], inst) -> None:
    print(sol.summary())
    A, M = len(sol.routes), len(sol.tasks)  # a mission that grew while it ran: as it ended
    grew = "" if (A, M) == (inst.n_agents, inst.n_tasks) else \
        f" (at the start {inst.n_agents} robots, {inst.n_tasks} tasks)"
    print(f"  robots {A}, tasks {M}{grew}: {M - len(extra.get('undone_tasks', []))} done"
          + (f", undone (cancelled included) {extra['undone_tasks']}" if extra.get("undone_tasks") else ""))
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
    if extra.get("authenticated"):
        print(f"  robots authenticated (hmrta.keys); refused: {extra.get('auth_rejections')}")


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # before any process started (loading, choosing the method)
        print("hmrta-mission: interrupted before the mission started: no process was started, no result written",
              file=sys.stderr)
        return 130


def _main(argv: list[str] | None = None) -> int:
    from rclpy.executors import ExternalShutdownException
    from rclpy.utilities import remove_ros_args

    from hmrta.cli import HelpFormatter, Parser  # each default shown once; bad arguments: one line

    argv = list(sys.argv if argv is None else argv)
    p = Parser(prog="hmrta-mission", description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("instance", nargs="?", default=None,
                   help="instance YAML (or CTAS-D config.json); default: the built-in example mission")
    p.add_argument("--scenario", default=None, metavar="FILE",
                   help="play an hmrta-scenario/1 file's timed events live (instead of the instance argument); "
                        "for each robot its add_robot events add, an agent robot_<n> starts and waits until the "
                        "board adds it")
    p.add_argument("--seed", type=int, default=0, help="episode seed (decision order, sampling)")
    p.add_argument("--out", default="out/mission.json", help="solution JSON to write")
    methods.add_arguments(p, live=True, default="portfolio")  # --method and its options, from the method table
    p.add_argument("--agents-per-process", type=int, default=1, metavar="N",
                   help="robots hosted per agent process (lean nodes on one executor)")
    p.add_argument("--time-scale", type=float, default=0.0,
                   help="sim seconds per wall second (0: as fast as possible)")
    p.add_argument("--heartbeat-timeout", type=float, default=5.0, help="wall seconds before a silent robot is lost")
    p.add_argument("--domain-id", type=int, default=None, help="ROS domain (default: $ROS_DOMAIN_ID or random 100-199)")
    p.add_argument("--mission-namespace", default="/", metavar="NS",
                   help="namespace of the mission's topics (NS/hmrta/..., NS/<robot>/pose and goal_pose), to run "
                        "beside another mission on the same ROS domain (default /)")
    p.add_argument("--plot", default=None, help="routes + Gantt picture (default: next to --out, .png)")
    p.add_argument("--no-plot", action="store_true", help="do not draw the picture")
    p.add_argument("--check-offline", action="store_true",
                   help="also run the offline rollout (hmrta solve) and compare routes and makespan (exit 4 "
                        "when they differ); when operators, joining or dropped robots changed the mission, "
                        "replay the board's journal and check every decision against the method's on the same "
                        "state instead")
    p.add_argument("--timeout", type=float, default=600.0, help="give up after this many wall seconds")
    auth = p.add_mutually_exclusive_group()
    auth.add_argument("--keystore", default=None, metavar="DIR",
                      help="authenticate robots with this mission keystore (hmrta keys create; docs/security.md)")
    auth.add_argument("--authenticate", action="store_true",
                      help="authenticate robots with a fresh keystore made in the mission's log folder")
    p.add_argument("--no-journal", action="store_true",
                   help="no board journal (<out>_logs/journal.jsonl): a board that dies ends the mission")
    p.add_argument("--record", default=None, metavar="FILE.mcap",
                   help="record every /hmrta topic and the robots' goals and poses to this MCAP file "
                        "(Foxglove, rosbag2; hmrta render --from FILE.mcap)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bars (the portfolio's simulation of its candidates, the mission)")
    args = p.parse_args(remove_ros_args(argv)[1:])
    for flag, v, ok, want in (("--time-scale", args.time_scale, args.time_scale >= 0, "a number >= 0"),
                              ("--timeout", args.timeout, args.timeout > 0, "a number of seconds > 0"),
                              ("--heartbeat-timeout", args.heartbeat_timeout, args.heartbeat_timeout > 0,
                               "a number of seconds > 0"),
                              ("--seed", args.seed, args.seed >= 0, "an integer >= 0"),
                              ("--domain-id", args.domain_id, args.domain_id is None or 0 <= args.domain_id <= 232,
                               "a ROS domain id in 0..232")):
        if not ok or (isinstance(v, float) and not math.isfinite(v)):
            p.error(f"{flag}: expected {want}, got {v}")
    from hmrta_msgs_py.topics import check_mission_namespace

    try:
        mission_namespace = check_mission_namespace(args.mission_namespace, "--mission-namespace")
    except ValueError as e:
        p.error(str(e))

    from hmrta.formats import load_instance
    from hmrta.instance import InstanceError
    from hmrta.solution import Solution

    if args.scenario and args.instance:
        p.error("give the instance argument or --scenario, not both")
    if args.plot and args.no_plot:
        p.error("--plot and --no-plot: give one of them, not both")
    path = Path(args.scenario or args.instance) if (args.scenario or args.instance) else default_instance()
    if args.agents_per_process < 1:
        p.error(f"--agents-per-process: expected an integer >= 1, got {args.agents_per_process}")
    from hmrta.cli import UserError, writable

    try:  # every output can be written (and is not the mission itself), checked before any work
        for flag, value in (("--out", args.out), ("--plot", None if args.no_plot else args.plot),
                            ("--record", args.record)):
            if value:
                writable(flag, value, inputs=(path,))
    except UserError as e:
        print(f"hmrta-mission: error: {e}", file=sys.stderr)
        return 2
    from hmrta import keys as hkeys

    asked, keystore = args.method, None
    try:
        inst = load_instance(path)
        if args.scenario and not inst.dynamic:  # --scenario of a plain mission file: said, then run
            print(f"hmrta-mission: note: --scenario {path} has no timed events or releases: it runs as a plain "
                  f"mission", file=sys.stderr)
        robots = [f"robot_{a}" for a in range(inst.n_agents)]
        if args.keystore:  # every robot of the mission has a key (checked before any simulation runs)
            keystore = Path(args.keystore).absolute()
            hkeys.load_keystore(keystore, robots)
        # the live method every robot runs (a per-mission choice such as portfolio is made here)
        from hmrta.cli import SolveProgress  # a bar on stderr when the choice takes seconds (a large mission)

        with SolveProgress(args.method, not args.quiet and sys.stderr.isatty()) as prog:
            args.method, method_options, scores = methods.resolve(inst, args.method, args.seed, progress=prog,
                                                                  **methods.options_from_args(args))
        methods.rules(args.method, **method_options)  # its checkpoint readable (a bad one: here, not in every node)
    except (InstanceError, methods.MethodError, hkeys.KeystoreError) as e:
        print(f"hmrta-mission: error: {e}", file=sys.stderr)
        return 2
    chosen = None
    if scores is not None:
        ck = method_options.get("checkpoint")
        chosen = args.method + (f"@{ck}" if ck else "")  # as offline results name it
        print("method chosen by simulation: " + args.method + (f" with checkpoint {ck}" if ck else "") + " ("
              + ", ".join(f"{c} {v:.2f}" for c, v in scores.items()) + ")", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():
        out.unlink()  # never report a previous run's result
    log_dir = out.with_name(out.stem + "_logs")
    env = local_env(domain_id=args.domain_id)
    env.setdefault("ROS_LOG_DIR", str(log_dir / "ros"))
    env.setdefault("PYTHONUNBUFFERED", "1")
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_LOG_DIR")})
    # robots the scenario's add_robot events add: the board names the k-th robot_<robots + k>; their
    # agents start now and wait until the board adds them (sim_robot simulates them from then on)
    added = [f"robot_{inst.n_agents + k}" for k in range(sum(e.get("type") == "add_agent" for e in inst.events))]
    if args.authenticate:  # a fresh keystore in the mission's log folder
        log_dir.mkdir(parents=True, exist_ok=True)
        keystore = log_dir / "keys"
        try:
            hkeys.create_keystore(keystore, robots + added, force=True)  # (the robots the scenario adds too)
        except hkeys.KeystoreError as e:
            print(f"hmrta-mission: error: {e}", file=sys.stderr)
            return 2
    procs = MissionProcesses(path, robots, out, log_dir, env, seed=args.seed, method=args.method,
                             method_options=method_options, agents_per_process=args.agents_per_process,
                             time_scale=args.time_scale, keystore=keystore,
                             board_params={"heartbeat_timeout": args.heartbeat_timeout, "progress_period": 0.0},
                             journal=None if args.no_journal else log_dir / "journal.jsonl",
                             record=Path(args.record) if args.record else None, added=added,
                             mission_namespace=mission_namespace)
    if procs.journal is not None and procs.journal.exists():  # a new mission never resumes a previous run's
        # journal; it is kept beside (the record of an interrupted run; task_board -p journal:=... resumes it)
        kept = procs.journal.with_name("journal.previous.jsonl")
        procs.journal.replace(kept)
        print(f"hmrta-mission: kept the previous run's journal as {kept}", flush=True)
    n_proc = 2 + len(procs.agent_groups())
    print(f"mission {inst.name}: {inst.n_agents} robots, {inst.n_tasks} tasks, method {args.method}, seed {args.seed}; "
          f"{n_proc} processes on ROS domain {env['ROS_DOMAIN_ID']} "
          f"(discovery {env['ROS_AUTOMATIC_DISCOVERY_RANGE']}); logs in {log_dir}", flush=True)
    ns = f" --mission-namespace {mission_namespace}" if mission_namespace != "/" else ""
    print(f"operators: hmrta-task --domain-id {env['ROS_DOMAIN_ID']}{ns} list (add, cancel)", flush=True)
    t0 = time.monotonic()
    interrupted, status = False, "interrupted"
    try:
        procs.start()
        status = run_monitor(procs, inst.n_tasks, args.timeout, args.quiet)
    except (KeyboardInterrupt, ExternalShutdownException):
        print("interrupted: stopping the mission", file=sys.stderr)
        interrupted = True
    finally:
        procs.stop(grace=5.0 if status == "ok" else 0.0)  # a failed mission: stop the rest at once
    wall = time.monotonic() - t0
    if not out.exists():  # the board did not finish: a partial result from the last board seen
        if status == "ok":
            status = "the task board exited without writing the result"
        sol = partial_result(inst, procs, args.method, args.seed, wall, status)
        sol.save(out)
        resume = (f"; its journal {sol.extra['journal']} can resume it (task_board -p journal:=..., docs/ros.md)"
                  if sol.extra.get("journal") else "")
        print(f"hmrta-mission: the mission did not complete ({status}); {sol.extra['tasks_done']}/{len(sol.tasks)} "
              f"tasks were done; wrote the partial result {out}{resume}; board log tail:\n{log_tail(procs.board.log)}",
              file=sys.stderr)
        if procs.record is not None and procs.record.exists():
            print(f"wrote {procs.record} (the recording up to the end)", file=sys.stderr)
        return 130 if interrupted else 1
    sol = Solution.from_dict(json.loads(out.read_text()))
    if chosen is not None:  # labelled as offline: the method asked for, what it chose and why
        sol.method = asked
        sol.extra["portfolio"] = {"chosen": chosen, "candidates": scores}
    if procs.incidents:  # the mission completed in spite of them: the result says what happened
        sol.extra["incidents"] = list(procs.incidents)
    if chosen is not None or procs.incidents:
        sol.save(out)
        for line in procs.incidents:
            print(f"  incident: {line}")
    print_metrics(sol, sol.extra, inst)
    print(f"  total wall time {wall:.2f} s (including start-up of {n_proc} processes)")
    print(f"wrote {out}")
    if procs.record is not None:
        print(f"wrote {procs.record}" if procs.record.exists() else
              f"hmrta-mission: the recording {procs.record} was not written (see {log_dir / 'recorder.log'})")
    differs = False
    if args.check_offline:
        changed = sol.extra.get("live_events") or {}
        if args.method == "rl-sample":  # each robot samples its own decisions: no rollout repeats them
            print("offline rollout: not compared: live, rl-sample samples each decision on the deciding robot "
                  "(offline it keeps the best of several sampled rollouts)")
        elif changed:  # operator tasks, robots joining or dropped: no rollout has them; the journal has
            what = ", ".join(f"{n} {kind}" for kind, n in sorted(changed.items()))
            if procs.journal is None or not procs.journal.exists():
                print(f"offline rollout: not compared: the mission changed while it ran ({what}) and no "
                      f"journal was kept")
            else:
                from hmrta.board import JournalError, check_journal_decisions
                from hmrta.methods import decider

                decide, rules = decider(args.method, seed=args.seed, **method_options)
                try:
                    agree, first = check_journal_decisions(inst, procs.journal, decide, args.seed, rules)
                except (JournalError, ValueError, KeyError, TypeError, IndexError) as e:
                    agree, first = 0, f"the journal does not replay ({type(e).__name__}: {e})"
                print(f"offline replay of the journal ({args.method}; the mission changed while it ran: {what}): "
                      f"{agree} decisions the method's on the same state" + (f"; NOT {first}" if first else ": yes"))
                differs = first is not None
        else:
            from hmrta.methods import solve

            ref = solve(inst, args.method, seed=args.seed, **method_options)
            same = ref.routes == sol.routes and (ref.makespan == sol.makespan or (
                math.isnan(ref.makespan) and math.isnan(sol.makespan)))  # a failed mission has none
            print(f"offline rollout ({args.method}): makespan {ref.makespan:.3f}; same routes and makespan: "
                  f"{'yes' if same else 'NO'}")
            differs = not same
    if not args.no_plot:
        plot = Path(args.plot) if args.plot else out.with_suffix(".png")
        try:
            from hmrta.render import render
        except ImportError:
            print("(no picture: hmrta.render is not available; pip install 'hmrta[plot]')")
        else:
            from hmrta.solution import final_instance

            try:  # a mission that grew while it ran is drawn as it ended
                render(final_instance(inst, sol, str(out)), sol, plot)
                print(f"wrote {plot}")
            except (ValueError, OSError) as e:
                print(f"hmrta-mission: no picture: {e}", file=sys.stderr)
    if differs:
        print("hmrta-mission: the live mission differs from the offline rollout (--check-offline)", file=sys.stderr)
    return 3 if not sol.success else 4 if differs else 0


if __name__ == "__main__":
    sys.exit(main())
