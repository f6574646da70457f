"""The training config, typed: one dataclass per YAML section, validated on construction.

The sections and keys are those of the config files (``policy/configs/*.yaml``) and of the
resolved config every checkpoint stores, so every such file loads unchanged. A value of the wrong
type or range, or options that do not fit together, is a ValueError naming the key
(``train.lr: expected a number in (0, inf), got -1``); :func:`load_config` also rejects unknown
keys and names the file. :meth:`TrainConfig.to_dict` gives back the plain mapping (what
checkpoints store and ``config.yaml`` shows).
"""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..baselines import BASELINES
from ..core import Rules, parse_rules
from ..generators import ScenarioGenerator
from ..reading import finite, read_yaml, short
from .features import K_MAX
from .model import ModelConfig

CONFIG_VERSION = 1
DISTRIBUTIONS = ("ma-at", "broad", "mixed")  # train.distribution.generator
TEACHERS = BASELINES  # behaviour-cloning / lookahead teachers, by method name


def teacher_checkpoint(name: object) -> str | None:
    """The checkpoint of a behaviour-cloning teacher named ``rl@CHECKPOINT`` (a shipped name such
    as ``default``, or a path): that policy's greedy decoding labels the decisions (distilling it
    into the network trained, e.g. a narrower one). None for any other name."""
    if isinstance(name, str) and name.startswith("rl@") and name[3:].strip():
        return name[3:]
    return None


# ---- value checks: each returns an error text or None ------------------------------------------
def _paths(v: Any) -> list[str] | None:
    """A path or a non-empty list of paths, as a list (None: neither)."""
    v = [v] if isinstance(v, str) else v
    ok = isinstance(v, list) and v and all(isinstance(x, str) and x.strip() for x in v)
    return list(v) if ok else None


def _integer(lo: int, hi: int | None = None) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if isinstance(v, bool) or not isinstance(v, int) or v < lo or (hi is not None and v > hi):
            return f"expected an integer >= {lo}" + (f" and <= {hi}" if hi is not None else "")
        return None
    return check


def _number(lo: float, hi: float = math.inf, *, lo_open: bool = False, hi_open: bool = True,
            text: str | None = None) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        ok = finite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
        if ok:
            return None
        if text:
            return text
        lo_s, hi_s = ("(" if lo_open else "[") + f"{lo:g}", f"{hi:g}" + (")" if hi_open else "]")
        return f"expected a number in {lo_s}, {hi_s}"
    return check


def _boolean(v: Any) -> str | None:
    return None if isinstance(v, bool) else "expected true or false"


def _range(lo: int) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if (not isinstance(v, (list, tuple)) or len(v) != 2 or _integer(lo)(v[0]) or _integer(lo)(v[1])
                or v[0] > v[1]):
            return f"expected [low, high]: two integers with {lo} <= low <= high"
        return None
    return check


def _scale_range(v: Any) -> str | None:
    if (not isinstance(v, (list, tuple)) or len(v) != 2 or any(_number(1)(x) for x in v) or v[0] > v[1]):
        return "expected [low, high]: two numbers with 1 <= low <= high"
    return None


def _optional(check: Callable[[Any], str | None]) -> Callable[[Any], str | None]:
    def opt(v: Any) -> str | None:
        err = check(v)
        return None if v is None or err is None else err + " (or null)"
    return opt


def _name(v: Any) -> str | None:
    if not isinstance(v, str) or not v or len(v) > 100 or not all(c.isalnum() or c in "._+-" for c in v) \
            or v.startswith("."):
        return "expected a run name: letters, digits, '.', '_', '+' or '-' (it names the run folder)"
    return None


def _curriculum(v: Any) -> str | None:
    if not isinstance(v, list):
        return "expected a list of {until: ITERATION, tasks: [low, high]} stages"
    for i, stage in enumerate(v):
        if not isinstance(stage, dict) or set(stage) - {"until", "tasks"} or "tasks" not in stage:
            return f"stage {i}: expected {{until: ITERATION, tasks: [low, high]}}, got {short(stage)}"
        if _optional(_integer(0))(stage.get("until")) or _range(1)(stage["tasks"]):
            return f"stage {i}: expected until an integer >= 0 (or null) and tasks [low, high] >= 1, " \
                   f"got {short(stage)}"
    return None


