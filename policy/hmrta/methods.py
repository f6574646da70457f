"""The method table: one record per solution method, the single source of method names.

Each :class:`Method` says how the method solves a whole mission offline (``solve``), how it decides
one step live on a robot (``decide``, None when it has no per-decision form), the state-machine
rules it runs under, its options (name, type, default, help) and what it needs installed. The
``hmrta`` CLI's ``--method`` choices and option flags, ``hmrta-mission``, the ROS nodes' parameters
and the launch files' help are all generated from :data:`METHODS`.

Entry points are named as ``"module:attribute"`` strings and imported on first use, so that this
module (and the task board, which only needs :func:`rules`) never imports torch or ortools.

``rl-sN`` is shorthand for ``rl-sample`` with ``samples=N`` in method lists (``bench --methods
greedy,rl,rl-s10``); :func:`parse` is the one place that reads it, :func:`label` the one place that
writes it.
"""
from __future__ import annotations

import contextlib
import contextvars
import importlib
import inspect
import math
import re
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from .deps import require
from .errors import MethodError
from .rl.checkpoint_info import shipped_checkpoints

__all__ = ["METHODS", "Method", "MethodError", "Option", "decider", "label", "parse", "rules", "solve"]


@dataclass(frozen=True)
class Option:
    """A method option: CLI flag ``--<name with dashes>``, ROS parameter ``<name>``."""

    name: str
    type: type  # int | float | str
    default: Any
    help: str
    choices: tuple[str, ...] | None = None
    minimum: float | None = None  # smallest value allowed (numbers)
    maximum: float | None = None  # largest value allowed (numbers)
    live: bool = True  # also an option of the per-decision (ROS agent) form
    within: str | None = None  # another option whose value bounds this one's (a time it is part of)

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def label(self) -> str:
        """How an error names it: ROS parameter and command-line flag (``option time_limit
        (--time-limit)``)."""
        return f"option {self.name}" + (f" ({self.flag})" if self.flag[2:] != self.name else "")

    def coerce(self, method: str, value: Any) -> Any:
        """``value`` as this option's type, or MethodError naming the method and the option."""
        try:
            if self.type is int and (isinstance(value, bool) or (isinstance(value, float) and not value.is_integer())):
                raise ValueError
            v = self.type(value)
        except (TypeError, ValueError):
            raise MethodError(f"{method}: {self.label}: expected {self.type.__name__}, got {value!r}") from None
        if self.choices is not None and v not in self.choices:
            raise MethodError(f"{method}: {self.label}: expected one of {', '.join(self.choices)}, got {v!r}")
        if isinstance(v, float) and not math.isfinite(v):
            raise MethodError(f"{method}: {self.label}: expected a finite number{self._range()}, got {value!r}")
        if (self.minimum is not None and v < self.minimum) or (self.maximum is not None and v > self.maximum):
            kind = "an integer" if self.type is int else "a number"
            raise MethodError(f"{method}: {self.label}: expected {kind}{self._range()}, got {value!r}")
        return v

    def _range(self) -> str:
        if self.minimum is not None and self.maximum is not None:
            return f" in [{self.minimum}, {self.maximum}]"
        if self.minimum is not None:
            return f" >= {self.minimum}"
        return "" if self.maximum is None else f" <= {self.maximum}"


