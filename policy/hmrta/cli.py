"""The ``hmrta`` command line.

User errors (bad files, options, checkpoints) exit 2 with a one-line message on stderr; internal
errors exit 1 with a traceback.
"""
from __future__ import annotations

import argparse
import json
import sys
import traceback
from pathlib import Path

from . import __version__

EXAMPLE = Path(__file__).resolve().parent / "data" / "example.yaml"


class UserError(Exception):
    pass


def _user_errors() -> tuple[type[BaseException], ...]:
    from .instance import InstanceError
    from .methods import MethodError
    from .solution import RouteError

    errs: list[type[BaseException]] = [UserError, InstanceError, RouteError, MethodError]
    try:
        from .rl.inference import CheckpointError

        errs.append(CheckpointError)
    except ImportError:  # torch missing: rl methods unavailable
        pass
    return tuple(errs)


def _load(path: str):
    from .instance import load_instance

    return load_instance(path)


def _resolve_instances(paths: list[str]) -> list[Path]:
    out: list[Path] = []
    for p in paths:
        pp = Path(p)
        if pp.is_dir() and not (pp / "config.json").exists():
            files = sorted([*pp.glob("*.yaml"), *pp.glob("*.yml")])
            if not files:
                raise UserError(f"{pp}: folder has no instance files (*.yaml) and no config.json")
            out += files
        else:
            out.append(pp)
    return out


def _solve_opts(args) -> dict:
    opts = {}
    for k in ("checkpoint", "time_limit", "warm_start", "samples", "workers"):
        v = getattr(args, k, None)
        if v is not None:
            opts[k] = v
    return opts


# ---------------------------------------------------------------------------------------------
def cmd_solve(args) -> int:
    from .methods import solve
    from tqdm import tqdm

    files = _resolve_instances(args.instances)
    method = args.method
    if args.samples and method == "rl-sample":
        method = f"rl-s{args.samples}"
    out = Path(args.out) if args.out else None
    many = len(files) > 1
    if many and out and out.suffix == ".json":
        raise UserError(f"--out {out}: with several instances, --out must be a folder")
    sols = []
    for f in tqdm(files, desc="solve", disable=len(files) < 5 or args.json, unit="instance"):
        inst = _load(str(f))
        sol = solve(inst, method, seed=args.seed, **_solve_opts(args))
        sols.append(sol)
        if out:
            target = out / f"{f.stem}.json" if (many or out.is_dir() or out.suffix != ".json") else out
            sol.save(target)
        if not args.json:
            print(sol.summary())
            if args.schedule:
                print(schedule_text(inst, sol))
    if args.json:
        data = [s.to_dict() for s in sols]
        print(json.dumps(data[0] if len(data) == 1 else data, indent=1))
    return 0 if all(s.success for s in sols) else 3


def schedule_text(inst, sol) -> str:
    lines = [f"  {'task':>4}  {'start':>8}  {'finish':>8}  members"]
    for m, t in sorted(enumerate(sol.tasks), key=lambda x: (x[1]["start"] is None, x[1]["start"] or 0)):
        if t["start"] is None or t["start"] != t["start"]:
            lines.append(f"  {m:>4}  {'—':>8}  {'—':>8}  (not done)")
        else:
            lines.append(f"  {m:>4}  {t['start']:8.2f}  {t['finish']:8.2f}  {t['members']}")
    lines.append(f"  {'agent':>5}  species  return  route")
    for a, (info, r) in enumerate(zip(sol.agents, sol.routes)):
        rt = info["return_time"]
        lines.append(f"  {a:>5}  {info['species']:>7}  {rt:6.2f}  {r}")
    return "\n".join(lines)


def cmd_evaluate(args) -> int:
    from .solution import evaluate_routes, parse_routes

    inst = _load(args.instance)
    try:
        data = json.loads(Path(args.routes).read_text())
    except FileNotFoundError:
        raise UserError(f"{args.routes}: no such file") from None
    except json.JSONDecodeError as e:
        raise UserError(f"{args.routes}:{e.lineno}: invalid JSON ({e.msg})") from None
    routes = parse_routes(inst, data, args.routes)
    sol = evaluate_routes(inst, routes)
    if args.json:
        print(json.dumps(sol.to_dict(), indent=1))
    else:
        print(f"{inst.name}: makespan {sol.makespan:.6f}  AWT {sol.awt:.6f}  redundancy {sol.redundancy:.6f}")
    return 0


