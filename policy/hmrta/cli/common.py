"""What every command shares: user errors, the checks of options, paths and mission files."""
from __future__ import annotations

import sys
from pathlib import Path


EXAMPLE = Path(__file__).resolve().parents[1] / "data" / "example.yaml"
CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # the training configs (policy/configs), shipped with the package
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
    from ..instance import InstanceError
    from ..errors import MethodError
    from ..reading import InputError
    from ..solution import RouteError, SolutionError

    errs: list[type[BaseException]] = [UserError, InstanceError, RouteError, MethodError, SolutionError, InputError]
    # CheckpointError and MissingDependency are MethodErrors
    return tuple(errs)


def _load(path: str, static: str | None = None, releases: bool = False):
    """The mission in ``path``; with ``static`` (what the command does), a scenario (a mission with
    timed events) is refused: the command would silently drop its events. So are tasks with
    release times, unless ``releases`` (the command keeps or honours them)."""
    from ..formats import load_instance

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
    from ..methods import MethodError, check_instance, parse

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
