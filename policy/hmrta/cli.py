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
CONFIGS = Path(__file__).resolve().parent / "configs"  # the training configs (policy/configs), shipped with the package
INSTANCE_HELP = "instance YAML, CTAS-D config.json (or its folder), or a folder of *.yaml"


class UserError(Exception):
    pass


def _positive(flag: str, value: int | None) -> None:
    """UserError naming ``flag`` unless ``value`` (None: not given) is a positive integer."""
    if value is not None and value < 1:
        raise UserError(f"{flag}: expected a positive integer, got {value}")


def _jobs(args) -> None:
    """--jobs N: a positive integer and, on a local Ray (no --ray-address: a cluster may have more
    CPUs), at most this machine's cores: more workers than cores make every solve and torch thread
    wait for a core."""
    import os

    _positive("--jobs", args.jobs)
    cores = os.cpu_count() or 1
    if args.ray_address is None and args.jobs > cores:
        raise UserError(f"--jobs {args.jobs}: expected at most {cores}, the cores of this machine (a local Ray with "
                        f"more workers than cores oversubscribes them; --ray-address HOST:PORT for a cluster)")


ROW_SIZES = ("agents", "species", "tasks", "skills")  # the options of a generated row's size (_row_args)
BENCH_COUNT, BENCH_SEED = 50, 1000  # hmrta bench's generated rows: missions per row, the test-set seed
MAX_SET_TASKS = 1_000_000  # tasks in all of a generated set (hmrta generate draws it in memory, ~0.5 KB a task)


def _row_sizes(args) -> None:
    """--agents, --species, --tasks and --skills of a generated row: positive integers (a mission
    without tasks is readable, but a generated set of them measures nothing), --agents a multiple
    of --species."""
    for k in ROW_SIZES:
        _positive(f"--{k}", getattr(args, k))
    if args.agents < args.species:
        raise UserError(f"--agents {args.agents}: expected at least --species ({args.species}): every species has "
                        f"a robot")
    if args.agents % args.species:  # (each species has agents / species robots)
        raise UserError(f"--agents {args.agents}: expected a multiple of --species ({args.species}): each species "
                        f"has --agents / --species robots")


def _with_scenario_missions(files) -> tuple:
    """``files`` and, for each scenario among them, the mission file it names (its ``instance``
    path, as given and beside the scenario): what the command reads."""
    import yaml

    out = list(files)
    for f in files:
        f = Path(f)
        try:
            if f.suffix.lower() not in (".yaml", ".yml") or "hmrta-scenario/1" not in f.read_text()[:4096]:
                continue
            name = (yaml.safe_load(f.read_text()) or {}).get("instance")
        except (OSError, UnicodeDecodeError, yaml.YAMLError, AttributeError):
            continue
        if isinstance(name, str):
            out += [Path(name), f.parent / name]
    return tuple(out)


def _not_an_input(flag: str, out: Path, inputs) -> None:
    """A UserError when the output file ``out`` is one of the files ``inputs`` (or a folder's
    config.json): writing it would destroy what the command reads."""
    import os

    for i in inputs:
        for f in (Path(i), Path(i) / "config.json"):
            try:
                same = out.exists() and f.is_file() and os.path.samefile(out, f)
            except OSError:
                same = False
            if same:
                raise UserError(f"{flag} {out}: is an input of this command ({f}); write the output elsewhere")


