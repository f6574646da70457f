"""``hmrta train``, ``checkpoint`` and ``schedules``."""
from __future__ import annotations

import itertools
import json
import sys
from pathlib import Path

from .common import CONFIGS, UserError, _jobs, _positive, _seconds, _seed, writable
from .threads import check_threads
from .progress import _progress_on


def _interrupt_on(*signals: int) -> None:
    """These signals raise KeyboardInterrupt in the main thread, as a Ctrl-C does."""
    import signal

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    for s in signals:
        signal.signal(s, interrupt)


def cmd_train(args) -> int:
    import os

    from ..deps import require

    check_threads("--threads", args.threads)
    _jobs(args)
    # idle OpenMP threads sleep instead of spinning: read once, when torch loads its OpenMP runtime
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    torch = require("torch", "hmrta train")

    from ..rl.checkpoint_info import CheckpointError
    from ..rl.config import teacher_checkpoint
    from ..rl.train import Trainer, load_config, write_config

    if not Path(args.config).exists() and (CONFIGS / f"{args.config}.yaml").is_file():
        args.config = str(CONFIGS / f"{args.config}.yaml")  # a shipped config by its name
    elif not Path(args.config).exists():
        raise UserError(f"--config {args.config}: no such file, and no shipped config of that name (shipped: "
                        f"{', '.join(sorted(p.stem for p in CONFIGS.glob('*.yaml')))})")
    over = {k: v for k, v in (("max_minutes", args.max_minutes), ("iterations", args.iterations)) if v is not None}
    try:  # the command line's values replace the file's and are checked with them (also by --check)
        cfg = load_config(args.config, {"train": over},
                          ", ".join(f"--{k.replace('_', '-')} {v}" for k, v in over.items()))
    except ValueError as e:
        raise UserError(str(e)) from None
    given = cfg["pretrain"].get("schedules")  # the datasets it reads (a path or a list): before any run folder
    for f in [given] if isinstance(given, str) else list(given or []):
        if not Path(f).is_file():
            raise UserError(f"{args.config}: pretrain.schedules: {f}: no such file (a config's paths are relative "
                            f"to the working folder, {Path.cwd()}; the shipped configs' to the repository root)")
    teacher = teacher_checkpoint(cfg["pretrain"].get("teacher"))  # a checkpoint to distil: loaded before any run folder
    if teacher is not None and cfg["pretrain"].get("iterations"):
        from ..rl.inference import load_policy

        try:
            load_policy(teacher)
        except CheckpointError as e:
            raise UserError(f"{args.config}: pretrain.teacher: {e}") from None
    _train_device(torch, args.device)
    if (args.init or args.reseed) and not args.resume:
        raise UserError("--init and --reseed only apply with --resume")
    run_dir = writable("--run-dir", args.run_dir or f"runs/{cfg['name']}", folder=True)
    last = run_dir / "last.pt"
    if last.exists() and not args.resume:
        raise UserError(f"{run_dir} already holds a run: pass --resume to continue it or --run-dir for a new one")
    if args.init:  # a file, or a shipped checkpoint by its name (as every other command takes one)
        from ..rl.checkpoint_info import checkpoint_path, shipped_checkpoints

        init = checkpoint_path(args.init)
        if init.is_dir():
            raise UserError(f"--init {args.init}: is a folder, expected a checkpoint file")
        if not init.is_file():
            raise UserError(f"--init {args.init}: no such checkpoint file, and no shipped checkpoint of that name "
                            f"(shipped: {', '.join(sorted(shipped_checkpoints()))})")
        args.init = str(init)
    if args.export:  # never over what the run reads or writes (the checkpoints by their resolved paths)
        from ..rl.checkpoint_info import checkpoint_path

        reads = [args.config, *([args.init] if args.init else []),
                 *([str(checkpoint_path(teacher))] if teacher is not None else [])]
        writable("--export", args.export, inputs=tuple(reads))
        for own in ("last.pt", "best.pt", "config.yaml", "log.csv"):  # (the run's: they may not exist yet)
            if Path(args.export).resolve() == (run_dir / own).resolve():
                raise UserError(f"--export {args.export}: is the run's own {own}; export elsewhere")
    if args.resume and not args.init and not last.is_file():
        raise UserError(f"--resume: no checkpoint {last} to continue (start a new run without --resume, or give "
                        f"--init CHECKPOINT)")
    if args.check:  # the config, and the command line as it would run (the checkpoint it resumes included)
        print(f"{args.config}: a valid training config (name {cfg['name']!r})")
        if args.resume:
            import tempfile

            src = Path(args.init) if args.init else last
            with tempfile.TemporaryDirectory() as probe_dir:  # read as the run would, into a trainer thrown away
                Trainer(cfg, probe_dir, device=args.device, log=lambda s: None).load(
                    src, reseed=args.reseed, same_run=not args.init)
            print(f"{src}: a checkpoint this run can {'start from' if args.init else 'continue'}")
        return 0
    if args.threads:
        torch.set_num_threads(args.threads)
    import signal

    # stop at once; the trainer writes last.pt on the way out (the state after the latest finished
    # iteration: an exact resume); SIGINT also when started in the background (ignored there)
    _interrupt_on(signal.SIGTERM, signal.SIGINT)
    from tqdm import tqdm

    # log lines above the progress bar, not into it
    made = list(itertools.takewhile(lambda d: not d.exists(), [run_dir, *run_dir.parents]))  # innermost first
    try:
        tr = Trainer(cfg, run_dir, device=args.device, log=lambda s: tqdm.write(s, file=sys.stderr), jobs=args.jobs,
                     ray_address=args.ray_address)
        if args.resume:
            src = Path(args.init) if args.init else last
            tr.load(src, reseed=args.reseed, same_run=not args.init)
    except BaseException:  # (e.g. --init of another network): no empty run folder is left behind
        for d in made:
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
        raise
    if args.resume:
        print(f"resumed from {src}: iteration {tr.iteration}, {tr.episodes} episodes, cloning iteration "
              f"{tr.pretrain_done}, distillation iteration {tr.distill_done}", file=sys.stderr)
        changed = tr.changed_keys()
        if changed:
            print(f"this config differs from the checkpoint's ({len(changed)} setting(s); the run goes on under "
                  f"this config's and records it): " + "; ".join(changed), file=sys.stderr)
    write_config(cfg, run_dir / "config.yaml")
    print(f"training on {tr.device}; log {run_dir / 'log.csv'}", file=sys.stderr)
    try:
        res = tr.run(progress=_progress_on(args))
    except KeyboardInterrupt:
        if tr.saved_last:
            print(f"stopped: checkpoint saved to {last}: the state after the latest finished iteration "
                  f"(iteration {tr.saved_last['iteration']}, cloning {tr.saved_last['pretrain_done']}; --resume "
                  f"continues from there, the iteration under way is done again)", file=sys.stderr)
        else:
            print("stopped before the first iteration finished: no checkpoint written", file=sys.stderr)
        return 130
    from ..bench import clean

    if tr.stopped_by_time:
        print(f"stopped at the time limit ({cfg['train']['max_minutes']:g} min), the iterations not all done: "
              f"{last} holds the state (--resume continues)", file=sys.stderr)
    print(json.dumps(clean(res)))  # strict JSON: no score yet is null, not Infinity
    if args.export:
        from ..rl.checkpoint import export_run_checkpoint

        src = run_dir / "best.pt" if (run_dir / "best.pt").exists() else last
        which = export_run_checkpoint(src, args.export)
        print(f"exported the weights of {src} ({'the moving average' if which == 'ema' else which}) to "
              f"{args.export}", file=sys.stderr)
    return 0