@dataclass(frozen=True)
class Method:
    name: str
    summary: str  # one line, for --help
    solve: str | Callable  # "module:function"(inst, seed=0, **options) -> Solution
    decide: str | None = None  # "module:function"(seed=0, **options) -> decide(state) -> node
    rules: str | None = "hmrta.baselines:GREEDY_RULES"  # "module:attr": Rules, or a function(**options) -> Rules
    options: tuple[Option, ...] = ()
    needs: tuple[str, ...] = ()  # optional modules it imports (see hmrta.deps.EXTRAS)
    # for a method with no per-decision form that picks one per mission (portfolio):
    # "module:function"(inst, seed=0, **options) -> (method name, {candidate: makespan})
    choose: str | None = None

    def option(self, name: str) -> Option | None:
        return next((o for o in self.options if o.name == name), None)

    def check(self, options: dict[str, Any], live: bool = False) -> dict[str, Any]:
        """Validated and typed options; an option this method does not take is a MethodError."""
        out = {}
        for k, v in options.items():
            o = self.option(k)
            if o is None or (live and not o.live):
                takes = [x.name for x in self.options if x.live or not live]
                raise MethodError(f"method {self.name} takes no option {k!r}"
                                  + (f" (it takes: {', '.join(takes)})" if takes else " (it takes no options)"))
            out[k] = v if v is None and k == "checkpoint" else o.coerce(self.name, v)
        for k, v in out.items():
            o = self.option(k)
            if o.within is not None and v is not None:
                b = self.option(o.within)
                limit = out.get(b.name, b.default)
                if v > limit:
                    raise MethodError(f"{self.name}: option {o.name} ({o.flag}) {v:g} is more than option {b.name} "
                                      f"({b.flag}) {limit:g}{'' if b.name in out else ', its default'}: it is a "
                                      f"part of that time (expected at most {limit:g})")
        return out


CHECKPOINT = Option("checkpoint", str, None, "policy checkpoint: a file or a shipped name "
                    f"({', '.join(shipped_checkpoints())}; a file of such a name here is ./NAME); "
                    "default: $HMRTA_CHECKPOINT, else default")
_RL = dict(rules="hmrta.rl.checkpoint_info:checkpoint_rules", needs=("torch",))
# rl-sample's default temperature, chosen on the dev missions (docs/training.md, "Sampling
# temperature"): the shipped policies are cloned (from greedy-coalition, from the solver's
# schedules), and at T = 1 their samples wander so far from their greedy decoding that the best of
# ten is often worse than it
SAMPLE_TEMPERATURE = 0.15
MAX_SAMPLES = 10_000  # rollouts per mission: more would run for hours on a large mission

METHODS: dict[str, Method] = {m.name: m for m in (
    Method("greedy", "the nearest admissible task, the cheap rule",
           "hmrta.baselines:solve_greedy", "hmrta.baselines:greedy_decider"),
    Method("greedy-coalition", "the task whose coalition can start first",
           "hmrta.baselines:solve_greedy_coalition", "hmrta.baselines:coalition_decider",
           rules="hmrta.baselines:COALITION_RULES"),
    Method("random", "a seeded random admissible task, for tests",
           "hmrta.baselines:solve_random", "hmrta.baselines:random_decider", rules="hmrta.baselines:RANDOM_RULES"),
    Method("rl", "learned policy, greedy decoding: RL(g.)",
           "hmrta.rl.inference:solve_rl", "hmrta.rl.inference:rl_decider", options=(CHECKPOINT,), **_RL),
    Method("rl-sample", "learned policy, N sampled rollouts, best kept: RL(s.N); live: sampled decoding",
           "hmrta.rl.inference:solve_rl_sample", "hmrta.rl.inference:sample_decider",
           options=(Option("samples", int, 10, f"sampled rollouts per mission, 1 to {MAX_SAMPLES} (offline; rl-sN "
                           "is shorthand)", minimum=1, maximum=MAX_SAMPLES, live=False),
                    Option("temperature", float, SAMPLE_TEMPERATURE,
                           "sampling temperature T (at least 0.01): softmax(logits / T); below 1 the samples stay "
                           "nearer the greedy decoding (docs/semantics.md#sampling-temperature)", minimum=0.01),
                    CHECKPOINT), **_RL),
    Method("rl-lookahead", "one-step lookahead over the policy's greedy continuations: better, and far "
           "slower (a whole rollout per admissible task at every decision: up to a minute or two at 20 tasks; "
           "a 50-task mission did not finish in 25 minutes): for small missions",
           "hmrta.rl.inference:solve_rl_lookahead", "hmrta.rl.inference:lookahead_decider",
           options=(CHECKPOINT,), **_RL),
    Method("cpsat", "anytime exact solver: list scheduler, annealing and CP-SAT; offline only",
           "hmrta.solvers.cpsat:solve_cpsat", None, rules=None,
           options=(Option("time_limit", float, 60.0, "seconds per mission (at least 0.01)", minimum=0.01),
                    Option("warm_start", str, "none", "start from this method's solution",
                           choices=("none", "greedy", "rl")),
                    Option("workers", int, 2, "parallel search workers (at least 1)", minimum=1),
                    Option("heuristic_seconds", float, None,
                           "seconds of list scheduling and annealing before CP-SAT, a part of the time limit (at "
                           "most --time-limit; default: a quarter of it)", minimum=0.0, within="time_limit")),
           needs=("ortools",)),
    Method("portfolio", "per mission, the best of several methods by simulation (rl with the default, broad "
           "and coalition-team checkpoints, greedy-coalition, greedy) on the mission as known at time 0 "
           "(tasks released later are not seen: the choice may then do worse than a rule on the rest); "
           "live missions run the chosen one",
           "hmrta.portfolio:solve_portfolio", None, rules=None, choose="hmrta.portfolio:select",
           options=(Option("candidates", str, "rl,greedy-coalition,rl@broad,rl@coalition-team,greedy",
                           "comma list of methods to choose from (METHOD@CHECKPOINT: an rl method with a checkpoint "
                           "of its own, a shipped name or a path; the checkpoint option applies to the others); "
                           "ties, and a mission with no task known at time 0, go to the first listed"),
                    CHECKPOINT)),
)}


