"""The argument parser of every command (what ``--help`` prints)."""
from __future__ import annotations

import argparse
import sys

from .. import __version__
from ..rl.checkpoint_info import shipped_checkpoints
from .benchmarking import cmd_bench
from .common import BENCH_COUNT, BENCH_SEED, CONFIGS, INSTANCE_HELP
from .data import cmd_convert, cmd_generate, cmd_keys
from .rendering import cmd_bound, cmd_render
from .solving import cmd_demo, cmd_evaluate, cmd_solve
from .threads import THREADS_HELP
from .training import cmd_checkpoint, cmd_checkpoint_info, cmd_schedules, cmd_train


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
    from ..generators import SCENARIOS

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
    from ..fanout import split_address

    try:
        split_address(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


class Parser(argparse.ArgumentParser):
    """A bad command line is one line on stderr, like every other user error (exit 2); the usage is
    in --help. Its subcommands' parsers are of this class too."""

    _mixing = False  # within parse_known_intermixed_args (which calls parse_known_args)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        """An argument no parser knows is said by the (sub)command's own parser: ``hmrta solve
        --bogus`` points to ``hmrta solve --help``."""
        ns, extra = self.parse_known_args(args, namespace)
        if extra:
            self._innermost(ns).error(f"unrecognized arguments: {' '.join(extra)}")
        return ns

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        """Options may stand between the positional arguments of a command (``hmrta solve a.yaml
        --method greedy b.yaml``, ``hmrta render m.yaml --out f.png sol.json``): a command with
        positionals and no subcommands of its own is parsed intermixed."""
        given = sys.argv[1:] if args is None else args
        if self._mixing or not self._intermixed() or "--" in given:  # (after --: positionals)
            return super().parse_known_args(args, namespace)
        self._mixing = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._mixing = False

    def _intermixed(self) -> bool:
        positionals = self._get_positional_actions()
        return bool(positionals) and not any(a.nargs in (argparse.PARSER, argparse.REMAINDER) for a in positionals)

    def _innermost(self, ns) -> argparse.ArgumentParser:
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                sub = action.choices.get(getattr(ns, action.dest, None) or "")
                if sub is not None:
                    return sub._innermost(ns) if isinstance(sub, Parser) else sub
        return self


def build_parser() -> argparse.ArgumentParser:
    from ..methods import add_arguments as add_method_arguments
    from ..rl.schedules import GENERATORS as SCHEDULE_GENERATORS

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
                   help="paper: every paper row (Tables I-IV); families: the mission families (docs/families.md) "
                        "(default: no suite: your missions, or the one row of --agents ... --skills)")
    b.add_argument("--tables", default=None, help="with --suite: comma list of SA-BT,SA-AT,MA-AT,MA-AT-large "
                   "(families: of family names, e.g. homog,binary; default: every table of the suite)")
    b.add_argument("--max-tasks", type=int, default=None, help="with --suite: skip rows with more tasks (at least "
                                                              "one row must remain; default: no limit)")
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
                        "regenerated with --out docs/results/families, and for the paper's tables "
                        "docs/results/sa, ma and large: docs/results.md)")
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
    t.add_argument("--init", default=None, help="with --resume: start from this checkpoint (a file, or a shipped "
                                                "checkpoint by name, e.g. broad) instead of last.pt")
    t.add_argument("--reseed", action="store_true",
                   help="with --resume: draw fresh random streams from the config's seed and forget the "
                        "checkpoint's best validation score (an independent continuation, e.g. under other rules)")
    t.add_argument("--run-dir", default=None, help="run folder (default runs/<config name>)")
    t.add_argument("--max-minutes", type=float, default=None, help="stop after this many minutes, last.pt "
                   "holding the state (default: the config's train.max_minutes; none: every iteration)")
    t.add_argument("--iterations", type=int, default=None,
                   help="override train.iterations (REINFORCE's; the cloning and distillation phases run "
                        "pretrain.iterations and distill.iterations: cap them in the config, or the run with "
                        "--max-minutes)")
    t.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: cuda when available)")
    t.add_argument("--threads", type=int, default=None, metavar="N",
                   help="torch CPU threads (default: torch's, one per core; fewer beside other busy processes)")
    _fanout_args(t, "label the teachers' missions (behaviour cloning) and roll out the validation set",
                 "; the labels, and so the run, are the same whatever N")
    t.add_argument("--export", default=None, help="after training, write an inference checkpoint here: the "
                   "weights of the run's best.pt (its moving average with train.ema; last.pt without a "
                   "validation), its config, counters and lineage; never over the run's own files or one it "
                   "reads. "
                   "To export a run without training more: hmrta checkpoint average RUN/best.pt --out FILE")
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
                    help=f"checkpoint file, or the name of a shipped one ({', '.join(shipped_checkpoints())}); "
                         "default: the shipped default.pt or $HMRTA_CHECKPOINT")
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
    lb.add_argument("--time-limit", type=float, default=None, help="also run CP-SAT for this many seconds; its bound "
                    "counts (default: off, the fast bounds only)")
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