def writable(flag: str, path: str | Path, folder: bool = False, inputs: tuple = ()) -> Path:
    """``path``, the output named by ``flag``: a file (``folder``: a folder) that can be written there,
    checked before any work by creating and removing a probe file in the nearest existing folder on
    its way, and (a file) none of the command's ``inputs``. Otherwise a UserError naming the option,
    the path and the reason (nothing is left)."""
    import os
    import tempfile

    p = Path(path)
    if not folder and str(path).endswith(("/", os.sep)):  # (Path drops the slash)
        raise UserError(f"{flag} {path}: names a folder (a trailing /), expected a file name")
    if not folder:
        _not_an_input(flag, p, inputs)
    if folder and p.exists() and not p.is_dir():
        raise UserError(f"{flag} {p}: exists and is not a folder")
    if not folder and p.is_dir():
        raise UserError(f"{flag} {p}: is a folder, expected a file name")
    if not folder and p.exists() and not p.is_file():
        raise UserError(f"{flag} {p}: exists and is not a regular file")
    here = p if folder else p.parent
    while not here.exists() and here != here.parent:
        here = here.parent
    if not here.is_dir():
        raise UserError(f"{flag} {p}: {here} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".hmrta-probe-", dir=here)
    except OSError as e:
        raise UserError(f"{flag} {p}: cannot write in {here} ({e.strerror})") from None
    os.close(fd)
    os.unlink(probe)
    return p


def _seconds(flag: str, value: float | None) -> None:
    """UserError naming ``flag`` unless ``value`` (None: not given) is a finite positive time."""
    if value is not None and not 0 < value < float("inf"):  # NaN fails too
        raise UserError(f"{flag}: expected a positive number of seconds, got {value}")


def _seed(value: int) -> None:
    """A seed: numpy's seed sequences take non-negative integers only, torch's generators 64 bits."""
    if not 0 <= value < 2**63:
        raise UserError(f"--seed: expected an integer in 0..2^63-1, got {value}")


def _user_errors() -> tuple[type[BaseException], ...]:
    from .instance import InstanceError
    from .errors import MethodError
    from .reading import InputError
    from .solution import RouteError, SolutionError

    errs: list[type[BaseException]] = [UserError, InstanceError, RouteError, MethodError, SolutionError, InputError]
    # CheckpointError and MissingDependency are MethodErrors
    return tuple(errs)


def _load(path: str, static: str | None = None, releases: bool = False):
    """The mission in ``path``; with ``static`` (what the command does), a scenario (a mission with
    timed events) is refused: the command would silently drop its events. So are tasks with
    release times, unless ``releases`` (the command keeps or honours them)."""
    from .formats import load_instance

    inst = load_instance(path)
    if static and inst.events:
        raise UserError(f"{path}: a scenario (a mission with timed events): {static}, so its events would be "
                        f"lost; give its mission file (the scenario's instance), or solve the scenario "
                        f"(hmrta solve / bench run its events)")
    late = sum(t.release > 0 for t in inst.tasks)
    if static and late and not releases:
        raise UserError(f"{path}: {late} task(s) with a release time: {static}, which would take every task as "
                        f"known at time 0; solve the mission instead (hmrta solve / bench honour release times)")
    return inst


def _plannable(methods: list[str], missions: list[tuple[str, object]]) -> None:
    """MethodError naming the mission (``(where, instance)`` pairs) unless every method can plan
    every mission (:func:`hmrta.methods.check_instance`): checked before any work."""
    from .methods import MethodError, check_instance, parse

    for m in methods:  # a method that does not exist is not the missions' fault
        parse(m)
    for where, inst in missions:
        for m in methods:
            try:
                check_instance(m, inst)
            except MethodError as e:
                raise MethodError(f"{where}: {e}") from None


def _ctas_folder(folder: Path) -> bool:
    """Whether ``folder`` is one CTAS-D mission (it holds config.json), saying so where it also
    holds mission files, which are then not read."""
    if not (folder / "config.json").exists():
        return False
    if any(folder.glob("*.yaml")) or any(folder.glob("*.yml")):
        print(f"warning: {folder}: read as one CTAS-D mission (its config.json); the *.yaml files in it are not "
              "read (name them to use them)", file=sys.stderr)
    return True


def _resolve_instances(paths: list[str]) -> list[Path]:
    out: list[Path] = []
    for p in paths:
        pp = Path(p)
        if pp.is_dir() and not _ctas_folder(pp):
            files = sorted([*pp.glob("*.yaml"), *pp.glob("*.yml")])
            if not files:
                raise UserError(f"{pp}: folder has no instance files (*.yaml) and no config.json")
            out += files
        else:
            out.append(pp)
    return out


def _matching(folder: Path, inst_file: Path, what: str) -> Path:
    """``folder/<stem>.json`` for an instance file (a CTAS-D folder's stem is the folder name)."""
    p = folder / f"{inst_file.stem}.json"
    if not p.is_file():
        raise UserError(f"{p}: no such file (expected the {what} of instance {inst_file})")
    return p


THREADS_HELP = ("torch CPU threads of the learned policy's methods (rl, rl-sample, rl-lookahead, portfolio). "
                "One suits inference: a decision's forward pass is too small to share between threads, and "
                "torch's own choice (a thread per core) collapses when other processes keep the cores busy "
                "(on 2 cores beside two busy processes, 10 to 100 times slower than one thread)")


def set_torch_threads(torch, n: int) -> None:
    """``n`` intra-op and (when still possible) inter-op threads for ``torch``."""
    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(n)
    except RuntimeError:  # only before any inter-op parallel work, and once per process
        pass


class TorchThreads:
    """Sets torch's CPU threads as soon as torch is imported, without importing it (greedy-only
    runs never load torch): a meta-path finder that, the first time ``torch`` is imported, lets the
    other finders locate it and sets the threads right after the module has run. Where torch is
    already imported, the threads are set at once. ``remove()`` uninstalls the finder."""

    def __init__(self, n: int):
        self.n = n
        if "torch" not in sys.modules:
            sys.meta_path.insert(0, self)
        elif sys.modules["torch"] is not None:  # (None: an import of torch is blocked)
            set_torch_threads(sys.modules["torch"], n)

    def remove(self) -> None:
        if self in sys.meta_path:
            sys.meta_path.remove(self)

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        import importlib.util

        self.remove()  # once, and the other finders locate torch
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run, n = spec.loader.exec_module, self.n

        def exec_module(module) -> None:
            run(module)
            set_torch_threads(module, n)

        spec.loader.exec_module = exec_module  # this spec's own loader object
        return spec


def _threads(args) -> TorchThreads | None:
    n = getattr(args, "threads", None)
    if n is None or args.cmd == "train":  # training sets its own (cmd_train)
        return None
    _positive("--threads", n)
    return TorchThreads(n)


def _terminal() -> bool:
    """Whether stderr is a terminal: progress bars are drawn only there (in a log file or a pipe
    they would be runs of carriage returns)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def _progress_on(args) -> bool:
    return not getattr(args, "no_progress", False) and _terminal()


class SolveProgress:
    """A progress bar on stderr for one solve, fed by the solver's ``progress(done, total, unit,
    note)`` calls (``unit`` "s": seconds of a time limit, then the bar also advances between calls;
    "task": tasks started). It appears only once the solve has run for :attr:`DELAY` seconds, so
    short solves print nothing."""

    DELAY = 2.0

    def __init__(self, desc: str, enabled: bool = True):
        import threading

        self.desc, self.enabled = desc, enabled
        self.bar = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ticker = None
        self._last = (0.0, 0.0)  # (done, wall clock) of the last call, for "s" bars

    def __call__(self, done: float, total: float | None = None, unit: str = "", note: str = "") -> None:
        import time

        if not self.enabled:
            return
        with self._lock:
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=total, desc=self.desc, unit=unit or "it", delay=self.DELAY, leave=False,
                                file=sys.stderr, bar_format=None if unit != "s" else
                                "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s{postfix}")
                import threading

                self._unit, self._t0 = unit, time.monotonic()
                self._ticker = threading.Thread(target=self._tick, daemon=True)
                self._ticker.start()
            if total is not None and self.bar.total != total:
                self.bar.total = total
            self._last = (done, time.monotonic())
            if note:
                self.bar.set_postfix_str(note, refresh=False)
            self._advance(done)

    def _advance(self, value: float) -> None:
        if self.bar.total is not None:
            value = min(value, self.bar.total)
        if value > self.bar.n:
            self.bar.update(value - self.bar.n)

    def _tick(self) -> None:
        import time

        while not self._stop.wait(0.5):
            with self._lock:
                done, at = self._last
                if self._unit == "s":  # seconds of a time limit pass between the solver's calls
                    self._advance(done + time.monotonic() - at)
                elif time.monotonic() - self._t0 >= self.DELAY:  # shown, its elapsed time going, between calls
                    self.bar.refresh()
                    self.bar.last_print_t = self.bar._time()  # shown: close() clears it (tqdm counts updates only)

    def close(self) -> None:
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(timeout=2.0)
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> "SolveProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _solve_opts(args) -> dict:
    from .methods import options_from_args

    return options_from_args(args)


# ---------------------------------------------------------------------------------------------
def cmd_solve(args) -> int:
    from .methods import keep_best_on_interrupt, solve
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
        if not args.json:
            print(sol.summary())
            if args.schedule:
                print(schedule_text(inst, sol))
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
    from .solution import RouteError, evaluate_routes

    try:
        return evaluate_routes(inst, routes)
    except RouteError as e:
        raise RouteError(f"{path}: {e}") from None


def cmd_evaluate(args) -> int:
    from .solution import read_routes

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


def cmd_generate(args) -> int:
    from .generators import ScenarioGenerator, index_width

    _positive("--count", args.count)
    _row_sizes(args)
    if args.count * args.tasks > MAX_SET_TASKS:  # the whole set is drawn in memory before it is written
        raise UserError(f"--count {args.count} x --tasks {args.tasks}: at most {MAX_SET_TASKS:,} tasks in one set "
                        f"(write several sets with other --seed values)")
    _seed(args.seed)
    writable("--out", args.out, folder=True)
    try:  # every instance is drawn before the folder is made: a row no team can do leaves nothing
        gen = ScenarioGenerator(args.scenario, args.agents, args.species, args.tasks, args.skills)
        instances = gen.generate(args.count, args.seed)
    except ValueError as e:
        raise UserError(str(e)) from None
    out = Path(args.out)
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    width = index_width(args.count)
    name = f"{gen.name}_s{args.seed}"
    written: list[Path] = []
    try:
        for i, inst in enumerate(instances):
            written.append(out / f"{name}_{str(i).zfill(width)}.yaml")
            inst.save(written[-1])
    except BaseException:  # interrupted (or a write failed): no partial set is left behind
        for f in written:
            f.unlink(missing_ok=True)
        if made and not any(out.iterdir()):
            out.rmdir()
        raise
    print(f"wrote {args.count} instances to {out}/{name}_*.yaml")
    return 0


def robot_mapping(inst, config: dict) -> dict:
    """CTAS-D robot ids -> hmrta agent ids of the converted instance. Robots sharing pose and
    skillset form one species (in order of the lowest robot id); agents are numbered species-major,
    each species' robots in increasing id order."""
    robots = config["robots"]
    k = inst.skills
    slots: dict[int, list[str]] = {}
    for key in sorted(robots, key=int):
        r = robots[key]
        traits = [0.0] * k
        for sk, v in r["skillset"].items():
            traits[int(sk)] = float(v)
        sig = ((float(r["pose"]["x"]), float(r["pose"]["y"])), tuple(traits))
        s = next(i for i, sp in enumerate(inst.species) if (tuple(sp.depot), tuple(sp.traits)) == sig)
        slots.setdefault(s, []).append(key)
    offset, robot_to_agent = 0, {}
    for s, sp in enumerate(inst.species):
        ids = slots.get(s, [])
        if len(ids) != sp.count:  # the reader grouped robots otherwise: never write a wrong mapping
            raise RuntimeError(f"species {s}: {len(ids)} robots map to it, the instance has {sp.count}")
        for j, key in enumerate(ids):
            robot_to_agent[key] = offset + j
        offset += sp.count
    return robot_to_agent