def _rows(v: Any) -> str | None:
    if not isinstance(v, list) or not v:
        return "expected a non-empty list of [agents, species, tasks, skills, count] rows"
    for i, row in enumerate(v):
        if not isinstance(row, list) or len(row) != 5 or any(_integer(1)(x) for x in row):
            return f"row {i}: expected [agents, species, tasks, skills, count], five integers >= 1, got {short(row)}"
        a, sp, m, k, n = row
        if k > K_MAX:
            return f"row {i}: skills {k}: the policy handles at most {K_MAX}"
        try:
            ScenarioGenerator("MA-AT", a, sp, m, k)
        except ValueError as e:
            return f"row {i}: {e}"
    return None


_SEED = _integer(0, 2**63 - 1)


def _validate(obj: Any, prefix: str) -> None:
    """Run the ``check`` of every field of a section (field metadata); ValueError naming the key."""
    for f in dataclasses.fields(obj):
        check = f.metadata.get("check")
        if check is None:
            continue
        v = getattr(obj, f.name)
        err = check(v)
        if err:
            raise ValueError(f"{prefix}{f.name}: {err}" + ("" if " got " in err else f", got {short(v)}"))


def _f(default: Any, check: Callable[[Any], str | None]) -> Any:
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: copy.deepcopy(default), metadata={"check": check})
    return field(default=default, metadata={"check": check})


def _section(cls: type) -> Any:
    return field(default_factory=cls)


# ---- sections ------------------------------------------------------------------------------------
@dataclass
class Distribution:
    """``train.distribution``: the training missions. ``generator: ma-at`` (the paper's: task,
    species and robots-per-species ranges), ``broad`` (:class:`hmrta.families.BroadGenerator`
    over the ``tasks`` range: every family axis, teams grown by a factor in ``team_scale``;
    ``species``, ``per_species`` and ``skills`` unused) or ``mixed``: each mission from one of
    ``broad``, ``ma-at`` and the single-skill teams (:class:`hmrta.rl.schedules.SingleSkillTraining`)
    with equal odds, all over the ``tasks`` range."""
    generator: str = _f("ma-at", lambda v: None if v in DISTRIBUTIONS else "expected ma-at, broad or mixed")
    tasks: list = _f([15, 50], _range(1))
    species: list = _f([3, 5], _range(1))
    per_species: list = _f([3, 5], _range(1))
    skills: int = _f(5, _integer(1, K_MAX))
    # broad: the factor range of hmrta.families.BroadGenerator.team_scale ([1, 1]: its own team sizes)
    team_scale: list = _f([1, 1], _scale_range)

    def __post_init__(self) -> None:
        _validate(self, "train.distribution.")
        if self.generator == "ma-at" and [float(x) for x in self.team_scale] != [1.0, 1.0]:
            raise ValueError(f"train.distribution.team_scale: grows the teams of broad missions only "
                             f"(generator broad or mixed), got {short(self.team_scale)} with generator ma-at")
        if self.generator in ("ma-at", "mixed") and self.species[1] > 2 ** self.skills - 1:
            raise ValueError(f"train.distribution.species: at most {2 ** self.skills - 1} species have distinct "
                             f"trait vectors with {self.skills} skills, got {short(self.species)}")


@dataclass
class SelfImitation:
    """``train.sil``: self-imitation of the best of the beta rollouts (coef 0 and steps 0: off)."""
    coef: float = _f(0.0, _number(0))
    steps: int = _f(0, _integer(0))
    batch: int = _f(512, _integer(1))
    buffer: int = _f(16, _integer(1))

    def __post_init__(self) -> None:
        _validate(self, "train.sil.")


