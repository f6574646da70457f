#!/usr/bin/env python3
"""Board bytes per decision: the board stream (each version's events) with keyframes, against a full
board (header, legs, state snapshot) on every version. A script, not a test.

    .venv/bin/python benchmarks/board_bytes.py [--sizes 150,500 300,1000 600,2000] [--seed 1]
                                               [--keyframe-period 0] [--samples 60]

Drives the ROS-free task board (:class:`hmrta.board.MissionBoard`) through a whole MA-AT mission
(10 species, or 5 when the robots are not a multiple of 10; 5 skills) with greedy agents and
robots that arrive at once, and encodes every message with the ROS codec (``hmrta_msgs_py.codec``; plain JSON of the same shape when ROS is not
installed): no DDS. An agent's replica (:class:`hmrta.replica.Replica`) follows the stream and
decides; its state is checked against the board's at the end. The full board of every version is
what the board published before the stream: it is built and parsed (``MissionState.from_snapshot``,
what an agent did per board) on ``--samples`` versions spread over the mission, and its total is
the sampled mean times the versions. Prints, per size: versions, decisions, keyframes, message
bytes (median, per decision, total) both ways, and the board's build and an agent's read time per
version both ways, with the machine load.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

from hmrta.baselines import GREEDY_RULES, Greedy
from hmrta.board import MissionBoard, board_header
from hmrta.core import MissionState
from hmrta.generators import ScenarioGenerator
from hmrta.replica import Frame, Replica

try:  # the wire encoding of the ROS nodes
    from hmrta_msgs_py import codec as C
    from std_msgs.msg import String
except ImportError:  # no ROS here: the same JSON, written the same way
    C = None

DEFAULT_SIZES = ["150,500", "300,1000", "600,2000"]


class _Choice:  # what the codec's choice_from_msg gives the board
    def __init__(self, robot, session, version, node):
        self.robot, self.session, self.version, self.node, self.compute_ms, self.payload = \
            robot, session, version, node, 0.0, None


def _compact(d) -> str:
    return json.dumps(d, separators=(",", ":"), allow_nan=False)


def encode(v, keyframe: bool) -> str:
    """The text of the stream message (or of the keyframe) of View ``v``."""
    if C is not None:
        b = C.Board(v.session, v.version, v.rev, v.phase, v.decider, v.clock, v.horizon, v.n_done, v.n_cancelled,
                    v.n_tasks, v.lost, prev=v.prev, events=v.events, digest=v.digest)
        if keyframe:
            b = C.Board(**{**b.__dict__, "legs": v.legs, "until": v.until, "keyframe": True})
            return C.board_to_msg(b, v.state_json).data
        return C.board_to_msg(b).data
    head = board_header(v)
    if not keyframe:
        head.pop("until", None)  # only keyframes carry it
        return _compact(head)
    legs = _compact([None if g is None else [g[0], [list(x) for x in g[1]]] for g in v.legs])
    return "\n".join((_compact(head), legs, v.state_json))


def decode(text: str):
    """(header, keyframe parts function or None), as an agent decodes a message."""
    if C is not None:
        msg = String(data=text)
        b = C.board_from_msg(msg, legs=False, state=False)
        return b, ((lambda: (lambda f: (f.legs, f.state))(C.board_from_msg(msg))) if b.keyframe else None)
    parts = text.split("\n", 2)
    f = Frame.from_header(json.loads(parts[0]))
    return f, ((lambda: (json.loads(parts[1]), json.loads(parts[2]))) if len(parts) == 3 else None)


def full_board(b: MissionBoard) -> str:
    """The full board of the current version, as published before the stream (header, legs of
    every robot, state snapshot)."""
    st = b.state
    legs = _compact([st.legs(a) for a in range(st.A)])
    snap = json.dumps(st.snapshot(), separators=(",", ":"))
    head = _compact({"format": "hmrta-board/1", "session": b.session, "version": b.version, "rev": b.rev,
                     "phase": b.phase, "decider": st.agent, "clock": float(st.clock), "horizon": float(b._key[3]),
                     "n_done": int(st.n_done), "n_cancelled": int(st.n_cancelled), "n_tasks": st.M,
                     "lost": sorted(b.lost)})
    return "\n".join((head, legs, snap))


def run(agents: int, tasks: int, seed: int, period: int, samples: int) -> dict:
    species = 10 if agents % 10 == 0 else 5
    inst = ScenarioGenerator("MA-AT", agents, species, tasks, 5).instance(seed, 0)
    b = MissionBoard(inst, seed=seed, rules=GREEDY_RULES, wait_for_robots=False, tolerance=1e9,
                     keyframe_period=period)
    for a in range(inst.n_agents):
        b.pose(a, *inst.depots[a])
    rep, decide = Replica(), Greedy()
    # a rough count of the versions, to spread the full-board samples over the mission
    stride = max(1, int(3.2 * tasks) // max(1, samples))
    stream, keyframes, full, t_build, t_read, t_full_build, t_full_read = [], [], [], [], [], [], []
    t0 = time.perf_counter()
    for _ in range(10**7):
        t = time.perf_counter()
        v = b.poll()
        if v is not None:
            texts = [encode(v, False)] if v.stream else []
            if v.keyframe:
                texts.append(encode(v, True))
            t_build.append(time.perf_counter() - t)
            stream += [len(x) for x in texts[:1] if v.stream]
            keyframes += [len(texts[-1])] if v.keyframe else []
            t = time.perf_counter()
            for text in texts:  # the agent side: decode, apply (or load a keyframe it needs)
                f, kf = decode(text)
                rep.receive(f, kf, inst)
            t_read.append(time.perf_counter() - t)
            if v.stream and v.version % stride == 0:
                t = time.perf_counter()
                text = full_board(b)
                t_full_build.append(time.perf_counter() - t)
                full.append(len(text))
                t = time.perf_counter()
                MissionState.from_snapshot(inst, json.loads(text.split("\n", 2)[2]))
                t_full_read.append(time.perf_counter() - t)
        if b.finished:
            break
        if b.phase == "decide":
            assert rep.current and rep.version == b.version, rep.why
            assert b.choice(_Choice(b.names[b.state.agent], b.session, b.version, int(decide(rep.state)))) is None
        else:
            b.set_clock(b._key[3])
    wall = time.perf_counter() - t0
    assert b.finished and json.dumps(rep.state.snapshot()) == json.dumps(b.state.snapshot())
    n, d = b.version, int(b.state.decisions)
    total = sum(stream) + sum(keyframes)
    full_total = statistics.fmean(full) * n
    ms = 1e3
    return {"size": f"{agents}/{tasks}", "versions": n, "decisions": d, "keyframes": len(keyframes),
            "kf_reasons": dict(b.keyframes), "success": b.state.success,
            "stream_median": statistics.median(stream), "kf_median": statistics.median(keyframes),
            "total": total, "per_decision": total / d,
            "full_median": statistics.median(full), "full_total": full_total, "full_per_decision": full_total / d,
            "build_ms": statistics.fmean(t_build) * ms, "read_ms": statistics.fmean(t_read) * ms,
            "full_build_ms": statistics.fmean(t_full_build) * ms, "full_read_ms": statistics.fmean(t_full_read) * ms,
            "samples": len(full), "wall": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, help="robots,tasks (MA-AT, 10 species, 5 skills)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keyframe-period", type=int, default=0, help="versions between keyframes (0: by size)")
    ap.add_argument("--samples", type=int, default=60, help="versions whose full board is built and parsed")
    args = ap.parse_args()
    print(f"# board bytes per decision: python {platform.python_version()}, {platform.machine()} "
          f"x{os.cpu_count()}, load {' '.join(f'{x:.2f}' for x in os.getloadavg())}, encoding "
          f"{'hmrta_msgs_py.codec' if C is not None else 'plain JSON (no ROS)'}, keyframe_period "
          f"{args.keyframe_period or 'auto (by size)'}, seed {args.seed}")
    print("| robots/tasks | versions | decisions | keyframes | stream msg median | keyframe median "
          "| events+keyframes per decision | total | full board median | full board per decision | total "
          "| ratio | board build ms/version (stream / full) | agent read ms/version (replica / full) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for spec in args.sizes:
        agents, tasks = (int(x) for x in spec.split(","))
        r = run(agents, tasks, args.seed, args.keyframe_period, args.samples)
        kb = 1e-3
        print(f"| {r['size']} | {r['versions']} | {r['decisions']} | {r['keyframes']} | "
              f"{r['stream_median'] * kb:.2f} kB | {r['kf_median'] * kb:.0f} kB | {r['per_decision'] * kb:.2f} kB | "
              f"{r['total'] * 1e-6:.1f} MB | {r['full_median'] * kb:.0f} kB | {r['full_per_decision'] * kb:.0f} kB | "
              f"{r['full_total'] * 1e-6:.0f} MB | {r['full_total'] / r['total']:.0f}x | "
              f"{r['build_ms']:.2f} / {r['full_build_ms']:.1f} | {r['read_ms']:.2f} / {r['full_read_ms']:.1f} |",
              flush=True)
        print(f"#   {r['size']}: keyframes {r['kf_reasons']}, success {r['success']}, full board sampled on "
              f"{r['samples']} versions, {r['wall']:.1f} s", flush=True)
    print(f"# load after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