MAPPING_FORMAT = "hmrta-robot-mapping/1"  # convert's OUT.mapping.json (docs/schemas)


def mapping_path(out: str | Path) -> Path:
    """Where ``convert --out OUT.yaml`` writes the robot id mapping: ``OUT.mapping.json``."""
    out = Path(out)
    return out.with_name(f"{out.stem}.mapping.json")


def cmd_convert(args) -> int:
    from .instance import atomic_write_text

    writable("--out", args.out, inputs=(args.input,))
    inst = _load(args.input, "hmrta-instance/1 holds no events", releases=True)  # release times it holds
    if Path(args.out).suffix.lower() == ".json":
        raise UserError(f"--out {args.out}: convert writes hmrta-instance/1 YAML; give a .yaml file name")
    src = Path(args.input)
    cfg = src / "config.json" if src.is_dir() else src
    mapping = None
    if cfg.suffix.lower() == ".json":  # CTAS-D: robots are renumbered species-major
        r2a = robot_mapping(inst, json.loads(cfg.read_text()))
        mapping = {"format": MAPPING_FORMAT, "source": str(cfg), "instance": str(args.out), "robot_to_agent": r2a,
                   "agent_to_robot": sorted(r2a, key=r2a.get)}
    inst.save(args.out)
    print(f"wrote {args.out} ({inst.n_agents} agents in {inst.n_species} species, {inst.n_tasks} tasks)")
    if mapping is not None:
        mp = mapping_path(args.out)
        atomic_write_text(mp, json.dumps(mapping, indent=1) + "\n")
        print(f"wrote {mp} (CTAS-D robot id -> hmrta agent id, agents numbered species-major)")
    return 0


