"""``hmrta solve``, ``evaluate`` and ``demo``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from .common import (EXAMPLE, UserError, _load, _matching, _not_an_input, _plannable, _resolve_instances, _seed,
                     _with_scenario_missions, writable)
from .progress import SolveProgress, _progress_on


def _solve_opts(args) -> dict:
    from ..methods import options_from_args

    return options_from_args(args)


# ---------------------------------------------------------------------------------------------
def cmd_solve(args) -> int:
    from ..methods import keep_best_on_interrupt, solve
    from tqdm import tqdm

    _seed(args.seed)
    files = _resolve_instances(args.instances)
    method = args.method
    out = Path(args.out) if args.out else None
    many = len(files) > 1
    if many and out and out.suffix and not out.is_dir():
        raise UserError(f"--out {out}: with several instances, --out must be a folder")
    # one mission: a file unless --out is a folder or a name without a suffix (out.json, out.txt: files)
    to_folder = bool(out) and (many or out.is_dir() or not out.suffix or args.out.endswith(("/", "\\")))
    inputs = _with_scenario_missions(files) if out else ()
    if out:
        writable("--out", out, folder=to_folder, inputs=inputs)
    if to_folder:  # DIR/<stem>.json is none of the inputs either
        for f in files:
            _not_an_input("--out", out / f"{f.stem}.json", inputs)
    if to_folder:  # DIR/<stem>.json: two inputs of one stem would overwrite each other
        by_stem: dict[str, Path] = {}
        for f in files:
            if f.stem in by_stem:
                raise UserError(f"--out {out}: {by_stem[f.stem]} and {f} would both be written to "
                                f"{out / f'{f.stem}.json'} (rename one, or solve them into separate folders)")
            by_stem[f.stem] = f
    insts = [_load(str(f)) for f in files]  # every input is read before anything is solved or written
    _plannable([method], [(str(f), inst) for f, inst in zip(files, insts)])  # ... and can be planned
    sols = []
    for f, inst in tqdm(list(zip(files, insts)), desc="solve", disable=not many or not _progress_on(args),
                        unit="instance", file=sys.stderr, delay=SolveProgress.DELAY):
        # an anytime method stopped by a Ctrl-C keeps the best it found (written, then exit 130)
        with SolveProgress(f"{method} {inst.name}", _progress_on(args)) as prog, keep_best_on_interrupt():
            sol = solve(inst, method, seed=args.seed, progress=prog, **_solve_opts(args))
        sols.append(sol)
        if out:
            sol.save(out / f"{f.stem}.json" if to_folder else out)
        if not args.json:  # (above the progress bar, not on its line)
            tqdm.write(sol.summary())
            if args.schedule:
                tqdm.write(schedule_text(inst, sol))
        if sol.extra.get("interrupted"):
            where = f"; written to {out / f'{f.stem}.json' if to_folder else out}" if out else ""
            print(f"interrupted: {inst.name}: the best schedule found in {sol.compute_seconds:.1f} s{where}"
                  + (f"; {len(files) - len(sols)} mission(s) not solved" if len(sols) < len(files) else ""),
                  file=sys.stderr)
            break
    if args.json:  # one object for one mission, a list for several (however many were solved)
        data = [s.to_dict() for s in sols]
        print(json.dumps(data[0] if len(files) == 1 else data, indent=1))
    if any(s.extra.get("interrupted") for s in sols):
        return 130
    return 0 if all(s.success for s in sols) else 3


def _event_notes(sol) -> tuple[dict[int, str], dict[int, str]]:
    """({task: why it was not done}, {robot: when it was lost}) from a dynamic solution's events."""
    dyn = sol.extra.get("dynamic") if isinstance(sol.extra, dict) else None
    if not isinstance(dyn, dict):
        return {}, {}
    names = dyn.get("names") or []
    tasks, robots = {}, {}
    for e in dyn.get("events") or []:
        if not isinstance(e, dict) or "rejected" in e:
            continue
        if e.get("type") == "cancel_task":
            m = names.index(e["name"]) if e.get("name") is not None and e["name"] in names else e.get("task")
            if isinstance(m, int):
                tasks[m] = f"cancelled at {e['t']:.2f}"
        elif e.get("type") in ("drop_agent", "release"):
            for m in e.get("cancelled") or []:
                tasks[int(m)] = f"cancelled at {e['t']:.2f}: no longer satisfiable"
            if e.get("type") == "drop_agent" and isinstance(e.get("agent"), int):
                robots[e["agent"]] = f"lost {e['t']:.2f}"
    return tasks, robots