@dataclass
class ReinforceConfig:
    """``train``: REINFORCE, and the settings every phase shares (t_max, amp, grad_clip, ema,
    distribution, curriculum)."""
    iterations: int = _f(2000, _integer(0))
    max_minutes: float | None = _f(None, _optional(_number(0, lo_open=True)))
    instances_per_iter: int = _f(8, _integer(1))
    rollouts: int = _f(10, _integer(1))
    lr: float = _f(1.0e-4, _number(0, lo_open=True))
    lr_decay: float = _f(0.98, _number(0, 1, lo_open=True, hi_open=False))
    lr_decay_every: int = _f(100, _integer(1))
    grad_clip: float = _f(1.0, _number(0, lo_open=True))
    t_max: float = _f(1000.0, _number(0, lo_open=True))
    rescore_chunk: int = _f(2048, _integer(1))
    # fraction of decisions re-scored for the gradient (unbiased, 1/frac weights)
    rescore_fraction: float = _f(1.0, _number(0, 1, lo_open=True, hi_open=False))
    temperature: float = _f(1.0, _number(0, lo_open=True))  # collection samples softmax(logits / T)
    entropy_coef: float = _f(0.0, _number(0))  # entropy bonus (of the tempered policy) in the loss
    # advantage of a rollout: "raw" (return - the mean of its instance's beta returns) or "relative"
    # (the same divided by that mean cost: missions of different time scales weigh alike)
    advantage: str = _f("raw", lambda v: None if v in ("raw", "relative") else "expected raw or relative")
    amp: bool = _f(True, _boolean)  # bfloat16 autocast, collection and re-scoring, CPU only (a GPU: float32)
    # > 0: decay of an exponential moving average of the weights (every phase's updates), which
    # validation scores, best.pt keeps and export ships (0: the raw weights)
    ema: float = _f(0.0, _number(0, 1, text="expected a decay in [0, 1)"))
    distribution: Distribution = _section(Distribution)
    curriculum: list = _f([], _curriculum)  # [{until: ITER, tasks: [lo, hi]}, ...] narrows the task range early on
    sil: SelfImitation = _section(SelfImitation)

    def __post_init__(self) -> None:
        _validate(self, "train.")
        if self.iterations > 0 and self.rollouts < 2:
            raise ValueError(f"train.rollouts: expected at least 2 when train.iterations > 0, got {self.rollouts} "
                             f"(REINFORCE's baseline is the mean return of a mission's rollouts: with one rollout "
                             f"every advantage is 0 and nothing is learned)")


@dataclass
class DistillConfig:
    """``distill``: lookahead distillation (one-step lookahead policy improvement)."""
    iterations: int = _f(0, _integer(0))
    instances_per_iter: int = _f(8, _integer(1))
    snapshot_prob: float = _f(0.1, _number(0, 1, hi_open=False))
    steps: int = _f(4, _integer(0))
    batch: int = _f(512, _integer(1))
    buffer: int = _f(16, _integer(1))
    lr: float = _f(1.0e-4, _number(0, lo_open=True))
    tau: float = _f(0.0, _number(0))  # 0: hard target (best action); > 0: soft target softmax(-(cost - best) / tau)
    tasks: list | None = _f(None, _optional(_range(1)))  # task range (None: the training distribution)
    teacher: str = "policy"  # branches finished by: policy (own greedy decoding) | greedy | greedy-coalition

    def __post_init__(self) -> None:
        _validate(self, "distill.")
        t = self.teacher
        if not isinstance(t, str) or t not in ("policy", *TEACHERS):
            raise ValueError(f"distill.teacher: expected one of policy, {', '.join(TEACHERS)}, got {short(t)}")