def cmd_bench(args) -> int:
    from . import bench
    from .generators import PAPER_ROWS

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods:
        raise UserError(f"--methods: expected a comma list of methods, got {args.methods!r}")
    from .methods import METHODS, MethodError, check_options, options_for, parse

    for m in methods:
        parse(m)  # unknown method: user error before any work
    for k in _solve_opts(args):  # an option none of the methods takes is an error
        if not any(k in options_for(m, {k: 1}) for m in methods):
            takers = [n for n, rec in METHODS.items() if rec.option(k)]
            raise MethodError(f"--{k.replace('_', '-')}: none of the methods {', '.join(methods)} takes it "
                              f"(methods that do: {', '.join(takers)})")
    for m in methods:  # and a value out of range (a portfolio's candidates too), before the cache is written
        if check_options(m, options_for(m, _solve_opts(args))).get("candidates") is not None:
            from .portfolio import candidate_methods

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
        from .families import family_suite

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
            raise UserError(f"bench: give your missions (INSTANCE...), --suite paper, or all of --scenario --agents "
                            f"--species --tasks --skills (missing --{missing[0]})")
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
    from .bench import MissionSet

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


def _interrupt_on(*signals: int) -> None:
    """These signals raise KeyboardInterrupt in the main thread, as a Ctrl-C does."""
    import signal

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    for s in signals:
        signal.signal(s, interrupt)


def cmd_train(args) -> int:
    import os

    from .deps import require

    _positive("--threads", args.threads)
    _jobs(args)
    # idle OpenMP threads sleep instead of spinning: read once, when torch loads its OpenMP runtime
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    torch = require("torch", "hmrta train")

    from .rl.train import Trainer, load_config, write_config

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
    _train_device(torch, args.device)
    if (args.init or args.reseed) and not args.resume:
        raise UserError("--init and --reseed only apply with --resume")
    run_dir = writable("--run-dir", args.run_dir or f"runs/{cfg['name']}", folder=True)
    if args.export:
        writable("--export", args.export)
    last = run_dir / "last.pt"
    if last.exists() and not args.resume:
        raise UserError(f"{run_dir} already holds a run: pass --resume to continue it or --run-dir for a new one")
    if args.init and not Path(args.init).is_file():
        raise UserError(f"--init {args.init}: no such checkpoint file")
    if args.resume and not args.init and not last.is_file():
        raise UserError(f"--resume: no checkpoint {last} to continue (start a new run without --resume, or give "
                        f"--init CHECKPOINT)")
    if args.check:  # the config, and the command line as it would run
        print(f"{args.config}: a valid training config (name {cfg['name']!r})")
        return 0
    if args.threads:
        torch.set_num_threads(args.threads)
    import signal

    # stop at once; the trainer writes last.pt on the way out (the state after the latest finished
    # iteration: an exact resume); SIGINT also when started in the background (ignored there)
    _interrupt_on(signal.SIGTERM, signal.SIGINT)
    from tqdm import tqdm

    # log lines above the progress bar, not into it
    tr = Trainer(cfg, run_dir, device=args.device, log=lambda s: tqdm.write(s, file=sys.stderr), jobs=args.jobs,
                 ray_address=args.ray_address)
    if args.resume:
        src = Path(args.init) if args.init else last
        tr.load(src, reseed=args.reseed, same_run=not args.init)
        print(f"resumed from {src}: iteration {tr.iteration}, {tr.episodes} episodes", file=sys.stderr)
        changed = tr.changed_keys()
        if changed:
            print(f"this config differs from the checkpoint's ({len(changed)} setting(s); the run goes on under "
                  f"this config's and records it): " + "; ".join(changed[:8]) + ("; ..." if len(changed) > 8 else ""),
                  file=sys.stderr)
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
    from .bench import clean

    print(json.dumps(clean(res)))  # strict JSON: no score yet is null, not Infinity
    if args.export:
        best = run_dir / "best.pt"
        if best.exists():
            tr.load(best)
        tr.export(Path(args.export))
        print(f"exported {'best' if best.exists() else 'last'} weights to {args.export}", file=sys.stderr)
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

    from .rl.checkpoint_info import CheckpointError, checkpoint_path, describe

    refused = None
    if importlib.util.find_spec("torch") is not None:  # what solve, bench, the agents and --resume would refuse, info refuses too
        from .rl.checkpoint import COUNTERS, counter, load
        from .rl.inference import load_policy

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
    from .rl.checkpoint_info import lineage_lines

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
    rows += [(k, d[k]) for k in ("iteration", "episodes", "best_val") if k in d]
    for k, v in rows:
        print(f"  {k:<13} {v}")
    if d["lineage"]:
        print("  lineage")
        for line in lineage_lines(d["lineage"]):
            print("    " + line)


def cmd_checkpoint(args) -> int:
    from .deps import require

    require("torch", "hmrta checkpoint")
    from .bench import file_sha256
    from .rl.checkpoint import average
    from .rl.checkpoint_info import checkpoint_path

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
    from .rl.schedules import ScheduleError, ScheduleSet, generate, make_generator

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


def cmd_bound(args) -> int:
    from .bounds import bound_report, format_report
    from .solution import check_planned_for, check_solution

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
        work.append((inst, sols))
    reports = []
    for inst, sols in tqdm(work, desc="bound", disable=not many or not _progress_on(args), unit="instance",
                           file=sys.stderr, delay=SolveProgress.DELAY):
        if args.time_limit is not None:
            from .methods import solve

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
    from .solution import read_solution

    return read_solution(path)