def schedule_text(inst, sol) -> str:
    why, lost = _event_notes(sol)
    lines = [f"  {'task':>4}  {'start':>8}  {'finish':>8}  members"]
    for m, t in sorted(enumerate(sol.tasks), key=lambda x: (x[1]["start"] is None, x[1]["start"] or 0)):
        if t["start"] is None or t["start"] != t["start"]:
            lines.append(f"  {m:>4}  {'—':>8}  {'—':>8}  ({why.get(m, 'not done')})")
        else:
            lines.append(f"  {m:>4}  {t['start']:8.2f}  {t['finish']:8.2f}  {t['members']}")
    lines.append(f"  {'agent':>5}  species  return  route")
    for a, (info, r) in enumerate(zip(sol.agents, sol.routes)):
        rt = info["return_time"]
        ret = lost.get(a) or (f"{rt:6.2f}" if isinstance(rt, (int, float)) and rt == rt else f"{'—':>6}")
        lines.append(f"  {a:>5}  {info['species']:>7}  {ret:>6}  {r}")
    return "\n".join(lines)


def _evaluated(inst, routes, path):
    """The routes read from ``path`` re-simulated on ``inst``; a RouteError (e.g. a deadlock)
    names the file."""
    from ..solution import RouteError, evaluate_routes

    try:
        return evaluate_routes(inst, routes)
    except RouteError as e:
        raise RouteError(f"{path}: {e}") from None


def cmd_evaluate(args) -> int:
    from ..solution import read_routes

    files = _resolve_instances([args.instance])
    routes_arg = Path(args.routes)
    if len(files) > 1 and not routes_arg.is_dir():
        raise UserError(f"{routes_arg}: with a folder of instances, expected a folder of <instance stem>.json routes")
    sols = []
    for f in files:
        inst = _load(str(f), "evaluate re-simulates routes on a mission without events or release times")
        path = _matching(routes_arg, f, "routes") if routes_arg.is_dir() else routes_arg
        routes = read_routes(inst, path)  # RouteError naming the file (unreadable, not UTF-8, bad JSON, bad ids)
        sol = _evaluated(inst, routes, path)
        sols.append(sol)
        if not args.json:
            print(f"{inst.name}: makespan {sol.makespan:.6f}  AWT {sol.awt:.6f}  redundancy {sol.redundancy:.6f}")
    if args.json:
        data = [s.to_dict() for s in sols]
        print(json.dumps(data[0] if len(data) == 1 else data, indent=1))
    return 0


def cmd_demo(args) -> int:
    from ..methods import solve

    _seed(args.seed)
    if args.out:
        writable("--out", args.out)
    inst = _load(args.instance or str(EXAMPLE))
    _plannable([args.method], [(str(args.instance or EXAMPLE), inst)])  # before anything is printed
    print(f"mission {inst.name}: {inst.n_agents} robots in {inst.n_species} species, {inst.n_tasks} tasks, "
          f"{inst.requirement_type} requirements")
    with SolveProgress(args.method, _progress_on(args)) as prog:
        sol = solve(inst, args.method, seed=args.seed, progress=prog, **_solve_opts(args))
    print(sol.summary())
    print(schedule_text(inst, sol))
    if args.out:
        sol.save(args.out)
        print(f"wrote {args.out}")
    return 0 if sol.success else 3