@dataclass
class PretrainConfig:
    """``pretrain``: behaviour cloning of a baseline, with DAgger and expert iteration."""
    iterations: int = _f(0, _integer(0))
    instances_per_iter: int = _f(16, _integer(1))
    lr: float = _f(1.0e-3, _number(0, lo_open=True))
    epochs: int = _f(2, _integer(1))
    batch: int = _f(512, _integer(1))
    # whose choices are cloned: a baseline (greedy | greedy-coalition), or rl@CHECKPOINT: a
    # checkpoint's greedy decoding (a shipped name or a path; distillation into this network)
    teacher: str = "greedy"
    # share of instances whose visited states come from the policy's greedy rollout
    dagger: float = _f(0.0, _number(0, 1, hi_open=False, text="expected a share in [0, 1]"))
    # who labels them: ``teacher`` at every state the policy visits, or ``solver``: the policy
    # drives to a random decision, the solver plans the rest from there (hmrta.solvers.fromstate,
    # ``dagger_evals`` annealing decodes) and its plan labels every decision from there on
    dagger_teacher: str = _f("teacher", lambda v: None if v in ("teacher", "solver") else "expected teacher or solver")
    dagger_evals: int = _f(2000, _integer(0))
    # > 0: soft targets; greedy-coalition: from its start estimates; rl@CHECKPOINT: its own
    # distribution softmax(logits / tau)
    tau: float = _f(0.0, _number(0))
    # expert iteration: > 0 policy samples compete with the teacher's trajectory, the best is cloned
    samples: int = _f(0, _integer(0))
    temperature: float = _f(1.0, _number(0, lo_open=True))
    # what ranks the pool: ``return`` (-T - W, the REINFORCE reward) or ``makespan`` (the mission's
    # objective; a failed episode counts T_max, ties keep the teacher)
    select: str = _f("return", lambda v: None if v in ("return", "makespan") else "expected return or makespan")
    # the solver as teacher: a schedules dataset, or a list of them drawn from as one (hmrta
    # schedules; rl/schedules.py, relative paths from the working directory). Teacher-driven
    # missions come from it and are labelled by their routes; where a route's choice is not
    # admissible, and on DAgger states, ``teacher`` labels.
    schedules: Any = _f(None, _optional(lambda v: None if _paths(v) else "expected a path or a list of paths"))
    # with schedules: that many missions per iteration are drawn from train.distribution as well
    # (larger missions than the solver can schedule), driven and labelled by ``teacher`` (and DAgger)
    generated: int = _f(0, _integer(0))
    # who drives the missions drawn from train.distribution (with schedules: the ``generated``
    # ones; without: all of them): ``teacher`` (labelled by it), or ``policy``: its own greedy
    # decoding competes with the samples (needs samples > 0) and a mission teaches only where a
    # sample beats it (self-improvement: the labels are the winning sample's decisions)
    generated_teacher: str = _f("teacher",
                                lambda v: None if v in ("teacher", "policy") else "expected teacher or policy")
    # what one unit of the loss is: a label (every decision counts once, so a mission of hundreds
    # of decisions outweighs a small one) or a mission (its labels share one unit)
    label_weight: str = _f("label", lambda v: None if v in ("label", "mission") else "expected label or mission")

    @property
    def schedule_files(self) -> list[str]:
        """``schedules`` as a list of paths (empty: none)."""
        return _paths(self.schedules) or []

    def __post_init__(self) -> None:
        _validate(self, "pretrain.")
        if self.generated and self.schedules is None:
            raise ValueError("pretrain.generated: adds generated missions to pretrain.schedules' (set schedules, "
                             "or use instances_per_iter without them)")
        if self.label_weight == "mission" and self.samples:
            raise ValueError("pretrain.label_weight: mission is not defined with expert iteration (samples > 0: a "
                             "winning sample's labels replace its mission's)")
        if self.schedules is not None and self.tau > 0:
            raise ValueError("pretrain.tau: soft targets are not defined for pretrain.schedules (use tau: 0)")
        if not isinstance(self.teacher, str) or (self.teacher not in TEACHERS and not teacher_checkpoint(self.teacher)):
            raise ValueError(f"pretrain.teacher: expected one of {', '.join(TEACHERS)} or rl@CHECKPOINT (a shipped "
                             f"checkpoint's name or a path), got {short(self.teacher)}")
        if self.tau > 0 and not (hasattr(TEACHERS.get(self.teacher), "estimates") or teacher_checkpoint(self.teacher)):
            raise ValueError(f"pretrain.tau: soft targets need a teacher with start estimates "
                             f"(greedy-coalition) or a checkpoint teacher (rl@CHECKPOINT), not {self.teacher!r}")
        if self.samples and self.tau > 0:
            raise ValueError("pretrain.samples needs hard targets (pretrain.tau: 0)")
        if self.generated_teacher == "policy" and not self.samples:
            raise ValueError("pretrain.generated_teacher: policy needs policy samples to compete with "
                             "(pretrain.samples > 0)")


