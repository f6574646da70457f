"""Mutation fuzzing of every file the hmrta command line reads (the long run of
tests/policy/test_fuzz.py).

    .venv/bin/python benchmarks/fuzz_inputs.py --cases 5000 --seed 1

Instance YAML, CTAS-D config.json, routes, solutions, checkpoints and training configs, mutated
byte by byte and structure by structure (see tests/policy/fuzz_cases.py). Prints the count of
each outcome per format, and every case that ended badly: an internal error (exit 1 or a
traceback), a hang (beyond the time limit), or exit 2 without exactly one line naming the file.
Exits 1 when there is any such case.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "policy"))
sys.path.insert(0, str(ROOT / "policy"))

import fuzz_cases as fz  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=5000, help="number of cases")
    ap.add_argument("--seed", type=int, default=1, help="fuzzing seed (the same seed gives the same files)")
    ap.add_argument("--heavy-share", type=float, default=0.01,
                    help="share of heavy cases (deep nesting, alias bombs, FIFOs, malicious pickles), each in "
                         "a subprocess under a memory limit and a timeout")
    ap.add_argument("--formats", default=",".join(fz.FORMATS), help="comma list of formats to fuzz")
    ap.add_argument("--show", type=int, default=20, help="bad cases to print in full")
    ap.add_argument("--keep", default=None, help="keep the case files in this folder")
    args = ap.parse_args()
    formats = tuple(f for f in args.formats.split(",") if f)
    unknown = [f for f in formats if f not in fz.FORMATS]
    if unknown:
        ap.error(f"--formats: unknown format {unknown[0]!r} (expected some of {', '.join(fz.FORMATS)})")
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="hmrta-fuzz-"))
    t0 = time.perf_counter()
    with fz.one_thread():
        outcomes = _run(args, formats, work, t0)
    wall = time.perf_counter() - t0
    return _report(args, outcomes, wall)


def _run(args, formats, work: Path, t0: float) -> list:
    try:
        seeds = fz.make_seeds(work / "seeds")
        cases = fz.generate(args.cases, args.seed, seeds, heavy_share=args.heavy_share, formats=formats)
        outcomes = []
        for c in cases:
            where = work / f"case{c.id:06d}"
            outcomes.append(fz.run_case(c, seeds, where))
            if not args.keep:
                shutil.rmtree(where, ignore_errors=True)
            if (c.id + 1) % 500 == 0:
                print(f"  {c.id + 1}/{len(cases)} cases, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return outcomes


def _report(args, outcomes: list, wall: float) -> int:
    print(f"{len(outcomes)} cases, seed {args.seed}, {wall:.1f} s wall")
    print(fz.summary(outcomes))
    bad = [o for o in outcomes if o.outcome not in fz.GOOD]
    if bad:
        print(f"\n{len(bad)} bad cases; by format / mutation / outcome:")
        for (fmt, kind, out), n in Counter((o.case.fmt, o.case.kind, o.outcome) for o in bad).most_common():
            print(f"  {n:5d}  {fmt}/{kind}: {out}")
        for o in bad[:args.show]:
            print(f"\n--- {o.case.describe()}: {o.outcome} (rc {o.rc}, {o.seconds:.2f} s)\n{o.detail.strip()[-1500:]}")
    unnamed = [o for o in outcomes if o.names_field is False]
    if unnamed:
        print(f"\nstructure mutations whose message names no mutated key or index ({len(unnamed)}), e.g.:")
        for o in unnamed[:args.show]:
            print(f"  {o.case.describe()}: {o.message[:220]}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
