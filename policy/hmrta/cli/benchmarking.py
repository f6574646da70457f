"""``hmrta bench``: methods over mission sets, in the paper-table layout."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from .common import (BENCH_COUNT, BENCH_SEED, ROW_SIZES, UserError, _ctas_folder, _jobs, _plannable, _positive,
                     _resolve_instances, _row_sizes, _seed, writable)
from .progress import _progress_on
from .solving import _solve_opts


def cmd_bench(args) -> int:
    from .. import bench
    from ..generators import PAPER_ROWS

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods:
        raise UserError(f"--methods: expected a comma list of methods, got {args.methods!r}")
    from ..methods import METHODS, MethodError, check_options, options_for, parse

    for m in methods:
        parse(m)  # unknown method: user error before any work
    for k in _solve_opts(args):  # an option none of the methods takes is an error
        if not any(k in options_for(m, {k: 1}) for m in methods):
            takers = [n for n, rec in METHODS.items() if rec.option(k)]
            raise MethodError(f"--{k.replace('_', '-')}: none of the methods {', '.join(methods)} takes it "
                              f"(methods that do: {', '.join(takers)})")
    for m in methods:  # and a value out of range (a portfolio's candidates too), before the cache is written
        if check_options(m, options_for(m, _solve_opts(args))).get("candidates") is not None:
            from ..portfolio import candidate_methods

            candidate_methods(args.candidates)
    given = [x for x, on in (("INSTANCE", args.instances), ("--suite", args.suite), ("--scenario", args.scenario))
             if on]
    if len(given) > 1:
        raise UserError(f"bench: give your missions (INSTANCE...), --suite, or one --scenario row, not both "
                        f"{given[0]} and {given[1]}")
    if args.instances and (args.count is not None or args.seed is not None):
        raise UserError(f"{'--count' if args.count is not None else '--seed'}: only applies to generated rows "
                        f"(--suite, --scenario); your missions are benchmarked as they are")
    args.count = BENCH_COUNT if args.count is None else args.count
    args.seed = BENCH_SEED if args.seed is None else args.seed
    _positive("--count", args.count)
    _positive("--max-tasks", args.max_tasks)
    _seed(args.seed)
    if args.max_tasks is not None and not args.suite:
        raise UserError("--max-tasks: only applies with --suite (it skips the suite's larger rows)")
    if given and given[0] != "--scenario":  # the sizes of a generated row, beside missions or a suite
        row = next((f"--{k}" for k in ROW_SIZES if getattr(args, k) is not None), None)
        if row:
            raise UserError(f"{row}: only applies with --scenario (a generated row), not with {given[0]}")
    if args.out and Path(args.out).suffix.lower() in (".json", ".md", ".csv"):
        raise UserError(f"--out {args.out}: expected a folder (results.md, results.json and results.csv go in it)")
    try:
        compare = None if args.compare is None else [_pair(c) for c in args.compare]
        bench.comparison_pairs(methods, compare)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.instances:
        rows = _mission_sets(args.instances)
    elif args.suite == "families":
        from ..families import family_suite

        try:
            rows = family_suite(args.tables.split(",") if args.tables else None, args.max_tasks)
        except ValueError as e:
            raise UserError(f"--tables: {e}") from None
    elif args.suite:
        tables = args.tables.split(",") if args.tables else None
        if tables:
            bad = [t for t in tables if t not in PAPER_ROWS]
            if bad:
                raise UserError(f"--tables: unknown table {bad[0]!r} (expected {', '.join(PAPER_ROWS)})")
        rows = bench.paper_suite(tables)
        if args.max_tasks is not None:
            rows = [r for r in rows if r.tasks <= args.max_tasks]
    else:
        missing = [k for k in ("scenario", *ROW_SIZES) if getattr(args, k) is None]
        if missing:
            raise UserError(f"bench: give your missions (INSTANCE...), --suite paper or families, or all of "
                            f"--scenario --agents --species --tasks --skills (missing --{missing[0]})")
        _row_sizes(args)
        table = args.scenario
        try:  # every instance can be drawn (a team too small for the tasks cannot), before any work
            rows = [bench.Row(table, args.agents, args.species, args.tasks, args.skills)]
            drawn = rows[0].generator().generate(args.count, args.seed)
        except ValueError as e:
            raise UserError(str(e)) from None
        _plannable(methods, [(f"{rows[0].key} ({inst.name})", inst) for inst in drawn[:1]])  # one row: one size
    _plannable(methods, [(f"{row.name} ({inst.name})", inst) for row in rows if isinstance(row, bench.MissionSet)
                         for _, inst in row.instances(args.count, args.seed)])  # your missions, before any work
    if not rows:  # --max-tasks below every row of the suite
        raise UserError(f"--max-tasks {args.max_tasks}: every row of --suite {args.suite}"
                        f"{' --tables ' + args.tables if args.tables else ''} has more tasks")
    _jobs(args)
    if args.suite and not args.out:  # never the committed tables (docs/results/<suite>) unless asked for
        args.out = f"bench-{args.suite}"
    out_dir = writable("--out", args.out, folder=True) if args.out else None
    summary = bench.run_bench(rows, methods, args.count, args.seed, out_dir, _solve_opts(args),
                              progress=_progress_on(args), with_bounds=args.bounds,
                              log=lambda s: print(s, file=sys.stderr), compare=compare,
                              command=_command_line(args), workers=args.jobs, ray_address=args.ray_address)
    if args.json:
        print(json.dumps(bench.clean(summary), indent=1))
    else:
        print(bench.to_markdown(summary))
    if out_dir:
        written = bench.save(summary, out_dir)
        print(f"wrote {', '.join(map(str, written))}", file=sys.stderr)
    return 0


def _pair(text: str) -> tuple[str, str]:
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or not all(parts):
        raise ValueError(f"--compare {text}: expected two methods A,B (e.g. rl,greedy)")
    return parts[0], parts[1]


def _command_line(args) -> str:
    import shlex

    return "hmrta " + shlex.join(getattr(args, "argv", None) or [])


def _mission_sets(paths: list[str]) -> list:
    """Bench rows of user missions: one per folder of *.yaml, one for the files given singly."""
    from ..bench import MissionSet

    rows, singles = [], []
    for p in paths:
        pp = Path(p)
        if pp.is_dir() and not _ctas_folder(pp):
            rows.append(MissionSet.load(pp.resolve().name, _resolve_instances([p])))
        else:
            singles.append(pp)
    if singles:
        name = (singles[0].resolve().name if singles[0].is_dir() else singles[0].stem) if len(singles) == 1 \
            else "missions"
        rows.append(MissionSet.load(name, singles))
    seen: dict[Path, Path] = {}
    for f in (f for r in rows for f in r.files):  # a mission given twice would count twice
        if f.resolve() in seen:
            also = "" if seen[f.resolve()] == f else f" (also as {seen[f.resolve()]})"
            raise UserError(f"{f}: given twice{also}: its results would count twice")
        seen[f.resolve()] = f
    return rows