@dataclass
class ValidationConfig:
    """``validation``: RL(g.) on a fixed set of MA-AT rows every ``every`` iterations of a phase."""
    every: int = _f(25, _integer(1))
    seed: int = _f(990001, _SEED)
    rows: list = _f([[9, 3, 20, 3, 16], [25, 5, 50, 5, 16]], _rows)
    # > 0: that many broad-distribution missions (hmrta.families.BroadGenerator, 10-50 tasks) join
    # the validation set
    broad: int = _f(0, _integer(0))
    # > 0: that many single-skill missions (SA-AT and SA-BT teams, rl/schedules.py's
    # SingleSkillTraining, 10-50 tasks) join the validation set
    single_skill: int = _f(0, _integer(0))
    # > 0: that many missions of every mission-family row up to 50 tasks (hmrta.families: the
    # generators of ``hmrta bench --suite families``, drawn at the validation seed, never the
    # suite's test seed) join the validation set, so that checkpoints are chosen on every family axis
    families: int = _f(0, _integer(0))
    # what best.pt keeps the lowest of: the mean makespan, or the mean ratio of the makespan to
    # greedy-coalition's on the same mission (comparable across missions of different time scales)
    metric: str = _f("makespan", lambda v: None if v in ("makespan", "ratio") else "expected makespan or ratio")

    def __post_init__(self) -> None:
        _validate(self, "validation.")


@dataclass
class CheckpointConfig:
    """``checkpoint``: last.pt every ``every`` iterations of a phase (and on exit)."""
    every: int = _f(10, _integer(1))

    def __post_init__(self) -> None:
        _validate(self, "checkpoint.")


@dataclass
class TrainConfig:
    """A whole training config (the YAML file's top level)."""
    version: int = CONFIG_VERSION
    name: str = _f("default", _name)
    seed: int = _f(0, _SEED)
    model: ModelConfig = field(default_factory=lambda: ModelConfig(ff_hidden=128))
    rules: dict = field(default_factory=lambda: {"max_open": 2, "safety": True})
    train: ReinforceConfig = _section(ReinforceConfig)
    distill: DistillConfig = _section(DistillConfig)
    pretrain: PretrainConfig = _section(PretrainConfig)
    validation: ValidationConfig = _section(ValidationConfig)
    checkpoint: CheckpointConfig = _section(CheckpointConfig)

    def __post_init__(self) -> None:
        if type(self.version) is not int or self.version != CONFIG_VERSION:
            raise ValueError(f"version: expected {CONFIG_VERSION}, got {short(self.version)}")
        _validate(self, "")
        if not isinstance(self.model, ModelConfig):
            raise ValueError(f"model: expected a model config, got {short(self.model)}")
        ModelConfig.from_dict(self.model.to_dict())
        if not isinstance(self.rules, dict):
            raise ValueError(f"rules: expected a mapping, got {type(self.rules).__name__}")
        self.rule_set()

    def rule_set(self) -> Rules:
        """State-machine rules of the config (the same in training and at inference). A config
        names only some rules (max_open, safety); the others take their defaults."""
        return parse_rules({**Rules().to_dict(), **self.rules}, "rules")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "config") -> "TrainConfig":
        """A config from a complete mapping (a resolved config, e.g. ``defaults()`` updated);
        ValueError ``<where>: <key>: ...`` naming the key."""
        try:
            return _build(cls, d, "")
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None

    @classmethod
    def coerce(cls, cfg: "TrainConfig | dict", where: str = "config") -> "TrainConfig":
        return cfg if isinstance(cfg, TrainConfig) else cls.from_dict(deep_update(defaults(), cfg), where)