def cmd_generate(args) -> int:
    from .generators import ScenarioGenerator, index_width
    from .instance import Instance

    try:
        gen = ScenarioGenerator(args.scenario, args.agents, args.species, args.tasks, args.skills)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.count < 1:
        raise UserError(f"--count: expected a positive integer, got {args.count}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    width = index_width(args.count)
    name = f"{gen.name}_s{args.seed}"
    for i, inst in enumerate(gen.generate(args.count, args.seed)):
        inst.save(out / f"{name}_{str(i).zfill(width)}.yaml")
    print(f"wrote {args.count} instances to {out}/{name}_*.yaml")
    return 0


def cmd_convert(args) -> int:
    inst = _load(args.input)
    inst.save(args.output)
    print(f"wrote {args.output} ({inst.n_agents} agents in {inst.n_species} species, {inst.n_tasks} tasks)")
    return 0


def cmd_bench(args) -> int:
    from . import bench
    from .generators import PAPER_ROWS

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    from .methods import get, parse

    for m in methods:
        get(parse(m)[0])  # unknown method: user error before any work
    if args.suite:
        tables = args.tables.split(",") if args.tables else None
        if tables:
            bad = [t for t in tables if t not in PAPER_ROWS]
            if bad:
                raise UserError(f"--tables: unknown table {bad[0]!r} (expected {', '.join(PAPER_ROWS)})")
        rows = bench.paper_suite(tables)
        if args.max_tasks:
            rows = [r for r in rows if r.tasks <= args.max_tasks]
    else:
        missing = [k for k in ("scenario", "agents", "species", "tasks", "skills") if getattr(args, k) is None]
        if missing:
            raise UserError(f"bench: give --suite paper, or all of --scenario --agents --species --tasks --skills "
                            f"(missing --{missing[0]})")
        table = args.scenario
        try:
            rows = [bench.Row(table, args.agents, args.species, args.tasks, args.skills)]
            rows[0].generator()
        except ValueError as e:
            raise UserError(str(e)) from None
    if args.suite and not args.out_dir:
        args.out_dir = f"docs/results/{args.suite}"  # the suite's tables live in docs/results/
    out_dir = Path(args.out_dir) if args.out_dir else None
    summary = bench.run_bench(rows, methods, args.count, args.seed, out_dir, _solve_opts(args),
                              progress=not args.no_progress, with_bounds=args.bounds,
                              log=lambda s: print(s, file=sys.stderr))
    md = bench.to_markdown(summary)
    print(md)
    json_path = Path(args.json) if args.json else (out_dir / "results.json" if out_dir else None)
    md_path = Path(args.markdown) if args.markdown else (out_dir / "results.md" if out_dir else None)
    bench.save(summary, md, json_path, md_path)
    return 0


def cmd_train(args) -> int:
    import torch

    from .rl.train import Trainer, load_config, write_config

    try:
        cfg = load_config(args.config)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.max_minutes is not None:
        cfg["train"]["max_minutes"] = args.max_minutes
    if args.iterations is not None:
        cfg["train"]["iterations"] = args.iterations
    if (args.init or args.reseed) and not args.resume:
        raise UserError("--init and --reseed only apply with --resume")
    run_dir = Path(args.run_dir or f"runs/{cfg['name']}")
    last = run_dir / "last.pt"
    if last.exists() and not args.resume:
        raise UserError(f"{run_dir} already holds a run: pass --resume to continue it or --run-dir for a new one")
    if args.threads:
        torch.set_num_threads(args.threads)
    import signal

    def _stop(signum, frame):  # SIGTERM / SIGINT: stop at once, the trainer saves last.pt on the way out
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)  # also when started in the background (SIGINT ignored there)
    tr = Trainer(cfg, run_dir, device=args.device, log=lambda s: print(s, file=sys.stderr))
    if args.resume:
        src = Path(args.init) if args.init else last
        if src.exists():
            tr.load(src, reseed=args.reseed)
            print(f"resumed from {src}: iteration {tr.iteration}, {tr.episodes} episodes", file=sys.stderr)
        else:
            print(f"nothing to resume in {run_dir}: starting fresh", file=sys.stderr)
    write_config(cfg, run_dir / "config.yaml")
    print(f"training on {tr.device}; log {run_dir / 'log.csv'}", file=sys.stderr)
    try:
        res = tr.run(progress=not args.no_progress)
    except KeyboardInterrupt:
        print(f"stopped: checkpoint saved to {last} (continue with --resume)", file=sys.stderr)
        return 130
    print(json.dumps(res))
    if args.export:
        best = run_dir / "best.pt"
        if best.exists():
            tr.load(best)
        tr.export(Path(args.export))
        print(f"exported {'best' if best.exists() else 'last'} weights to {args.export}", file=sys.stderr)
    return 0


def cmd_bound(args) -> int:
    from .bounds import bound_report, format_report

    inst = _load(args.instance)
    sols = [_read_solution(p) for p in args.solutions]
    if args.time_limit:
        from .methods import solve

        sols.append(solve(inst, "cpsat", seed=0, time_limit=args.time_limit))
    rep = bound_report(inst, sols)
    print(json.dumps(rep, indent=1) if args.json else format_report(rep))
    return 0