def _solution_or_routes(inst, path: str):
    """An ``hmrta-solution/1`` file, or a routes file as ``hmrta evaluate`` takes it (then
    re-simulated on ``inst``); when it is neither, the error is the routes reader's for a file
    that looks like a routes file (an object with ``routes`` and no ``format``), else the
    solution reader's."""
    from .solution import RouteError, SolutionError, read_routes

    try:
        return _read_solution(path)
    except SolutionError as e:
        try:
            routes = read_routes(inst, path)
        except RouteError as r:
            raise (r if _looks_like_routes(path) else e) from None
    if inst.dynamic or bool((inst.releases > 0).any()):
        raise UserError(f"{path}: routes are re-simulated without release times or events (as hmrta evaluate "
                        f"does), which this mission has: give its solution file (hmrta solve --out)")
    return _evaluated(inst, routes, path)


def _looks_like_routes(path: str) -> bool:
    """A JSON object with ``routes`` and no ``format``: a routes file (``hmrta evaluate``'s input)."""
    from .reading import InputError, read_json

    try:
        d = read_json(path)
    except InputError:  # unreadable or not JSON: the solution reader's error says so
        return False
    return isinstance(d, dict) and "routes" in d and "format" not in d


def cmd_render_recording(args) -> int:
    """``hmrta render [INSTANCE] --from FILE.mcap --out fig.png``: the executed mission."""
    from .replay import ReplayError, read_recording, render_recording, summary
    from .solution import check_solution

    if args.solution is not None:
        raise UserError("render --from: give the recording and (optionally) the instance, not a solution file")
    if args.gif:
        raise UserError("render --from: --gif is not available for recordings")
    writable("--out", args.out, inputs=tuple(x for x in (args.from_, args.instance) if x))
    try:
        rec = read_recording(args.from_)
    except ReplayError as e:
        raise UserError(str(e)) from None
    if args.instance is not None:  # the recorded mission must be this instance
        inst = _load(args.instance)
        if inst.to_dict() != rec.instance.to_dict():
            raise UserError(f"{args.from_}: the recorded mission ({rec.instance.name}, {rec.instance.n_agents} robots, "
                            f"{rec.instance.n_tasks} tasks) is not the instance {args.instance} ({inst.name})")
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
    from .deps import require
    from .render import check_gif_options, render
    from .solution import SolutionError, check_planned_for, final_instance

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


def cmd_demo(args) -> int:
    from .methods import solve

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


def cmd_keys(args) -> int:
    from .keys import KeystoreError, create_keystore, robot_key_path

    if args.instance:
        inst = _load(args.instance)  # (a scenario: the robots its add_robot events add too)
        added = sum(e.get("type") == "add_agent" for e in inst.events)
        robots = [f"robot_{a}" for a in range(inst.n_agents + added)]
    else:
        robots = [r.strip() for r in args.robots.split(",")]
        if not all(robots):
            raise UserError(f"--robots {args.robots!r}: expected comma-separated robot names, found an empty one")
    try:
        create_keystore(args.out, robots, force=args.force)
    except KeystoreError as e:
        raise UserError(f"keys create: {e}") from None
    print(f"wrote keystore {args.out} for {len(robots)} robots: {Path(args.out) / 'keys.json'} (the task board's, "
          f"every key) and {robot_key_path(args.out, robots[0]).parent}/<robot>.key.json (give each robot only its own)")
    return 0


# ---------------------------------------------------------------------------------------------
class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default once: appended as "(default: X)" unless the help text already
    speaks of its default, and never for options without a default (None, off flags, empty)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        if d is None or d is False or d == argparse.SUPPRESS or (isinstance(d, list) and not d) \
                or "default" in text:
            return text
        return super()._get_help_string(action)


def _row_args(p: argparse.ArgumentParser, required: bool) -> None:
    """--scenario --agents --species --tasks --skills (one scenario row)."""
    from .generators import SCENARIOS

    pre = "" if required else "single row: "
    p.add_argument("--scenario", required=required, choices=SCENARIOS, default=None,
                   help=pre + "trait kind (SA single-skill / MA multi-skill) x requirement kind (AT additive / BT binary)")
    p.add_argument("--agents", type=int, required=required, default=None,
                   help=pre + "number of agents (a multiple of --species)")
    p.add_argument("--species", type=int, required=required, default=None, help=pre + "number of species (at least 1)")
    p.add_argument("--tasks", type=int, required=required, default=None, help=pre + "number of tasks (at least 1)")
    p.add_argument("--skills", type=int, required=required, default=None, help=pre + "number of skills K (at least 1)")


def _fanout_args(p: argparse.ArgumentParser, what: str, note: str = "") -> None:
    """--jobs and --ray-address (hmrta.fanout) of a command that fans ``what`` out."""
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help=f"{what} as Ray tasks on a local Ray with N CPUs (one torch thread each; needs pip "
                        f"install 'hmrta[ray]'), N at most this machine's cores unless --ray-address; 1: in this "
                        f"process{note}")
    p.add_argument("--ray-address", default=None, metavar="HOST:PORT", type=_ray_address,
                   help=f"{what} on an existing Ray cluster instead: its head's GCS address (ray start --head "
                        "prints it; port 6379 by default); with token authentication, Ray's default, also "
                        "RAY_AUTH_MODE=token and the cluster's token (docs/training.md)")


