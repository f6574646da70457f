"""``hmrta bound`` and ``render``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from .common import UserError, _load, _matching, _resolve_instances, _seconds, writable
from .progress import SolveProgress, _progress_on
from .solving import _evaluated


def cmd_bound(args) -> int:
    from ..bounds import bound_report, format_report
    from ..solution import check_planned_for, check_solution

    from tqdm import tqdm

    _seconds("--time-limit", args.time_limit)
    files = _resolve_instances([args.instance])
    many = len(files) > 1
    sol_args = [Path(p) for p in args.solutions]
    if many:
        loose = [p for p in sol_args if not p.is_dir()]
        if loose:
            raise UserError(f"{loose[0]}: with a folder of instances, expected a folder of <instance stem>.json "
                            f"solutions")
    work = []  # every instance and solution is read and checked before any bound is computed or printed
    for f in files:
        # release times only delay tasks (the "release" bound takes them into account)
        inst = _load(str(f), "the bounds hold for a mission without events", releases=True)
        sols = []
        for p in sol_args:
            path = str(_matching(p, f, "solution") if p.is_dir() else p)
            sols.append(_solution_or_routes(inst, path))
            check_planned_for(inst, sols[-1], path)  # a solution of another instance has no gap here
            check_solution(inst, sols[-1], path)
        if args.time_limit is not None and inst.dynamic:  # (checked before any CP-SAT run)
            raise UserError(f"--time-limit: {f}: CP-SAT plans a mission known at the start, and this one "
                            f"has tasks released later; run without --time-limit "
                            f"for its other bounds")
        work.append((inst, sols))
    reports = []
    for inst, sols in tqdm(work, desc="bound", disable=not many or not _progress_on(args), unit="instance",
                           file=sys.stderr, delay=SolveProgress.DELAY):
        if args.time_limit is not None:
            from ..methods import solve

            with SolveProgress(f"cpsat {inst.name}", _progress_on(args)) as prog:
                sols.append(solve(inst, "cpsat", seed=0, progress=prog, time_limit=args.time_limit))
        rep = bound_report(inst, sols)
        reports.append(rep)
        if not args.json:
            print(format_report(rep))
    if args.json:
        print(json.dumps(reports[0] if len(reports) == 1 else reports, indent=1))
    return 0


def _read_solution(path: str):
    from ..solution import read_solution

    return read_solution(path)


def _solution_or_routes(inst, path: str):
    """An ``hmrta-solution/1`` file, or a routes file as ``hmrta evaluate`` takes it (then
    re-simulated on ``inst``): an object with ``routes`` and no ``format``. Anything else is read
    as a solution, and its error is the solution reader's: a damaged solution file (a wrong
    ``format``, a makespan that is not one) is refused, never re-simulated from its routes."""
    from ..solution import SolutionError, read_routes

    try:
        return _read_solution(path)
    except SolutionError:
        if not _looks_like_routes(path):
            raise
    routes = read_routes(inst, path)
    if inst.dynamic or bool((inst.releases > 0).any()):
        raise UserError(f"{path}: routes are re-simulated without release times or events (as hmrta evaluate "
                        f"does), which this mission has: give its solution file (hmrta solve --out)")
    return _evaluated(inst, routes, path)


def _looks_like_routes(path: str) -> bool:
    """A JSON object with ``routes`` and no ``format``: a routes file (``hmrta evaluate``'s input)."""
    from ..reading import InputError, read_json

    try:
        d = read_json(path)
    except InputError:  # unreadable or not JSON: the solution reader's error says so
        return False
    return isinstance(d, dict) and "routes" in d and "format" not in d


def _begins(grown, inst) -> bool:
    """Whether the mission ``grown`` is ``inst``, or ``inst`` with robots that joined it (the mission
    a board publishes once robots have joined: more ``added_agents``, and a species of no robot of
    its own for each new kind; the tasks are the mission's own)."""
    a, b = inst.to_dict(), grown.to_dict()
    rest = (set(a) | set(b)) - {"species", "added_agents"}
    n = len(a["species"])
    joined = b.get("added_agents", [])
    return (all(a.get(k) == b.get(k) for k in rest) and b["species"][:n] == a["species"]
            and all(s["count"] == 0 for s in b["species"][n:])
            and joined[:len(a.get("added_agents", []))] == a.get("added_agents", []))


def cmd_render_recording(args) -> int:
    """``hmrta render [INSTANCE] --from FILE.mcap --out fig.png``: the executed mission."""
    from ..replay import ReplayError, read_recording, render_recording, summary
    from ..solution import check_solution

    if args.solution is not None:
        raise UserError("render --from: give the recording and (optionally) the instance, not a solution file")
    if args.gif:
        raise UserError("render --from: --gif is not available for recordings")
    writable("--out", args.out, inputs=tuple(x for x in (args.from_, args.instance) if x))
    try:
        rec = read_recording(args.from_)
    except ReplayError as e:
        raise UserError(str(e)) from None
    if args.instance is not None:  # the recorded mission must be this instance (robots may have joined it)
        inst, started = _load(args.instance), rec.recorded or rec.instance
        if not _begins(started, inst):
            raise UserError(f"{args.from_}: the recorded mission ({started.name}, {started.n_agents} robots, "
                            f"{started.n_tasks} tasks) is not the instance {args.instance} ({inst.name})")
    if rec.plan is not None:
        check_solution(rec.instance, rec.plan, f"{args.from_} (recorded {rec.plan_source})")
    try:
        out = render_recording(rec, args.out)
    except ValueError as e:  # e.g. an image format matplotlib cannot write
        raise UserError(f"--out {args.out}: {' '.join(str(e).splitlines())}") from None
    print(summary(rec).splitlines()[0])
    print(f"wrote {out}")
    return 0


def cmd_render(args) -> int:
    from ..deps import require
    from ..render import check_gif_options, render
    from ..solution import SolutionError, check_planned_for, final_instance

    if args.from_ is not None:
        return cmd_render_recording(args)
    if args.instance is None or args.solution is None:
        raise UserError("render: give INSTANCE and SOLUTION (or --from FILE.mcap, a recorded mission)")
    require("matplotlib", "hmrta render")  # before anything is read
    try:  # before anything is read or drawn, also for a PNG only
        check_gif_options(args.frames, args.fps)
    except ValueError as e:
        raise UserError(f"--{e}") from None
    writable("--out", args.out, inputs=(args.instance, args.solution))
    inst = _load(args.instance)
    sol = _solution_or_routes(inst, args.solution)  # (routes: re-simulated, as hmrta evaluate and bound take them)
    check_planned_for(inst, sol, args.solution)
    animated = args.gif or Path(args.out).suffix.lower() == ".gif"
    if animated and _progress_on(args):  # a GIF: 0.05 to 0.3 s per frame
        from tqdm import tqdm

        bar = tqdm(total=args.frames, desc="render GIF", unit="frame", file=sys.stderr, leave=False,
                   delay=SolveProgress.DELAY)
    else:
        bar = None
    try:  # render() first checks that the solution belongs to the instance (SolutionError naming the file)
        # a mission that grew while it ran (tasks added, robots joining) is drawn as it ended
        written = render(final_instance(inst, sol, args.solution), sol, args.out, gif=args.gif, frames=args.frames,
                         fps=args.fps, source=args.solution,
                         progress=None if bar is None else lambda i, n: bar.update(i - bar.n))
    except SolutionError:
        raise
    except ValueError as e:  # e.g. an image format matplotlib cannot write
        raise UserError(f"--out {args.out}: {' '.join(str(e).splitlines())}") from None
    finally:
        if bar is not None:
            bar.close()
    for w in written if isinstance(written, (list, tuple)) else [args.out]:
        print(f"wrote {w}")
    return 0