def _train_device(torch, device: str | None) -> None:
    """``--device``: cpu, cuda or cuda:N, and a GPU that torch can use."""
    import re

    if device is None:
        return
    m = re.fullmatch(r"(cpu|cuda)(?::(\d+))?", device)
    if m is None:
        raise UserError(f"--device {device}: expected cpu, cuda or cuda:N")
    if m[1] == "cuda":
        if not torch.cuda.is_available():
            raise UserError(f"--device {device}: CUDA is not available (torch {torch.__version__} finds no usable "
                            f"GPU); use --device cpu")
        if m[2] is not None and int(m[2]) >= torch.cuda.device_count():
            raise UserError(f"--device {device}: no such GPU (torch finds {torch.cuda.device_count()})")


def cmd_checkpoint_info(args) -> int:
    import importlib.util

    from ..rl.checkpoint_info import CheckpointError, checkpoint_path, describe

    refused = None
    if importlib.util.find_spec("torch") is not None:  # what solve, bench, the agents and --resume would refuse, info refuses too
        from ..rl.checkpoint import COUNTERS, counter, load
        from ..rl.inference import load_policy

        path = checkpoint_path(args.checkpoint)
        try:
            load_policy(args.checkpoint)  # format, config, rules, weights (names, shapes, finite values)
            ck = load(path)
            for k in COUNTERS:
                counter(ck, k, path)
        except CheckpointError as e:
            refused = e  # shown after what can be read of the file (to diagnose it), then the exit status 2
    try:
        d = describe(args.checkpoint)
    except CheckpointError as e:  # unreadable: the loader's reason is the clearer one
        raise (refused or e) from None
    if args.json:
        print(json.dumps(d, indent=1, default=str))
    else:
        _print_checkpoint(d)
    if refused is not None:
        raise refused
    return 0