def _ray_address(text: str) -> str:
    from .fanout import split_address

    try:
        split_address(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


class Parser(argparse.ArgumentParser):
    """A bad command line is one line on stderr, like every other user error (exit 2); the usage is
    in --help. Its subcommands' parsers are of this class too."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        """An argument no parser knows is said by the (sub)command's own parser: ``hmrta solve
        --bogus`` points to ``hmrta solve --help``."""
        ns, extra = self.parse_known_args(args, namespace)
        if extra:
            self._innermost(ns).error(f"unrecognized arguments: {' '.join(extra)}")
        return ns

    def _innermost(self, ns) -> argparse.ArgumentParser:
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                sub = action.choices.get(getattr(ns, action.dest, None) or "")
                if sub is not None:
                    return sub._innermost(ns) if isinstance(sub, Parser) else sub
        return self


def build_parser() -> argparse.ArgumentParser:
    from .methods import add_arguments as add_method_arguments
    from .rl.schedules import GENERATORS as SCHEDULE_GENERATORS

    p = Parser(
        prog="hmrta",
        description="Heterogeneous multi-robot task allocation: instances, simulator, baselines, learned policy.",
        formatter_class=HelpFormatter)
    p.add_argument("--version", action="version", version=f"hmrta {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    F = HelpFormatter

    s = sub.add_parser("solve", help="solve instances and write hmrta-solution/1 JSON", formatter_class=F)
    s.add_argument("instances", nargs="+", metavar="INSTANCE", help=INSTANCE_HELP)
    add_method_arguments(s, default="portfolio")
    s.add_argument("--seed", type=int, default=0, help="episode seed (decision order, sampling)")
    s.add_argument("--out", default=None, help="solution file (one instance, a name with a suffix: sol.json) or "
                                               "folder (DIR/<stem>.json; a name without a suffix, an existing "
                                               "folder, or several instances); missing folders are created")
    shown = s.add_mutually_exclusive_group()
    shown.add_argument("--json", action="store_true", help="print the solution JSON instead of a summary")
    shown.add_argument("--schedule", action="store_true",
                       help="also print the per-task schedule and routes (the JSON holds them: not with --json)")
    s.add_argument("--no-progress", action="store_true",
                   help="no progress bars (per instance with several, per decision or second in a long solve, "
                        "per candidate of the portfolio; drawn only when stderr is a terminal)")
    s.add_argument("--threads", type=int, default=1, metavar="N", help=THREADS_HELP)
    s.set_defaults(fn=cmd_solve)

    e = sub.add_parser("evaluate", help="re-simulate given routes and print the metrics", formatter_class=F)
    e.add_argument("instance", help=INSTANCE_HELP)
    e.add_argument("routes", help="JSON object with a 'routes' key: per agent (species-major) the task ids in "
                                  "order; for several instances, a folder of <instance stem>.json files")
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
    c.add_argument("--out", required=True,
                   help="output YAML path; a CTAS-D input also writes the robot id -> agent id mapping beside it (--out X.yaml: X.mapping.json)")
    c.set_defaults(fn=cmd_convert)

    b = sub.add_parser("bench", help="compare methods on generated rows (the paper's tables, the paper's numbers "
                                     "beside ours) or on your own missions: Markdown, JSON and CSV with provenance",
                       formatter_class=F)
    b.add_argument("instances", nargs="*", metavar="INSTANCE",
                   help="your missions instead of generated rows: " + INSTANCE_HELP
                        + " (one table row per folder, one for the files given singly)")
    b.add_argument("--suite", choices=["paper", "families"], default=None,
                   help="paper: every paper row (Tables I-IV); families: the mission families (docs/families.md)")
    b.add_argument("--tables", default=None, help="with --suite: comma list of SA-BT,SA-AT,MA-AT,MA-AT-large "
                   "(families: of family names, e.g. homog,binary)")
    b.add_argument("--max-tasks", type=int, default=None, help="with --suite: skip rows with more tasks (at least "
                                                              "one row must remain)")
    _row_args(b, required=False)
    b.add_argument("--count", type=int, default=None,
                   help=f"instances per generated row, not for your missions (default: {BENCH_COUNT})")
    b.add_argument("--seed", type=int, default=None,
                   help=f"test-set seed of the generated rows (never used in training or validation), not for "
                        f"your missions (default: {BENCH_SEED})")
    add_method_arguments(b, methods_flag=True)
    b.add_argument("--bounds", action="store_true",
                   help="also report each method's gap to the best lower bound, (makespan - bound) / makespan as "
                        "hmrta bound gives it; none for missions with events")
    b.add_argument("--compare", action="append", default=None, metavar="A,B",
                   help="paired per-instance comparison of two methods (repeatable; default: rl and portfolio, "
                        "each against greedy and greedy-coalition, when those methods run)")
    b.add_argument("--out", default=None,
                   help="folder for results.md, results.json, results.csv and a resumable cache "
                        "(--suite default: bench-<suite> in the current folder; the committed tables are "
                        "regenerated with --out docs/results/<suite>)")
    b.add_argument("--json", action="store_true", help="print the results as JSON instead of Markdown")
    b.add_argument("--no-progress", action="store_true", help="no progress bar (drawn only when stderr is a terminal)")
    _fanout_args(b, "solve the uncached items", " (not to be confused with --workers, CP-SAT's search workers "
                                                "per solve)")
    b.add_argument("--threads", type=int, default=1, metavar="N",
                   help=THREADS_HELP + "; recorded in the results' provenance")
    b.set_defaults(fn=cmd_bench)

    t = sub.add_parser("train", help="train the policy (cloning a teacher or solver schedules, then REINFORCE; docs/training.md)", formatter_class=F,
                       description="Train the policy. Idle OpenMP threads wait passively (OMP_WAIT_POLICY=PASSIVE "
                                   "is set before torch loads, unless the environment already sets it), so a run "
                                   "does not spin on cores that other processes need.")
    t.add_argument("--config", default="default",
                   help="training config: a YAML file, or the name of a shipped one (" +
                        ", ".join(sorted(p.stem for p in CONFIGS.glob("*.yaml"))) + "; when left out: the shipped config named default)")
    t.add_argument("--resume", action="store_true", help="continue the run in --run-dir (model, optimiser, RNG) from "
                                                         "its last.pt, which must exist")
    t.add_argument("--init", default=None, help="with --resume: start from this checkpoint file instead of last.pt")
    t.add_argument("--reseed", action="store_true",
                   help="with --resume: draw fresh random streams from the config's seed and forget the "
                        "checkpoint's best validation score (an independent continuation, e.g. under other rules)")
    t.add_argument("--run-dir", default=None, help="run folder (default runs/<config name>)")
    t.add_argument("--max-minutes", type=float, default=None, help="stop after this many minutes (checkpointed)")
    t.add_argument("--iterations", type=int, default=None,
                   help="override train.iterations (REINFORCE's; the cloning and distillation phases run "
                        "pretrain.iterations and distill.iterations: cap them in the config, or the run with "
                        "--max-minutes)")
    t.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: cuda when available)")
    t.add_argument("--threads", type=int, default=None, metavar="N",
                   help="torch CPU threads (default: torch's, one per core; fewer beside other busy processes)")
    _fanout_args(t, "label the teachers' missions (behaviour cloning) and roll out the validation set",
                 "; the labels, and so the run, are the same whatever N")
    t.add_argument("--export", default=None, help="after training, write the best weights + config here")
    t.add_argument("--no-progress", action="store_true", help="no progress bar (drawn only when stderr is a terminal)")
    t.add_argument("--check", action="store_true", help="only validate the config (with --iterations and "
                                                        "--max-minutes applied) and the command line (the run "
                                                        "folder, --resume, --init, --export), then exit (no training)")
    t.set_defaults(fn=cmd_train)

    ck = sub.add_parser("checkpoint", help="policy checkpoints: info (what one holds), average (the weights of several)", formatter_class=F)
    cksub = ck.add_subparsers(dest="checkpoint_cmd", required=True, metavar="ACTION")
    ca = cksub.add_parser("average", help="average the weights (the moving average where present) of checkpoints "
                                          "of the same network and rules; writes the config and the lineage "
                                          "(sources with sha256)", formatter_class=F)
    ca.add_argument("checkpoints", nargs="+", metavar="CHECKPOINT",
                    help="checkpoint files (.pt), or names of shipped ones (default, broad, ...; a file of such a "
                         "name here is ./NAME)")
    ca.add_argument("--out", required=True, help="checkpoint to write (atomically); never one of the sources")
    ca.add_argument("--force", action="store_true", help="replace an existing --out file")
    ca.add_argument("--json", action="store_true",
                    help="print the lineage entry written (sources with sha256, window, greedy decoding) as JSON")
    ca.add_argument("--window", nargs=2, type=int, metavar=("TASKS", "ROBOTS"),
                    help="observation window of the written checkpoint: a mission with more tasks or robots "
                         "is observed through the decider's nearest TASKS tasks and ROBOTS robots (default: "
                         "the sources', 50 and 25 unless set; docs/training.md, 'The observation window')")
    ca.add_argument("--greedy-depot", choices=("argmax", "majority"), default=None,
                    help="greedy decoding of the written checkpoint (RL(g.), live agents, lookahead): argmax "
                         "takes the most likely of [depot, tasks]; majority goes to the depot only when its "
                         "probability is at least 1/2, else takes the most likely task (default: the "
                         "sources', argmax unless set; docs/training.md, 'Deciding the depot on its total "
                         "probability')")
    ca.set_defaults(fn=cmd_checkpoint)
    ci = cksub.add_parser("info", help="what a checkpoint says about itself (no torch needed): sha256, format, "
                                       "code version, network, greedy decoding, rules, training counters, lineage",
                          formatter_class=F)
    ci.add_argument("checkpoint", nargs="?", default=None, metavar="CHECKPOINT",
                    help="checkpoint file, or the name of a shipped one (default, broad, coalition-team, "
                         "coalition-open; default: the shipped default.pt or $HMRTA_CHECKPOINT)")
    ci.add_argument("--json", action="store_true", help="print everything as JSON (the whole resolved config "
                                                        "and lineage)")
    ci.set_defaults(fn=cmd_checkpoint_info)

    sc = sub.add_parser("schedules", help="solve seeded training missions with the anytime solver and store "
                                          "their routes (a teacher dataset for pretrain.schedules)",
                        formatter_class=F,
                        description="Solve missions 0..COUNT-1 of a seeded generator with cpsat (list scheduler, "
                                    "annealing and CP-SAT within --time-limit seconds each) and append their "
                                    "pruned routes to a JSON-lines file (hmrta-schedules/1; instances are "
                                    "regenerated from the seed, not stored). Resumable: a rerun skips the "
                                    "missions the file holds. See docs/training.md.")
    sc.add_argument("--out", required=True, help="schedules file (.jsonl), created or resumed")
    sc.add_argument("--count", type=int, required=True, help="missions 0..COUNT-1")
    sc.add_argument("--seed", type=int, default=1, help="generator seed (keep it apart from dev and test seeds)")
    sc.add_argument("--generator", choices=SCHEDULE_GENERATORS, default="broad",
                    help="broad: every family axis (hmrta.families.BroadGenerator); paper: the paper's "
                         "training distribution (MA-AT, 3-5 species of 3-5 robots); single-skill: the "
                         "paper's SA teams (3-5 one-skill species of 2-10 robots, SA-AT or SA-BT)")
    sc.add_argument("--min-tasks", type=int, default=10, help="fewest tasks per mission")
    sc.add_argument("--max-tasks", type=int, default=30, help="most tasks per mission")
    sc.add_argument("--team-scale", type=float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                    help="broad: grow every team by one factor per mission, log-uniform in [LOW, HIGH] "
                         "(1 <= LOW <= HIGH <= 20; default 1 1: the generator's own sizes, up to 25 robots)")
    sc.add_argument("--time-limit", type=float, default=1.5, help="solver seconds per mission")
    sc.add_argument("--workers", type=int, default=1, help="CP-SAT search workers per mission")
    _fanout_args(sc, "solve the missions")
    sc.add_argument("--no-progress", action="store_true", help="no progress bar (drawn only when stderr is a terminal)")
    sc.set_defaults(fn=cmd_schedules)

    lb = sub.add_parser("bound", help="lower bounds on the makespan (and the gap of given solutions)",
                        formatter_class=F)
    lb.add_argument("instance", help=INSTANCE_HELP + " (a report per instance)")
    lb.add_argument("solutions", nargs="*", metavar="SOLUTION",
                    help="solution JSON files to report gaps for; for several instances, folders of "
                         "<instance stem>.json files (e.g. written by solve --out DIR)")
    lb.add_argument("--time-limit", type=float, default=None, help="also run CP-SAT this long; its bound counts")
    lb.add_argument("--json", action="store_true", help="print JSON")
    lb.add_argument("--no-progress", action="store_true", help="no progress bars (drawn only when stderr is a terminal)")
    lb.set_defaults(fn=cmd_bound)

    r = sub.add_parser("render", help="draw the routes map and a Gantt chart of a solution", formatter_class=F)
    r.add_argument("instance", nargs="?", default=None,
                   help="instance file (with --from: optional, checked against the recorded mission)")
    r.add_argument("solution", nargs="?", default=None,
                   help="hmrta-solution/1 JSON, or a routes file as hmrta evaluate takes it ({\"routes\": ...}: "
                        "re-simulated)")
    r.add_argument("--from", dest="from_", default=None, metavar="FILE.mcap",
                   help="draw a recorded mission (hmrta-mission --record): planned vs actual arrival times")
    r.add_argument("--out", required=True, help="output image (.png, or any format matplotlib writes: .svg, .pdf, ...); an --out ending in .gif writes "
                        "only the animation")
    r.add_argument("--gif", action="store_true", help="also write an animated GIF beside the PNG")
    r.add_argument("--frames", type=int, default=80, help="GIF frames (1..1000)")
    r.add_argument("--fps", type=int, default=10, help="GIF frames per second (1..50)")
    r.add_argument("--no-progress", action="store_true", help="no progress bar while the GIF is drawn (drawn only when stderr is a terminal)")
    r.set_defaults(fn=cmd_render)

    d = sub.add_parser("demo", help="solve the built-in example mission and print its schedule", formatter_class=F)
    d.add_argument("--instance", default=None, help="another instance instead of the built-in example")
    add_method_arguments(d, default="portfolio")
    d.add_argument("--seed", type=int, default=0, help="episode seed")
    d.add_argument("--out", default=None, help="also write the solution JSON here")
    d.add_argument("--no-progress", action="store_true", help="no progress bar during a long solve (drawn only when stderr is a terminal)")
    d.add_argument("--threads", type=int, default=1, metavar="N", help=THREADS_HELP)
    d.set_defaults(fn=cmd_demo)

    k = sub.add_parser("keys", help="mission keystore: one secret key per robot (signed choices and statuses)",
                       formatter_class=F)
    ksub = k.add_subparsers(dest="keys_cmd", required=True, metavar="ACTION")
    kc = ksub.add_parser("create", help="write a new keystore: KEYSTORE/keys.json (the board's) and "
                                        "KEYSTORE/robots/<robot>.key.json (one per robot)", formatter_class=F)
    who = kc.add_mutually_exclusive_group(required=True)
    who.add_argument("--robots", default=None, help="comma-separated robot names, e.g. robot_0,robot_1")
    who.add_argument("--instance", default=None, help="instance file: robots robot_0..robot_{A-1}")
    kc.add_argument("--out", required=True, help="keystore folder to create")
    kc.add_argument("--force", action="store_true", help="replace an existing keystore at --out (never a folder that is not a keystore)")
    kc.set_defaults(fn=cmd_keys)
    return p


class _PrintedOutput:
    """Standard output that goes quiet, and lets the command go on, once its reader has gone
    (``hmrta solve ... | head -1``): what a command writes to files is its result, what it prints
    is a summary, so a closed pipe must not cut a solve short or lose a file it was to write.
    Another failure to write it (a full disk) also lets the command go on, and is kept in
    ``failed`` to be reported once."""

    def __init__(self, stream):
        self._stream, self.reader_gone = stream, False
        self.failed: OSError | None = None

    def write(self, text: str) -> int:
        if not self.reader_gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._gone()
            except OSError as e:
                self.failed = e
                self._gone()
        return len(text)

    def flush(self) -> None:
        if not self.reader_gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._gone()
            except OSError as e:
                self.failed = e
                self._gone()

    def _gone(self) -> None:
        self.reader_gone = True
        try:  # what is still buffered, and the interpreter's last flush, go nowhere
            import os

            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)
        except (OSError, ValueError, AttributeError):
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    stdout = sys.stdout
    sys.stdout = printed = _PrintedOutput(stdout)
    try:
        status = _main(argv)
        printed.flush()
    finally:
        sys.stdout = stdout
    if printed.failed is not None:  # what was to be printed is lost; files written with --out are whole
        print(f"hmrta: error: cannot write to standard output ({printed.failed.strerror or printed.failed})",
              file=sys.stderr)
        return status or 1
    return status


def _main(argv: list[str] | None) -> int:
    try:
        parser = build_parser()  # (imports the method table: a moment on a loaded machine)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # for the provenance of results
    threads = None
    try:
        threads = _threads(args)
        return args.fn(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as e:  # noqa: BLE001
        from .errors import caused_by_interrupt

        if isinstance(e, ImportError) and caused_by_interrupt(e):  # a Ctrl-C while an extension module loaded
            print("interrupted", file=sys.stderr)
            return 130
        if isinstance(e, _user_errors()):
            print(f"hmrta: error: {' '.join(str(e).splitlines())}", file=sys.stderr)  # always one line
            return 2
        traceback.print_exc()
        print(f"hmrta: internal error: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        if threads is not None:
            threads.remove()


if __name__ == "__main__":
    sys.exit(main())