def _build(cls: type, d: Any, prefix: str) -> Any:
    if not isinstance(d, dict):
        raise ValueError(f"{prefix.rstrip('.')}: expected a mapping, got {type(d).__name__}")
    names = {f.name: f for f in dataclasses.fields(cls)}
    for k in d:
        if k not in names:
            raise ValueError(f"unknown key {short(prefix + (k if isinstance(k, str) else short(k)))} "
                             f"(expected one of {sorted(names)})")
    kw = {}
    for k, v in d.items():
        sub = names[k].default_factory  # type: ignore[misc]
        if k == "model" and cls is TrainConfig:
            kw[k] = ModelConfig.from_dict(v, "model")
        elif dataclasses.is_dataclass(sub):
            kw[k] = _build(sub, v, f"{prefix}{k}.")
        else:
            kw[k] = copy.deepcopy(v)
    return cls(**kw)


def defaults() -> dict:
    """Every key with its default value (a config file names only what it changes)."""
    return TrainConfig().to_dict()


def deep_update(base: dict, new: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in (new or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_update(out[k], v)
        else:
            out[k] = v
    return out


def _check_keys(raw: dict, ref: dict, path: Path, where: str) -> None:
    """Reject misspelt keys in every section (a silently ignored option is a wrong experiment)."""
    for k, v in raw.items():
        if k not in ref:
            raise ValueError(f"{path}: unknown key {short(where + (k if isinstance(k, str) else short(k)))} "
                             f"(expected one of {sorted(ref)})")
        if isinstance(ref[k], dict):
            if not isinstance(v, dict):
                raise ValueError(f"{path}: {where + k}: expected a mapping, got {type(v).__name__}")
            _check_keys(v, ref[k], path, f"{where}{k}.")


def check_config(cfg: dict, where: str = "config") -> None:
    """Every value of a resolved config of the right type and range (ValueError naming the key)."""
    TrainConfig.from_dict(cfg, where)


def load_config(path: str | Path, overrides: dict | None = None, given: str = "") -> dict:
    """Read and validate a training config (YAML): unknown keys, values of the wrong type or range
    and inconsistent options are a ValueError (an InputError for an unreadable file) that names
    the file and the key. ``overrides`` (a partial config, e.g. from the command line) replace the
    file's values before the check; ``given`` (e.g. ``--iterations``) then says where they came
    from in a message. Returns the resolved config (every key, defaults filled in)."""
    p = Path(path)
    raw = read_yaml(p)
    if raw is None:  # (a config that wants every default says so: {} or name: ...)
        raise ValueError(f"{p}: empty (expected a training config: a mapping of settings, as in the shipped "
                         f"configs; {{}} for every default)")
    if not isinstance(raw, dict):
        raise ValueError(f"{p}: expected a mapping, got {type(raw).__name__}")
    ref = defaults()
    _check_keys(raw, ref, p, "")
    version = raw.get("version", CONFIG_VERSION)
    if type(version) is not int or version != CONFIG_VERSION:
        raise ValueError(f"{p}: version: expected {CONFIG_VERSION}, got {short(raw['version'])}")
    cfg = deep_update(deep_update(ref, raw), overrides or {})
    check_config(cfg, f"{p} (with {given})" if overrides and given else str(p))
    return cfg


def rules_from(cfg: "TrainConfig | dict") -> Rules:
    """State-machine rules of a config (the same in training and at inference). Raises ValueError
    naming the rule (``rules.<key>: ...``) for a value of the wrong type or range."""
    rules = cfg.rules if isinstance(cfg, TrainConfig) else cfg["rules"]
    return parse_rules({**Rules().to_dict(), **rules}, "rules")