def _read_solution(path: str):
    from .solution import Solution

    try:
        return Solution.from_dict(json.loads(Path(path).read_text()))
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise UserError(f"{path}: not an hmrta-solution/1 file ({type(e).__name__}: {e})") from None


def cmd_render(args) -> int:
    from .render import render

    inst = _load(args.instance)
    sol = _read_solution(args.solution)
    try:
        written = render(inst, sol, args.out, gif=args.gif, frames=args.frames, fps=args.fps)
    except ValueError as e:
        raise UserError(f"{args.solution}: {e}") from None
    for w in written if isinstance(written, (list, tuple)) else [args.out]:
        print(f"wrote {w}")
    return 0


def cmd_demo(args) -> int:
    from .methods import solve

    inst = _load(args.instance or str(EXAMPLE))
    print(f"mission {inst.name}: {inst.n_agents} robots in {inst.n_species} species, {inst.n_tasks} tasks, "
          f"{inst.requirement_type} requirements")
    sol = solve(inst, args.method, seed=args.seed)
    print(sol.summary())
    print(schedule_text(inst, sol))
    if args.out:
        sol.save(args.out)
        print(f"wrote {args.out}")
    return 0 if sol.success else 3


# ---------------------------------------------------------------------------------------------
def _row_args(p: argparse.ArgumentParser, required: bool) -> None:
    """--scenario --agents --species --tasks --skills (one scenario row)."""
    from .generators import SCENARIOS

    pre = "" if required else "single row: "
    p.add_argument("--scenario", required=required, choices=SCENARIOS, default=None,
                   help=pre + "trait kind (SA single-skill / MA multi-skill) x requirement kind (AT additive / BT binary)")
    p.add_argument("--agents", type=int, required=required, default=None,
                   help=pre + "number of agents (a multiple of --species)")
    p.add_argument("--species", type=int, required=required, default=None, help=pre + "number of species")
    p.add_argument("--tasks", type=int, required=required, default=None, help=pre + "number of tasks")
    p.add_argument("--skills", type=int, required=required, default=None, help=pre + "number of skills K")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="hmrta",
        description="Heterogeneous multi-robot task allocation: instances, simulator, baselines, learned policy.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--version", action="version", version=f"hmrta {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    F = argparse.ArgumentDefaultsHelpFormatter
    methods_help = ("method: greedy (nearest task) | greedy-coalition (task whose coalition can start first) | "
                    "random | rl (learned policy, greedy decoding) | rl-sample / rl-sN "
                    "(N sampled rollouts, best kept) | rl-lookahead (one-step lookahead over the policy's greedy "
                    "continuations at every decision: slower, better) | cpsat (CP-SAT solver)")

    s = sub.add_parser("solve", help="solve instances and write hmrta-solution/1 JSON", formatter_class=F)
    s.add_argument("instances", nargs="+", metavar="INSTANCE",
                   help="instance YAML, CTAS-D config.json (or its folder), or a folder of *.yaml")
    s.add_argument("--method", default="greedy", help=methods_help)
    s.add_argument("--seed", type=int, default=0, help="episode seed (decision order, sampling)")
    s.add_argument("--samples", type=int, default=None, help="rollouts for --method rl-sample (default 10)")
    s.add_argument("--checkpoint", default=None, help="policy checkpoint (default: the shipped one)")
    s.add_argument("--time-limit", type=float, default=None, help="cpsat: seconds per instance (default 60)")
    s.add_argument("--warm-start", choices=["greedy", "rl"], default=None, help="cpsat: warm start")
    s.add_argument("--workers", type=int, default=None, help="cpsat: parallel workers (default 2)")
    s.add_argument("--out", default=None, help="solution file (one instance) or folder (DIR/<stem>.json)")
    s.add_argument("--json", action="store_true", help="print the solution JSON instead of a summary")
    s.add_argument("--schedule", action="store_true", help="also print the per-task schedule and routes")
    s.set_defaults(fn=cmd_solve)

    e = sub.add_parser("evaluate", help="re-simulate given routes and print the metrics", formatter_class=F)
    e.add_argument("instance", help="instance file")
    e.add_argument("routes", help="JSON object with a 'routes' key: per agent (species-major) the task ids in order")
    e.add_argument("--json", action="store_true", help="print the re-evaluated solution as JSON")
    e.set_defaults(fn=cmd_evaluate)

    g = sub.add_parser("generate", help="write a seeded set of scenario instances", formatter_class=F)
    _row_args(g, required=True)
    g.add_argument("--count", type=int, default=50, help="instances to write")
    g.add_argument("--seed", type=int, default=0, help="set seed (instance i uses rng([seed, i]))")
    g.add_argument("--out", required=True, help="output folder (DIR/<name>_<index>.yaml)")
    g.set_defaults(fn=cmd_generate)

    c = sub.add_parser("convert", help="convert a CTAS-D config.json (or any instance) to hmrta-instance/1 YAML",
                       formatter_class=F)
    c.add_argument("input", help="config.json, its folder, or an instance YAML")
    c.add_argument("-o", "--output", required=True, help="output YAML path")
    c.set_defaults(fn=cmd_convert)

    b = sub.add_parser("bench", help="paper-style tables: our methods beside the paper's numbers", formatter_class=F)
    b.add_argument("--suite", choices=["paper"], default=None, help="every paper row (Tables I-IV)")
    b.add_argument("--tables", default=None, help="with --suite: comma list of SA-BT,SA-AT,MA-AT,MA-AT-large")
    b.add_argument("--max-tasks", type=int, default=None, help="with --suite: skip rows with more tasks")
    _row_args(b, required=False)
    b.add_argument("--count", type=int, default=50, help="instances per row")
    b.add_argument("--seed", type=int, default=1000, help="test-set seed (never used in training/validation)")
    b.add_argument("--methods", default="greedy", help="comma list, e.g. greedy,greedy-coalition,rl,rl-s10,cpsat")
    b.add_argument("--checkpoint", default=None, help="policy checkpoint for rl methods")
    b.add_argument("--time-limit", type=float, default=None, help="cpsat seconds per instance")
    b.add_argument("--bounds", action="store_true", help="also report each method's gap to the best lower bound")
    b.add_argument("--out-dir", default=None,
                   help="write results.md/results.json and a resumable cache here (--suite default: docs/results/<suite>)")
    b.add_argument("--json", default=None, help="save the tables as JSON to this file")
    b.add_argument("--markdown", default=None, help="save the Markdown tables to this file")
    b.add_argument("--no-progress", action="store_true", help="no progress bar")
    b.set_defaults(fn=cmd_bench)

    t = sub.add_parser("train", help="train the policy (REINFORCE + constrained flashforward)", formatter_class=F)
    t.add_argument("--config", default="policy/configs/default.yaml", help="training config YAML")
    t.add_argument("--resume", action="store_true", help="continue the run in --run-dir (model, optimiser, RNG)")
    t.add_argument("--init", default=None, help="with --resume: start from this checkpoint instead of last.pt")
    t.add_argument("--reseed", action="store_true",
                   help="with --resume: draw fresh random streams from the config's seed and forget the "
                        "checkpoint's best validation score (an independent continuation, e.g. under other rules)")
    t.add_argument("--run-dir", default=None, help="run folder (default runs/<config name>)")
    t.add_argument("--max-minutes", type=float, default=None, help="stop after this many minutes (checkpointed)")
    t.add_argument("--iterations", type=int, default=None, help="override train.iterations")
    t.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    t.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    t.add_argument("--export", default=None, help="after training, write the best weights + config here")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.set_defaults(fn=cmd_train)

    lb = sub.add_parser("bound", help="lower bounds on the makespan (and the gap of given solutions)",
                        formatter_class=F)
    lb.add_argument("instance", help="instance file")
    lb.add_argument("solutions", nargs="*", metavar="SOLUTION", help="solution JSON files to report gaps for")
    lb.add_argument("--time-limit", type=float, default=None, help="also run CP-SAT this long; its bound counts")
    lb.add_argument("--json", action="store_true", help="print JSON")
    lb.set_defaults(fn=cmd_bound)

    r = sub.add_parser("render", help="draw the routes map and a Gantt chart of a solution", formatter_class=F)
    r.add_argument("instance", help="instance file")
    r.add_argument("solution", help="hmrta-solution/1 JSON")
    r.add_argument("--out", required=True, help="output image (.png); an --out ending in .gif writes only the animation")
    r.add_argument("--gif", action="store_true", help="also write an animated GIF beside the PNG")
    r.add_argument("--frames", type=int, default=80, help="GIF frames")
    r.add_argument("--fps", type=int, default=10, help="GIF frames per second")
    r.set_defaults(fn=cmd_render)

    d = sub.add_parser("demo", help="solve the built-in example mission and print its schedule", formatter_class=F)
    d.add_argument("--instance", default=None, help="another instance instead of the built-in example")
    d.add_argument("--method", default="greedy", help=methods_help)
    d.add_argument("--seed", type=int, default=0, help="episode seed")
    d.add_argument("--out", default=None, help="also write the solution JSON here")
    d.set_defaults(fn=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.fn(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as e:  # noqa: BLE001
        if isinstance(e, _user_errors()):
            print(f"hmrta: error: {e}", file=sys.stderr)
            return 2
        traceback.print_exc()
        print(f"hmrta: internal error: {type(e).__name__}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