def _resolve(target: str | Callable) -> Any:
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


class UnknownMethod(MethodError):
    """A method name that is not in :data:`METHODS` (nor a shorthand of one)."""


def get(name: str) -> Method:
    """The record of ``name`` (not a shorthand), or UnknownMethod listing the known names."""
    try:
        return METHODS[name]
    except KeyError:
        raise UnknownMethod(f"unknown method {name!r} (expected one of {', '.join(METHODS)}, or rl-sN)") from None


def parse(spec: str) -> tuple[str, dict[str, Any]]:
    """A method spec -> (name, options it implies): 'rl-s10' -> ('rl-sample', {'samples': 10});
    ``METHOD@CHECKPOINT`` runs a method that takes a checkpoint with that one (a shipped name such
    as ``broad``, or a path): 'rl@broad' -> ('rl', {'checkpoint': 'broad'})."""
    base, at, checkpoint = spec.partition("@")
    if at and not base.strip():
        raise UnknownMethod(f"{spec}: expected a method before '@' (METHOD@CHECKPOINT, e.g. rl@broad)")
    m = re.fullmatch(r"rl-s(\d+)", base)
    name, implied = ("rl-sample", {"samples": int(m.group(1))}) if m else (base, {})
    method = get(name)
    if m:  # rl-s0 is no method, offline or live
        implied["samples"] = method.option("samples").coerce(base, implied["samples"])
    if at:
        if method.option("checkpoint") is None:
            raise MethodError(f"{spec}: method {name} takes no checkpoint (METHOD@CHECKPOINT is for "
                              f"{', '.join(k for k, v in METHODS.items() if v.option('checkpoint'))})")
        if not checkpoint.strip():
            raise MethodError(f"{spec}: expected a checkpoint after '@' (a shipped name such as broad, or a path)")
        implied["checkpoint"] = checkpoint
    return name, implied


def label(name: str, options: dict[str, Any] | None = None, implied: dict[str, Any] | None = None) -> str:
    """How results name a method: 'rl-sample' with samples=N -> 'rl-sN' (the paper's RL(s.N));
    with a checkpoint of its own (``implied`` by the spec) '@CHECKPOINT' is appended."""
    out = name
    if name == "rl-sample":
        out = f"rl-s{(options or {}).get('samples') or get(name).option('samples').default}"
    if implied and implied.get("checkpoint"):
        out += f"@{implied['checkpoint']}"
    return out


def options_for(spec: str, options: dict[str, Any]) -> dict[str, Any]:
    """Of shared options (e.g. a bench over several methods, a portfolio's options), those method
    ``spec`` takes; a spec that names its own checkpoint (``rl@broad``) keeps it over a shared one."""
    name, implied = parse(spec)
    m = get(name)
    return {k: v for k, v in options.items()
            if m.option(k) is not None and not (k == "checkpoint" and "checkpoint" in implied)}