def _print_checkpoint(d: dict) -> None:
    from ..rl.checkpoint_info import lineage_lines

    cfg = d["config"]
    model = cfg.get("model") if isinstance(cfg.get("model"), dict) else {}
    rules = cfg.get("rules") if isinstance(cfg.get("rules"), dict) else {}
    print(d["path"])
    rows = [("sha256", d["sha256"]), ("format", d["format"]), ("code", d["code_version"] or "not recorded"),
            ("config", f"{cfg.get('name', '?')} (version {cfg.get('version', '?')}, seed {cfg.get('seed', '?')})"),
            ("weights", ", ".join(d["weights"]) or "none"),
            ("network", ", ".join(f"{k} {v}" for k, v in model.items() if k not in ("greedy_depot",))),
            ("greedy depot", model.get("greedy_depot", "argmax (default)")),
            ("rules", ", ".join(f"{k} {v}" for k, v in rules.items()) or "defaults")]
    counters = (("iteration", "iteration"), ("pretrain_done", "cloning"), ("distill_done", "distillation"),
                ("episodes", "episodes"), ("decisions", "decisions"), ("best_val", "best_val"))
    rows += [(label, d[k]) for k, label in counters if k in d]  # (cloning, distillation: iterations done)
    for k, v in rows:
        print(f"  {k:<13} {v}")
    if d["lineage"]:
        print("  lineage")
        for line in lineage_lines(d["lineage"]):
            print("    " + line)


def cmd_checkpoint(args) -> int:
    from ..deps import require

    require("torch", "hmrta checkpoint")
    from ..bench import file_sha256
    from ..rl.checkpoint import average
    from ..rl.checkpoint_info import checkpoint_path

    if args.window is not None and not all(1 <= n <= 100_000 for n in args.window):  # (ModelConfig's range)
        raise UserError(f"--window: expected TASKS ROBOTS, each an integer in [1, 100000], got "
                        f"{' '.join(map(str, args.window))}")
    out = writable("--out", args.out)
    if out.exists():
        for src in map(checkpoint_path, args.checkpoints):
            if src.exists() and out.samefile(src):
                raise UserError(f"--out {out}: is one of the checkpoints being averaged ({src}); write to a new "
                                f"file and move it into place")
        if not args.force:
            raise UserError(f"--out {out}: exists (pass --force to replace it)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"--out {out}: cannot create its folder ({e.strerror or e})") from None
    entry = average(args.checkpoints, out, window=args.window, greedy_depot=args.greedy_depot)
    if args.json:
        print(json.dumps({"out": str(out), **entry}))
    else:
        print(f"averaged {len(entry['sources'])} checkpoint(s) into {out} (sha256 {file_sha256(out)}; its "
              f"lineage: hmrta checkpoint info {out})")
    return 0


def cmd_schedules(args) -> int:
    from ..rl.schedules import ScheduleError, ScheduleSet, generate, make_generator

    _positive("--count", args.count)
    _seed(args.seed)
    if not args.min_tasks <= args.max_tasks or args.min_tasks < 1 or args.max_tasks > 200:
        raise UserError(f"--min-tasks/--max-tasks: expected 1 <= min <= max <= 200, got {args.min_tasks}..{args.max_tasks}")
    _seconds("--time-limit", args.time_limit)
    _jobs(args)
    _positive("--workers", args.workers)
    out = writable("--out", args.out)
    spec = {"kind": args.generator, "min_tasks": args.min_tasks, "max_tasks": args.max_tasks}
    if args.team_scale is not None and tuple(args.team_scale) != (1, 1):  # 1 1: the plain broad header
        spec["team_scale"] = list(args.team_scale)
        try:
            make_generator(spec)  # the header's own check
        except ScheduleError as e:
            raise UserError(f"--team-scale {args.team_scale[0]:g} {args.team_scale[1]:g} with --generator "
                            f"{args.generator}: {e}") from None
    import signal

    _interrupt_on(signal.SIGTERM)  # as Ctrl-C: every finished schedule is in the file already
    try:
        n = generate(out, spec, args.seed, args.count, args.time_limit, args.workers, args.jobs, args.ray_address,
                     progress=_progress_on(args))
    except KeyboardInterrupt:
        print(f"stopped: {out} holds the schedules solved so far; the same command resumes it", file=sys.stderr)
        return 130
    ss = ScheduleSet(out)
    mk = [r["makespan"] for r in ss.rows.values()]
    print(json.dumps({"out": str(out), "solved_now": n, "schedules": len(ss),
                      "mean_makespan": round(sum(mk) / len(mk), 4) if mk else None,
                      "bytes": out.stat().st_size}))
    return 0