def _merge(m: Method, implied: dict[str, Any], options: dict[str, Any], live: bool = False) -> dict[str, Any]:
    """The options of a run: those implied by a shorthand (``rl-s10``: samples=10) and those
    given. A given option contradicting the shorthand is an error; live, a shorthand's offline-only
    options are dropped (live ``rl-sN`` decodes by sampling, there are no rollouts to keep)."""
    given = {k: v for k, v in options.items() if v is not None}
    for k, v in implied.items():
        if k in given and given[k] != v:
            raise MethodError(f"{label(m.name, implied, implied)} means {k}={v}, but {k}={given[k]} was given too")
    if live:
        implied = {k: v for k, v in implied.items() if m.option(k) is not None and m.option(k).live}
    return {**implied, **given}


def _needs(m: Method) -> None:
    for mod in m.needs:
        require(mod, f"method {m.name}")


def check_options(method: str, options: dict[str, Any]) -> dict[str, Any]:
    """The typed options of an offline run of ``method`` (a name or shorthand): those its shorthand
    implies and those given, each checked (MethodError naming the method and the option)."""
    name, implied = parse(method)
    m = get(name)
    return m.check(_merge(m, implied, options))


def check_instance(method: str, inst) -> None:
    """MethodError unless ``method`` can plan ``inst``: an offline solver cannot plan a mission
    whose tasks or robots change over time, and the learned policy takes at most 5 skills."""
    from .families import MAX_SKILLS  # the learned policy's K_MAX (hmrta.rl.features), without torch

    name = parse(method)[0]
    m = get(name)
    if m.decide is None and m.choose is None and getattr(inst, "dynamic", False):
        raise MethodError(f"method {name} is an offline solver: it cannot plan a scenario whose tasks or robots "
                          f"change over time (use portfolio, greedy, greedy-coalition or an rl method)")
    if m.rules == _RL["rules"] and inst.skills > MAX_SKILLS:
        raise MethodError(f"method {name}: the learned policy handles at most {MAX_SKILLS} skills, the mission "
                          f"has {inst.skills} (greedy, greedy-coalition, cpsat and portfolio take any number)")


def check_runnable(method: str, inst) -> None:
    """MissingDependency unless ``method``'s optional dependencies are installed, MethodError
    unless it can plan ``inst`` (:func:`check_instance`): what :func:`solve` checks before any work."""
    check_instance(method, inst)
    _needs(get(parse(method)[0]))


def _progress_for(fn: Callable, progress: Callable | None) -> dict[str, Any]:
    """``{"progress": progress}`` for a solver or chooser that reports progress, else nothing."""
    return {"progress": progress} if progress is not None and "progress" in inspect.signature(fn).parameters else {}


_KEEP_BEST = contextvars.ContextVar("hmrta_keep_best_on_interrupt", default=False)


@contextlib.contextmanager
def keep_best_on_interrupt() -> Iterator[None]:
    """Within it, an anytime method (``cpsat``) stopped by a Ctrl-C (KeyboardInterrupt) ends its
    solve with the best solution found so far, marked ``extra["interrupted"]``, instead of raising
    (once it has a first solution); every other method raises as usual. ``hmrta solve`` solves
    inside it; ``hmrta bench`` does not (nothing cut short is cached)."""
    token = _KEEP_BEST.set(True)
    try:
        yield
    finally:
        _KEEP_BEST.reset(token)


def keeping_best() -> bool:
    """Whether the solve runs inside :func:`keep_best_on_interrupt`."""
    return _KEEP_BEST.get()


def solve(inst, method: str, seed: int = 0, progress: Callable | None = None, **options: Any):
    """Solve ``inst`` with ``method`` (a name or shorthand) -> Solution (``sol.method`` = its label).
    ``progress`` (optional) is passed to solvers that report progress."""
    name, implied = parse(method)
    m = get(name)
    opts = check_options(method, options)
    check_runnable(method, inst)
    fn = _resolve(m.solve)
    sol = fn(inst, seed=seed, **opts, **_progress_for(fn, progress))
    sol.method = label(name, opts, implied)
    sol.extra["instance_sha256"] = inst.fingerprint  # the mission it plans (hmrta.solution.check_solution)
    return sol


def rules(method: str, **options: Any):
    """The state-machine rules ``method`` runs under (for rl methods: its checkpoint's, read from
    the checkpoint's config without building the network or importing torch)."""
    name, _ = parse(method)
    m = get(name)
    if m.rules is None:
        raise MethodError(f"method {name} has no fixed rules (it has no per-decision form; live methods: "
                          f"{', '.join(live_methods())})")
    opts = m.check({k: v for k, v in options.items() if v is not None and k == "checkpoint"})
    r = _resolve(m.rules)
    return r(**opts) if callable(r) else r


def decider(method: str, seed: int = 0, **options: Any):
    """A per-decision policy for live use (ROS agents): ``(decide, rules)`` where
    ``decide(state) -> node`` and ``rules`` are the state-machine rules it must run under."""
    name, implied = parse(method)
    m = get(name)
    if m.decide is None:
        raise MethodError(f"method {name} has no per-decision form (live methods: {', '.join(live_methods())})")
    opts = m.check(_merge(m, implied, options, live=True), live=True)
    _needs(m)
    return _resolve(m.decide)(seed=seed, **opts), rules(name, **opts)


def live_methods() -> list[str]:
    return [k for k, v in METHODS.items() if v.decide is not None]


def mission_methods() -> list[str]:
    """Methods a live mission can run: those with a per-decision form, and those that choose one
    per mission (see :func:`resolve`)."""
    return [k for k, v in METHODS.items() if v.decide is not None or v.choose is not None]


def resolve(inst, method: str, seed: int = 0, progress: Callable | None = None,
            **options: Any) -> tuple[str, dict[str, Any], dict | None]:
    """The live method a mission runs: ``(name, its options, None)`` for a method with a
    per-decision form; for a method that chooses per mission (portfolio), the chosen method, the
    options it takes and ``{candidate: makespan}`` of the choice (``progress`` is passed to the
    choice, as :func:`solve` passes it to a solver)."""
    name, implied = parse(method)
    m = get(name)
    if m.decide is not None:
        opts = m.check(_merge(m, implied, options, live=True), live=True)
        check_instance(method, inst)  # before any process starts
        return name, opts, None
    if m.choose is None:
        raise MethodError(f"method {name} has no per-decision form (live missions run: "
                          f"{', '.join(mission_methods())})")
    chosen, opts, scores = choose_live(inst, method, seed, progress, **options)
    return (*adopt(chosen, opts), scores)


def choose_live(inst, method: str, seed: int = 0, progress: Callable | None = None,
                **options: Any) -> tuple[str, dict[str, Any], dict[str, float]]:
    """For a method that chooses per mission (portfolio): ``(the chosen candidate's spec, e.g.
    'rl@coalition-team', the chooser's own options, {candidate: makespan})``. The live method is
    ``live_spec(spec, options)``; the spec is what a task board publishes as the mission's method,
    so that agents started with the chooser run the one chosen (:func:`adopt`)."""
    name, implied = parse(method)
    m = get(name)
    if m.choose is None:
        raise MethodError(f"method {name} does not choose per mission")
    opts = m.check(_merge(m, implied, options))
    _needs(m)
    choose = _resolve(m.choose)
    chosen, scores = choose(inst, seed=seed, **opts, **_progress_for(choose, progress))
    return chosen, opts, scores


def live_label(name: str, options: dict[str, Any]) -> str:
    """How a live method is named in a mission (the board's ``method``): its name, with
    ``@CHECKPOINT`` when a checkpoint is given (``rl@broad``, ``rl@/path/x.pt``), so that agents
    can tell that they run the mission's method and network (:func:`adopt` reads it back)."""
    ck = options.get("checkpoint")
    return f"{name}@{ck}" if ck else name


def chooses(method: str) -> bool:
    """Whether ``method`` (a spec) chooses a live method per mission (portfolio) instead of
    having a per-decision form of its own."""
    return get(parse(method)[0]).choose is not None


def adopt(spec: str, options: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """The live (name, options) an agent started with a chooser (portfolio) runs once its board
    names the chosen candidate ``spec`` (the mission's method): the spec's own checkpoint
    (``rl@broad``) wins; the agent's other options that the chosen method takes apply (its
    ``checkpoint``, as the board's applied to the candidates); the rest are the chooser's and are
    dropped. MethodError for a spec that is no live method."""
    if get(parse(spec)[0]).decide is None:
        raise MethodError(f"the mission's method {spec} has no per-decision form (live methods: "
                          f"{', '.join(live_methods())})")
    return live_spec(spec, options)  # (of the options, those the method takes)


def checkpoint_of(name: str, options: dict[str, Any]) -> dict[str, str] | None:
    """``{path, sha256}`` of the checkpoint live method ``name`` runs with ``options`` (its
    ``checkpoint``, else the default), as an offline solution records it; None for a method that
    takes none. CheckpointError (a MethodError) when it is not a file here. Torch-free."""
    if get(name).option("checkpoint") is None:
        return None
    from .rl.checkpoint_info import CheckpointError, checkpoint_path, existing, sha256

    path = existing(checkpoint_path(options.get("checkpoint")))
    try:
        return {"path": str(path), "sha256": sha256(path)}
    except OSError as e:
        raise CheckpointError(f"{path}: cannot read it ({e.strerror or type(e).__name__})") from None


def live_spec(spec: str, shared: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """The live (name, options) of a candidate ``spec`` given the chooser's ``shared`` options:
    its own checkpoint (``rl@broad``) wins over a shared one; live, ``rl-sN`` decodes by sampling
    (there are no rollouts to keep the best of)."""
    name, implied = parse(spec)
    m = get(name)
    return name, m.check(_merge(m, implied, options_for(spec, shared), live=True), live=True)


def live_options() -> dict[str, Option]:
    """Every option some live method takes (the ROS agents' and the launcher's parameters)."""
    out: dict[str, Option] = {}
    for m in METHODS.values():
        if m.decide is not None:
            for o in m.options:
                if o.live:
                    out.setdefault(o.name, o)
    return out


def node_options() -> dict[str, Option]:
    """Every option of a method a ROS node takes (``method`` parameter): the live options, then
    those of the methods that choose per mission (portfolio's ``candidates``)."""
    out = live_options()
    for m in METHODS.values():
        if m.choose is not None:
            for o in m.options:
                out.setdefault(o.name, o)
    return out


def help_text(names: list[str] | None = None) -> str:
    """'greedy: the nearest ... | rl: ... | ...' for --help."""
    return " | ".join(f"{k}: {METHODS[k].summary}" for k in (names or METHODS))


def add_arguments(parser, live: bool = False, default: str = "greedy", methods_flag: bool = False) -> None:
    """Add ``--method`` (or ``--methods``) and one flag per method option to an argparse parser;
    read them back with :func:`options_from_args`."""
    names = mission_methods() if live else list(METHODS)
    if methods_flag:
        parser.add_argument("--methods", default=default,
                            help=f"comma list of methods (default: {default}; rl-sN = rl-sample with N samples): "
                                 + help_text(names))
    else:
        parser.add_argument("--method", default=default, metavar="METHOD",
                            help=f"default: {default}. " + help_text(names) + "; rl-sN = rl-sample with N samples")
    seen: dict[str, tuple[Option, list[str]]] = {}
    for k in names:
        for o in METHODS[k].options:
            if o.live or not live or METHODS[k].decide is None:
                seen.setdefault(o.name, (o, []))[1].append(k)
    for name, (o, users) in seen.items():
        default_text = "" if o.default is None else f"; default {o.default}"
        parser.add_argument(o.flag, dest=name, type=o.type, default=None, choices=o.choices,
                            help=f"{', '.join(users)}: {o.help}{default_text}")


def options_from_args(args) -> dict[str, Any]:
    """The method options given on the command line (those left unset are omitted)."""
    names = {o.name for m in METHODS.values() for o in m.options}
    return {k: getattr(args, k) for k in names if getattr(args, k, None) is not None}
