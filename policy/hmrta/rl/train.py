"""REINFORCE with a shared mean baseline and the constrained flashforward mechanism (SPEC §5).

One iteration: draw one instance size from the (curriculum-narrowed) training distribution,
``instances_per_iter`` instances of that size, ``rollouts`` (beta) sampled rollouts of each, all
advanced together under ``torch.inference_mode``; then a single re-scoring forward (with gradient,
in chunks) over the recorded decisions gives the log-probabilities of the actions taken.
advantage = own return - mean of the instance's beta returns; loss = -mean(advantage * log p).

Optional self-imitation (``train.sil``, project choice): the best of each instance's beta rollouts
(by return) is also imitated with a cross-entropy term of weight ``coef`` in the same re-scoring
pass, and its decisions enter a small replay buffer (the last ``buffer`` iterations) on which
``steps`` extra cross-entropy minibatch steps are taken per iteration. This distils the
best-of-beta sample into the argmax policy (Oh et al. 2018, self-imitation learning) and is what
moves RL(g.) towards RL(s.N) on a CPU budget.

Optional rollout distillation (``distill``, project choice, run after the warm start): policy
improvement by one-step lookahead. From random decisions of the current policy's argmax rollouts,
every admissible action is tried and the mission completed by the same policy; the action with
the lowest cost T + W (ties: the policy's own choice) becomes a cross-entropy target, replayed
from a buffer of recent rounds. Each round imitates the rollout algorithm of the current policy,
which is never worse than the policy itself (Bertsekas' cost-improvement property). With
``distill.teacher`` set to a baseline (``greedy``, ``greedy-coalition``) the branches are finished
by that baseline instead: much cheaper labels, the rollout algorithm over the baseline.

Optional behaviour-cloning warm start (``pretrain``): cross-entropy on a baseline's choices
(``pretrain.teacher``: ``greedy`` or the coalition-aware ``greedy-coalition``), so that REINFORCE
starts from a baseline-level policy (project choice, recorded in the checkpoint config). With
``pretrain.dagger`` > 0 that share of the instances is driven by the policy's own argmax and
labelled by the teacher (DAgger, Ross et al. 2011), so the policy also learns to recover from its
own mistakes. With ``pretrain.samples`` > 0 (expert iteration, project choice) that many sampled
rollouts of the policy (``pretrain.temperature``) compete with the teacher's trajectory on each
teacher-driven instance, and the best of them by return is cloned: the targets are never worse
than the teacher, and where the policy won they are its own, learnable choices.

Checkpoints hold model, optimiser, learning-rate schedule, RNG states, counters, the resolved
config and the code version; ``--resume`` continues exactly.
"""
from __future__ import annotations

import copy
import csv
import functools
import math
import random
import subprocess
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import yaml

from ..baselines import BASELINES
from ..core import MissionState, Rules, parse_rules
from ..generators import ScenarioGenerator, TrainingGenerator
from ..instance import atomic_write_text
from ..reading import finite, read_yaml, short
from .checkpoint_file import check_optimizer, check_shapes, counter, load_checkpoint, weights
from .checkpoint_info import CheckpointError
from .features import K_MAX, collate, observe
from .model import ZERO_INIT_PARAMS, ModelConfig, PolicyNet
from .rollout import action_costs, best_action, returns, rollout

CONFIG_VERSION = 1
TEACHERS = BASELINES  # behaviour-cloning / lookahead teachers, by method name
DEFAULTS: dict[str, Any] = {
    "version": CONFIG_VERSION,
    "name": "default",
    "seed": 0,
    "model": ModelConfig(ff_hidden=128).to_dict(),
    "rules": {"max_open": 2, "safety": True},
    "train": {
        "iterations": 2000,
        "max_minutes": None,
        "instances_per_iter": 8,
        "rollouts": 10,
        "lr": 1.0e-4,
        "lr_decay": 0.98,
        "lr_decay_every": 100,
        "grad_clip": 1.0,
        "t_max": 1000.0,
        "rescore_chunk": 2048,
        "rescore_fraction": 1.0,  # fraction of decisions re-scored for the gradient (unbiased, 1/frac weights)
        "temperature": 1.0,  # collection samples softmax(logits / T); the gradient is for that policy
        "entropy_coef": 0.0,  # entropy bonus (of the tempered policy) in the loss
        "amp": True,  # bfloat16 autocast for collection and re-scoring (CPU); evaluation is float32
        "ema": 0.0,  # > 0: decay of an exponential moving average of the weights (every phase's updates),
        # which validation scores, best.pt keeps and export ships (0: the raw weights)
        "distribution": {"tasks": [15, 50], "species": [3, 5], "per_species": [3, 5], "skills": 5},
        "curriculum": [],  # [{until: ITER, tasks: [lo, hi]}, ...] narrows the task range early on
        # self-imitation of the best of the beta rollouts (coef 0 and steps 0: plain REINFORCE)
        "sil": {"coef": 0.0, "steps": 0, "batch": 512, "buffer": 16},
    },
    "distill": {"iterations": 0, "instances_per_iter": 8, "snapshot_prob": 0.1, "steps": 4, "batch": 512,
                "buffer": 16, "lr": 1.0e-4,
                "tau": 0.0,  # 0: hard target (best action); > 0: soft target softmax(-(cost - best) / tau)
                "tasks": None,  # task range of the distillation instances (None: the training distribution)
                "teacher": "policy"},  # branches finished by: policy (own argmax) | greedy | greedy-coalition
    "pretrain": {"iterations": 0, "instances_per_iter": 16, "lr": 1.0e-3, "epochs": 2, "batch": 512,
                 "teacher": "greedy",  # greedy | greedy-coalition (the baseline whose choices are cloned)
                 "dagger": 0.0,  # share of instances whose visited states come from the policy's argmax rollout
                 "tau": 0.0,  # > 0 (greedy-coalition): soft targets from its start estimates (see _soft_target)
                 # expert iteration: > 0 policy samples compete with the teacher's trajectory, the best is cloned
                 "samples": 0, "temperature": 1.0},
    "validation": {"every": 25, "seed": 990001, "rows": [[9, 3, 20, 3, 16], [25, 5, 50, 5, 16]]},
    "checkpoint": {"every": 10},
}


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


# value checks of every config key (section.key -> check); each returns an error text or None
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


_CHECKS: dict[str, Callable[[Any], str | None]] = {
    "name": _name, "seed": _integer(0, 2**63 - 1),
    "train.iterations": _integer(0), "train.max_minutes": _optional(_number(0, lo_open=True)),
    "train.instances_per_iter": _integer(1), "train.rollouts": _integer(1),
    "train.lr": _number(0, lo_open=True), "train.lr_decay": _number(0, 1, lo_open=True, hi_open=False),
    "train.lr_decay_every": _integer(1), "train.grad_clip": _number(0, lo_open=True),
    "train.t_max": _number(0, lo_open=True), "train.rescore_chunk": _integer(1),
    "train.rescore_fraction": _number(0, 1, lo_open=True, hi_open=False),
    "train.temperature": _number(0, lo_open=True), "train.entropy_coef": _number(0), "train.amp": _boolean,
    "train.ema": _number(0, 1, text="expected a decay in [0, 1)"),
    "train.distribution.tasks": _range(1), "train.distribution.species": _range(1),
    "train.distribution.per_species": _range(1), "train.distribution.skills": _integer(1, K_MAX),
    "train.curriculum": _curriculum,
    "train.sil.coef": _number(0), "train.sil.steps": _integer(0), "train.sil.batch": _integer(1),
    "train.sil.buffer": _integer(1),
    "distill.iterations": _integer(0), "distill.instances_per_iter": _integer(1),
    "distill.snapshot_prob": _number(0, 1, hi_open=False), "distill.steps": _integer(0),
    "distill.batch": _integer(1), "distill.buffer": _integer(1), "distill.lr": _number(0, lo_open=True),
    "distill.tau": _number(0), "distill.tasks": _optional(_range(1)),
    "pretrain.iterations": _integer(0), "pretrain.instances_per_iter": _integer(1),
    "pretrain.lr": _number(0, lo_open=True), "pretrain.epochs": _integer(0), "pretrain.batch": _integer(1),
    "pretrain.dagger": _number(0, 1, hi_open=False, text="expected a share in [0, 1]"),
    "pretrain.tau": _number(0), "pretrain.samples": _integer(0),
    "pretrain.temperature": _number(0, lo_open=True),
    "validation.every": _integer(1), "validation.seed": _integer(0, 2**63 - 1), "validation.rows": _rows,
    "checkpoint.every": _integer(1),
}


def check_config(cfg: dict, where: str = "config") -> None:
    """Every value of a resolved config of the right type and range (ValueError naming the key)."""
    def get(key: str) -> Any:
        v: Any = cfg
        for part in key.split("."):
            v = v[part]
        return v

    for key, check in _CHECKS.items():
        v = get(key)
        err = check(v)
        if err:
            raise ValueError(f"{where}: {key}: {err}" + ("" if " got " in err else f", got {short(v)}"))
    try:
        ModelConfig.from_dict(cfg["model"])
        rules_from(cfg)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    dist = cfg["train"]["distribution"]
    if dist["species"][1] > 2 ** dist["skills"] - 1:
        raise ValueError(f"{where}: train.distribution.species: at most {2 ** dist['skills'] - 1} species "
                         f"have distinct trait vectors with {dist['skills']} skills, got {short(dist['species'])}")
    p = cfg["pretrain"]
    if not isinstance(p["teacher"], str) or p["teacher"] not in TEACHERS:
        raise ValueError(f"{where}: pretrain.teacher: expected one of {', '.join(TEACHERS)}, got {short(p['teacher'])}")
    if p["tau"] > 0 and not hasattr(TEACHERS[p["teacher"]], "estimates"):
        raise ValueError(f"{where}: pretrain.tau: soft targets need a teacher with start estimates "
                         f"(greedy-coalition), not {p['teacher']!r}")
    if p["samples"] and p["tau"] > 0:
        raise ValueError(f"{where}: pretrain.samples needs hard targets (pretrain.tau: 0)")
    t = cfg["distill"]["teacher"]
    if not isinstance(t, str) or t not in ("policy", *TEACHERS):
        raise ValueError(f"{where}: distill.teacher: expected one of policy, {', '.join(TEACHERS)}, got {short(t)}")


def load_config(path: str | Path) -> dict:
    """Read and validate a training config (YAML): unknown keys, values of the wrong type or range
    and inconsistent options are a ValueError (an InputError for an unreadable file) that names
    the file and the key."""
    p = Path(path)
    raw = read_yaml(p) or {}
    if not isinstance(raw, dict):
        raise ValueError(f"{p}: expected a mapping, got {type(raw).__name__}")
    _check_keys(raw, DEFAULTS, p, "")
    version = raw.get("version", CONFIG_VERSION)
    if type(version) is not int or version != CONFIG_VERSION:
        raise ValueError(f"{p}: version: expected {CONFIG_VERSION}, got {short(raw['version'])}")
    cfg = deep_update(DEFAULTS, raw)
    check_config(cfg, str(p))
    return cfg


def code_version() -> str:
    try:
        root = Path(__file__).resolve().parents[3]
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=5)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "policy/hmrta"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return (out.stdout.strip() or "unknown") + ("-dirty" if dirty else "")
    except Exception:
        return "unknown"


def rules_from(cfg: dict) -> Rules:
    """State-machine rules of a config (the same in training and at inference). A config names
    only some rules (max_open, safety); the others take their defaults. Raises ValueError naming
    the rule (``rules.<key>: ...``) for a value of the wrong type or range."""
    return parse_rules({**Rules().to_dict(), **cfg["rules"]}, "rules")


def validation_set(cfg: dict) -> list:
    v = cfg["validation"]
    out = []
    for a, s, m, k, n in v["rows"]:
        out += ScenarioGenerator("MA-AT", a, s, m, k).generate(n, v["seed"])
    return out


class Trainer:
    def __init__(self, cfg: dict, run_dir: str | Path, device: str | None = None, log=print):
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.log = log
        seed = int(cfg["seed"])
        torch.manual_seed(seed)
        self.model = PolicyNet(ModelConfig(**cfg["model"])).to(self.device)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg["train"]["lr"])
        self.np_rng = np.random.default_rng(seed)
        self.torch_gen = torch.Generator().manual_seed(seed)
        self.iteration = 0
        self.pretrain_done = 0
        self.distill_done = 0
        self.episodes = 0
        self.decisions = 0
        self.best_val = math.inf
        self.greedy_val: float | None = None
        self.val_set = validation_set(cfg)
        self.train_rules = self.eval_rules = rules_from(cfg)
        self.sil_buffer: list[dict[str, torch.Tensor]] = []  # best-rollout decisions, not checkpointed
        self.distill_buffer: list[dict[str, torch.Tensor]] = []  # lookahead targets, not checkpointed
        self.ema: dict[str, torch.Tensor] | None = None  # averaged weights (train.ema > 0), from the first update

    # ---- checkpoints ---------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "config": self.cfg,
            "code_version": code_version(),
            "model": self.model.state_dict(),
            "ema": self.ema,
            "optimizer": self.opt.state_dict(),
            "iteration": self.iteration,
            "pretrain_done": self.pretrain_done,
            "distill_done": self.distill_done,
            "episodes": self.episodes,
            "decisions": self.decisions,
            "best_val": self.best_val,
            "greedy_val": self.greedy_val,
            "np_rng": self.np_rng.bit_generator.state,
            "torch_gen": self.torch_gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "py_rng": random.getstate(),
        }

    def save(self, path: Path) -> None:
        if not all(torch.isfinite(v).all() for sd in (self.model.state_dict(), self.ema or {}) for v in sd.values()):
            raise RuntimeError(f"refusing to save non-finite weights to {path}")
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)

    def load(self, path: Path, reseed: bool = False) -> None:
        """Restore a checkpoint (model, optimiser, averaged weights, counters, RNG streams, best
        validation). ``reseed``: keep this trainer's fresh RNG streams (from the config's seed) and
        its unset validation scores instead, for a second, independent continuation of the same
        checkpoint (possibly under other rules or another validation set).

        The file is unpickled weights-only (it cannot run code); anything missing, mistyped or not
        fitting this network is a CheckpointError naming the file and the field, raised before the
        trainer is changed."""
        ck = load_checkpoint(path, map_location=self.device)
        sd = weights(ck, "model", path)
        check_shapes(self.model, sd, path, "model", optional=ZERO_INIT_PARAMS)
        added = any(n not in sd for n in ZERO_INIT_PARAMS & set(self.model.state_dict()))  # e.g. travel_bias
        ema = weights(ck, "ema", path, required=False)
        if ema is not None and not added:
            check_shapes(self.model, ema, path, "ema")
        counters = {k: counter(ck, k, path) for k in
                    ("iteration", "pretrain_done", "distill_done", "episodes", "decisions")}
        best_val, greedy_val = ck.get("best_val", math.inf), ck.get("greedy_val")
        for k, v in (("best_val", best_val), ("greedy_val", greedy_val)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or v != v):  # v != v: NaN
                raise CheckpointError(f"{path}: {k}: expected a number, got {short(v)}")
        if "optimizer" in ck and not added:
            check_optimizer(ck["optimizer"], self.opt, path)
        model_before = copy.deepcopy(self.model.state_dict())
        opt_before = copy.deepcopy(self.opt.state_dict())
        try:
            self.model.load_state_dict(sd, strict=False)
            if "optimizer" in ck and not added:
                self.opt.load_state_dict(ck["optimizer"])
            rng = None
            if not reseed and "np_rng" in ck:  # random streams continue the checkpoint's run
                rng = (ck["np_rng"], *(t.cpu() if isinstance(t, torch.Tensor) else t  # (loaded onto self.device)
                                       for t in (ck["torch_gen"], ck["torch_rng"])), ck["py_rng"])
                # each state is tried on a throw-away generator before any stream is replaced
                np.random.default_rng().bit_generator.state = rng[0]
                torch.Generator().set_state(rng[1])
                torch.Generator().set_state(rng[2])  # the global CPU generator's state has the same layout
                random.Random().setstate(rng[3])
        except (ValueError, TypeError, KeyError, RuntimeError, AttributeError, IndexError, OverflowError) as e:
            self.model.load_state_dict(model_before)
            self.opt.load_state_dict(opt_before)
            first = (str(e).strip().splitlines() or [""])[0][:200]
            raise CheckpointError(f"{path}: not a resumable training checkpoint ({type(e).__name__}: {first})") from None
        self.ema = ema if self.cfg["train"]["ema"] > 0 and not added else None
        for k, v in counters.items():
            setattr(self, k, v)
        if not reseed:  # validation scores and random streams continue the checkpoint's run
            self.best_val = best_val
            self.greedy_val = greedy_val
            if rng is not None:
                self.np_rng.bit_generator.state = rng[0]
                self.torch_gen.set_state(rng[1])
                torch.set_rng_state(rng[2])
                random.setstate(rng[3])

    def export(self, path: Path, summary: dict | None = None) -> None:
        """Small inference checkpoint: weights + resolved config + code version + summary."""
        d = {"config": self.cfg, "code_version": code_version(), "iteration": self.iteration,
             "pretrain_done": self.pretrain_done, "distill_done": self.distill_done, "decisions": self.decisions,
             "episodes": self.episodes, "best_val": self.best_val, "greedy_val": self.greedy_val,
             "model": {k: v.detach().cpu() for k, v in self.policy_weights().items()}}
        if summary:
            d["summary"] = summary
        tmp = path.with_name(path.name + ".tmp")
        torch.save(d, tmp)
        tmp.replace(path)

    # ---- weight averaging ------------------------------------------------------------------------
    def _optimizer_step(self) -> None:
        """One optimiser update, then (``train.ema`` > 0) the moving average of the weights."""
        self.opt.step()
        decay = float(self.cfg["train"]["ema"])
        if decay <= 0:
            return
        with torch.no_grad():
            if self.ema is None:
                self.ema = {k: v.detach().clone() for k, v in self.model.state_dict().items()}
            else:
                for k, v in self.model.state_dict().items():
                    if v.is_floating_point():
                        self.ema[k].mul_(decay).add_(v.detach(), alpha=1.0 - decay)
                    else:
                        self.ema[k].copy_(v)

    def policy_weights(self) -> dict[str, torch.Tensor]:
        """The weights that are validated and shipped: the moving average when there is one."""
        return self.ema if self.ema is not None else self.model.state_dict()

    def eval_model(self) -> PolicyNet:
        """The network with ``policy_weights`` (the training model itself without averaging)."""
        if self.ema is None:
            return self.model.eval()
        m = copy.deepcopy(self.model)
        m.load_state_dict(self.ema)
        return m.eval()

    # ---- data --------------------------------------------------------------------------------
    def _lr(self) -> float:
        t = self.cfg["train"]
        return t["lr"] * t["lr_decay"] ** (self.iteration // t["lr_decay_every"])

    def _task_range(self) -> tuple[int, int]:
        t = self.cfg["train"]
        for stage in t["curriculum"]:
            if stage.get("until") is None or self.iteration < stage["until"]:
                return tuple(stage["tasks"])  # type: ignore[return-value]
        return tuple(t["distribution"]["tasks"])  # type: ignore[return-value]

    def _instances(self, n: int, task_range: tuple[int, int] | None = None) -> list:
        dist = self.cfg["train"]["distribution"]
        lo, hi = task_range or self._task_range()
        rng = self.np_rng
        s = int(rng.integers(dist["species"][0], dist["species"][1] + 1))
        per = int(rng.integers(dist["per_species"][0], dist["per_species"][1] + 1))
        m = int(rng.integers(lo, hi + 1))
        gen = ScenarioGenerator("MA-AT", s * per, s, m, dist["skills"])
        return [gen.sample(rng) for _ in range(n)]

    # ---- behaviour cloning warm start -----------------------------------------------------------
    def pretrain_step(self) -> dict:
        p = self.cfg["pretrain"]
        insts = self._instances(p["instances_per_iter"])
        obs, deciders, acts, soft = [], [], [], []
        teacher = TEACHERS[p["teacher"]]()
        tau = p["tau"]

        def label(st: MissionState) -> int:  # record the teacher's choice at st; returns it
            tf, af, mask, nodes, row = observe(st)
            n = teacher(st)
            hit = np.flatnonzero(nodes == n)
            if len(hit):  # (outside the observation window only on missions beyond the training scale)
                obs.append((tf, af, mask))
                deciders.append(row)
                acts.append(int(hit[0]))
                if tau > 0:
                    soft.append(self._soft_target(teacher, st, nodes, int(hit[0]), tau))
            return n

        on_policy, pool = [], []  # DAgger states; (teacher's finished state, its label range) per pooled instance
        for inst in insts:
            st = MissionState(inst, seed=int(self.np_rng.integers(2**31)), rules=self.train_rules)
            if self.np_rng.random() < p["dagger"]:
                on_policy.append(st)  # DAgger: the policy drives, the teacher labels
                continue
            first = len(acts)
            while not st.done:
                st.step(label(st))
            pool.append((st, first, len(acts)))
        self.model.eval()
        if on_policy:
            rollout(self.model, on_policy, sample=False,
                    before_step=lambda idx, o, nodes, act: [label(on_policy[i]) for i in idx])
        pool_stats = self._pool(pool, obs, deciders, acts) if p["samples"] and pool else {}
        for g in self.opt.param_groups:
            g["lr"] = p["lr"]
        self.model.train()
        n = len(acts)
        losses = []
        for _ in range(p["epochs"]):
            perm = self.np_rng.permutation(n)
            for lo in range(0, n, p["batch"]):
                idx = perm[lo:lo + p["batch"]]
                batch = {k: v.to(self.device) for k, v in collate([obs[i] for i in idx],
                                                                  [deciders[i] for i in idx]).items()}
                logits = self.model(**batch)  # [b, T]
                if tau > 0:  # [b, T] target distributions, zero-padded to the batch's rows
                    q = torch.zeros_like(logits)
                    for r, i in enumerate(idx):
                        q[r, :len(soft[i])] = torch.from_numpy(soft[i])
                    logp = torch.log_softmax(logits, -1).masked_fill(~batch["action_mask"], 0.0)  # [b, T]
                    loss = -(q * logp).sum(-1).mean()
                else:
                    target = torch.tensor([acts[i] for i in idx], device=self.device)
                    loss = torch.nn.functional.cross_entropy(logits, target)
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg["train"]["grad_clip"])
                self._optimizer_step()
                losses.append(loss.item())
        self.pretrain_done += 1
        return {"iteration": self.pretrain_done, "bc_loss": float(np.mean(losses)), "labels": n,
                "tasks": insts[0].n_tasks, "agents": insts[0].n_agents, **pool_stats}

    def _pool(self, pool: list[tuple[MissionState, int, int]], obs: list, deciders: list, acts: list) -> dict:
        """Expert iteration (``pretrain.samples``): ``samples`` sampled rollouts of the policy compete
        with the teacher's trajectory on each pooled instance; where a sample has the better return
        (-T - W), its decisions replace the teacher's labels of that instance. The targets are then
        never worse than the teacher and are, where the policy won, its own (learnable) choices.
        ``pool``: (the teacher's finished state, [first, end) of its labels) per instance; the other
        labels (DAgger's) are kept."""
        p, t = self.cfg["pretrain"], self.cfg["train"]
        S = int(p["samples"])
        states = [MissionState(st.inst, seed=st.seed, rules=self.train_rules) for st, _, _ in pool for _ in range(S)]
        traj = rollout(self.model, states, sample=True, generator=self.torch_gen, record=True,
                       amp=t["amp"] and self.device.type == "cpu", temperature=p["temperature"])
        self.episodes += len(states)
        self.decisions += traj.decisions
        R = returns(states, t["t_max"]).reshape(len(pool), S)  # [I, S]
        Rt = returns([st for st, _, _ in pool], t["t_max"])  # [I] the teacher's
        win = R.max(1) > Rt + 1e-9  # [I] a sample beats the teacher
        keep = np.ones(len(acts), dtype=bool)
        for (_, first, end), w in zip(pool, win):
            keep[first:end] = not w  # drop the teacher's labels where a sample won
        obs[:] = [o for o, k in zip(obs, keep) if k]
        deciders[:] = [d for d, k in zip(deciders, keep) if k]
        acts[:] = [a for a, k in zip(acts, keep) if k]
        best = torch.as_tensor(np.flatnonzero(win) * S + R.argmax(1)[win])  # winning episodes
        for o, a, e in zip(traj.obs, traj.actions, traj.episode):
            for r in torch.isin(e, best).nonzero()[:, 0].tolist():  # rows of this step from a winner
                n_t, n_a = int(o["task_valid"][r].sum()), int(o["agent_valid"][r].sum())
                obs.append((o["tasks"][r, :n_t].numpy(), o["agents"][r, :n_a].numpy(),
                            o["action_mask"][r, :n_t].numpy()))
                deciders.append(int(o["decider"][r]))
                acts.append(int(a[r]))
        mk_t = np.array([st.makespan for st, _, _ in pool])  # [I]
        mk_best = np.array([s.makespan for s in states])[np.arange(len(pool)) * S + R.argmax(1)]  # [I]
        return {"teacher_makespan": float(mk_t.mean()), "pool_makespan": float(np.where(win, mk_best, mk_t).mean()),
                "teacher_wins": float(1 - win.mean())}

    @staticmethod
    def _soft_target(teacher, st: MissionState, nodes: np.ndarray, row: int, tau: float) -> np.ndarray:
        """[1+W] half on the teacher's choice, half spread by its coalition-start estimates:
        softmax(-(start - earliest) / tau) over the admissible tasks in the observation."""
        q = np.zeros(len(nodes), dtype=np.float32)
        q[row] = 0.5
        cand, start, _ = teacher.estimates(st)
        pos = {int(n): r for r, n in enumerate(nodes)}
        rows = np.array([pos.get(1 + int(j), -1) for j in cand])  # [C] observation row of each candidate
        ok = (rows >= 0) & np.isfinite(start)
        if not ok.any():
            q[row] = 1.0
            return q
        w = np.exp(-(start[ok] - start[ok].min()) / tau)  # [C']
        q[rows[ok]] += 0.5 * w / w.sum()
        return q

    # ---- rollout distillation (one-step lookahead policy improvement) ---------------------------
    def distill_step(self) -> dict:
        d, t = self.cfg["distill"], self.cfg["train"]
        amp = t["amp"] and self.device.type == "cpu"
        insts = self._instances(d["instances_per_iter"], tuple(d["tasks"]) if d["tasks"] else None)
        states = [MissionState(inst, seed=int(self.np_rng.integers(2**31)), rules=self.train_rules)
                  for inst in insts]
        t0 = time.perf_counter()
        self.model.eval()
        rows: list[dict[str, torch.Tensor]] = []  # observation of each branched decision
        base: list[int] = []  # the policy's own action row there
        decisions: list[tuple[MissionState, np.ndarray, np.ndarray]] = []  # (state copy, nodes, mask)

        def branch(idx, obs, nodes, act):  # snapshot some decisions with more than one admissible action
            n_adm = obs["action_mask"].sum(1)  # [b]
            for j, i in enumerate(idx):
                if n_adm[j] > 1 and self.np_rng.random() < d["snapshot_prob"]:
                    rows.append({k: v[j] for k, v in obs.items()})
                    base.append(int(act[j]))
                    decisions.append((states[i].clone(), nodes[j], obs["action_mask"][j].numpy()))

        rollout(self.model, states, sample=False, amp=amp, before_step=branch)
        finisher = self.model if d["teacher"] == "policy" else TEACHERS[d["teacher"]]()
        costs, branches = action_costs(finisher, decisions, t["t_max"], amp=amp)  # [T] per branched decision
        target, gain, changed = [], [], 0
        for c, own in zip(costs, base):
            best_r = best_action(c, own)
            changed += best_r != own
            if d["tau"] > 0:  # [T] target distribution over action rows (0 where inadmissible)
                q = torch.softmax(torch.as_tensor(-(c - c.min()) / d["tau"]), 0).float()
            else:
                q = torch.zeros(len(c))
                q[best_r] = 1.0
            target.append(q)
            gain.append((c[own] - c.min()) / c[own])
        t_collect = time.perf_counter() - t0
        loss = math.nan
        if rows:
            entry = {k: torch.stack([r_[k] for r_ in rows]) for k in rows[0]}
            entry["target"] = torch.stack(target)  # [n, T] probabilities
            self.distill_buffer.append(entry)
            del self.distill_buffer[:-d["buffer"]]
            for g in self.opt.param_groups:
                g["lr"] = d["lr"]
            loss = self._replay_steps(self.distill_buffer, d["steps"], d["batch"], t["grad_clip"], t["amp"])
        self.distill_done += 1
        n_dec = sum(s.decisions for s in states) + sum(s.decisions for s in branches)
        self.decisions += n_dec
        self.episodes += len(states) + len(branches)
        return {"iteration": self.distill_done, "makespan": float(np.mean([s.makespan for s in states])),
                "success": float(np.mean([s.success for s in states])), "loss": loss,
                "lookahead_gain": float(np.mean(gain)) if gain else math.nan,
                "changed": changed / max(len(rows), 1), "labels": len(rows),
                "decisions_per_s": n_dec / max(t_collect, 1e-9), "tasks": insts[0].n_tasks,
                "agents": insts[0].n_agents, "seconds": time.perf_counter() - t0}

    # ---- REINFORCE -----------------------------------------------------------------------------
    def train_step(self) -> dict:
        t = self.cfg["train"]
        beta = t["rollouts"]
        insts = self._instances(t["instances_per_iter"])
        states = [MissionState(inst, seed=int(self.np_rng.integers(2**31)), rules=self.train_rules)
                  for inst in insts for _ in range(beta)]
        t0 = time.perf_counter()
        self.model.eval()
        traj = rollout(self.model, states, sample=True, generator=self.torch_gen, record=True,
                       amp=t["amp"] and self.device.type == "cpu", temperature=t["temperature"])
        t_collect = time.perf_counter() - t0
        R = returns(states, t["t_max"])  # [E]
        Rm = R.reshape(len(insts), beta)
        adv = (Rm - Rm.mean(1, keepdims=True)).reshape(-1)  # [E]
        adv_t = torch.tensor(adv, dtype=torch.float32, device=self.device)
        n_ep = len(states)
        # one re-scoring forward (with gradient) over all recorded decisions, in chunks
        for g in self.opt.param_groups:
            g["lr"] = self._lr()
        self.model.train()
        self.opt.zero_grad(set_to_none=True)
        keys = traj.obs[0].keys()
        allobs = {k: torch.cat([o[k] for o in traj.obs]) for k in keys}
        acts = torch.cat(traj.actions)  # [D]
        eps = torch.cat(traj.episode)  # [D]
        D = len(acts)
        sil = t["sil"]
        best_ep = torch.as_tensor(Rm.argmax(1) + beta * np.arange(len(insts)))  # [I] best rollout per instance
        is_best = torch.isin(eps, best_ep)  # [D]
        n_best = max(int(is_best.sum()), 1)
        # re-score a random fraction of the decisions (the best rollouts' always), weighted by the
        # inverse inclusion probability: an unbiased REINFORCE gradient at a fraction of the cost
        frac = float(t["rescore_fraction"])
        keep = is_best | torch.as_tensor(self.np_rng.random(D) < frac)  # [D]
        weight = torch.where(is_best, 1.0, 1.0 / frac)[keep]  # [D']
        sub = {k: v[keep] for k, v in allobs.items()}
        sub_acts, sub_eps, sub_best = acts[keep], eps[keep], is_best[keep]  # [D']
        ent_sum, loss_sum = 0.0, 0.0
        for lo in range(0, len(sub_acts), t["rescore_chunk"]):
            sl = slice(lo, lo + t["rescore_chunk"])
            batch = {k: v[sl].to(self.device) for k, v in sub.items()}
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=t["amp"]):
                logits = self.model(**batch).float()  # [c, T]
            logp_all = torch.log_softmax(logits / t["temperature"], dim=-1)  # [c, T]
            a = sub_acts[sl].to(self.device)
            logp = logp_all.gather(1, a[:, None])[:, 0]  # [c]
            safe = logp_all.masked_fill(~batch["action_mask"], 0.0)  # [c, T] (no 0 * -inf in the gradient)
            ent = -(safe.exp() * safe).masked_fill(~batch["action_mask"], 0.0).sum(-1)  # [c]
            wt = weight[sl].to(self.device)  # [c]
            loss = (-(wt * adv_t[sub_eps[sl].to(self.device)] * logp).sum()
                    - t["entropy_coef"] * (wt * ent).sum()) / n_ep
            if sil["coef"]:
                b = sub_best[sl].to(self.device)  # [c]
                ce = torch.nn.functional.cross_entropy(logits[b], a[b], reduction="sum")
                loss = loss + sil["coef"] * ce / n_best
            loss.backward()
            ent_sum += float((wt * ent).detach().sum())
            loss_sum += float(loss.detach())
        self._clipped_step(t["grad_clip"])
        sil_loss = math.nan
        if sil["steps"]:
            self.sil_buffer.append({k: v[is_best] for k, v in {**allobs, "target": acts}.items()})
            del self.sil_buffer[:-sil["buffer"]]
            sil_loss = self._replay_steps(self.sil_buffer, sil["steps"], sil["batch"], t["grad_clip"], t["amp"])
        dt = time.perf_counter() - t0
        self.iteration += 1
        self.episodes += n_ep
        self.decisions += D
        ok = np.array([s.success for s in states])
        mk = np.array([s.makespan for s in states if s.success])
        return {
            "iteration": self.iteration, "episodes": self.episodes, "reward": float(R.mean()),
            "makespan": float(mk.mean()) if len(mk) else math.nan, "success": float(ok.mean()),
            "entropy": ent_sum / max(D, 1), "loss": loss_sum, "lr": self._lr(), "sil_loss": sil_loss,
            "best_makespan": float(np.mean([states[i].makespan for i in best_ep.tolist()])),
            "decisions_per_s": D / max(t_collect, 1e-9), "episodes_per_s": n_ep / dt,
            "tasks": insts[0].n_tasks, "agents": insts[0].n_agents, "seconds": dt,
        }

    def _clipped_step(self, clip: float) -> None:
        gnorm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), clip)
        if torch.isfinite(gnorm):
            self._optimizer_step()
        else:  # never let one bad batch poison the weights
            self.log(f"iteration {self.iteration + 1}: non-finite gradient, update skipped")
        self.opt.zero_grad(set_to_none=True)

    def _replay_steps(self, buffer: list[dict[str, torch.Tensor]], steps: int, batch_size: int, clip: float,
                      amp: bool) -> float:
        """Cross-entropy minibatch steps on replayed (observation, target action) rows."""
        self.model.train()
        losses = []
        for _ in range(steps):
            entry = buffer[int(self.np_rng.integers(len(buffer)))]
            n = len(entry["target"])
            idx = torch.as_tensor(self.np_rng.permutation(n)[:batch_size])
            batch = {k: v[idx].to(self.device) for k, v in entry.items()}
            target = batch.pop("target")
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=amp):
                logits = self.model(**batch).float()  # [b, T]
            if target.dtype == torch.long:  # target actions
                loss = torch.nn.functional.cross_entropy(logits, target)
            else:  # target distributions over the admissible actions (zero elsewhere)
                logp = torch.log_softmax(logits, -1).masked_fill(~batch["action_mask"], 0.0)  # [b, T]
                loss = -(target * logp).sum(-1).mean()
            loss.backward()
            self._clipped_step(clip)
            losses.append(float(loss.detach()))
        return float(np.mean(losses))

    # ---- validation ----------------------------------------------------------------------------
    def validate(self) -> dict:
        from ..methods import solve

        if self.greedy_val is None:
            self.greedy_val = float(np.mean([solve(i, "greedy", 0).makespan for i in self.val_set]))
        states = [MissionState(i, seed=0, rules=self.eval_rules) for i in self.val_set]
        rollout(self.eval_model(), states, sample=False)
        mk = np.array([s.makespan if s.success else self.cfg["train"]["t_max"] for s in states])
        return {"val_makespan": float(mk.mean()), "val_success": float(np.mean([s.success for s in states])),
                "greedy_makespan": self.greedy_val}

    def _run_phase(self, desc: str, phase: str, total: int, counter: Callable[[], int], step: Callable[[], dict],
                   postfix: Callable[[dict], dict], *, w, f, start: float, deadline: float, progress: bool) -> None:
        """Run one training phase up to ``total`` iterations (or the deadline): CSV row, progress bar,
        validation and checkpoints after each iteration."""
        from tqdm import tqdm

        bar = tqdm(total=total, initial=counter(), desc=desc, disable=not progress or counter() >= total)
        while counter() < total and time.time() < deadline:
            row = step()
            row.update(phase=phase, wall=time.time() - start)
            w.writerow(row)
            f.flush()
            bar.update(1)
            bar.set_postfix(**postfix(row))
            self._periodic(counter(), phase, w, f, start)
        bar.close()

    def _periodic(self, it: int, phase: str, w, f, start: float) -> None:
        """Validation (keeping best.pt) and last.pt checkpoints every few iterations of a phase."""
        cfg = self.cfg
        if it % cfg["validation"]["every"] == 0:
            v = self.validate()
            w.writerow({**v, "phase": "val", "iteration": it, "wall": time.time() - start})
            f.flush()
            self.log(f"{phase} iteration {it}: validation makespan {v['val_makespan']:.3f} "
                     f"(greedy {v['greedy_makespan']:.3f}, best {min(self.best_val, v['val_makespan']):.3f})")
            if v["val_makespan"] < self.best_val:
                self.best_val = v["val_makespan"]
                self.save(self.run_dir / "best.pt")
        if it % cfg["checkpoint"]["every"] == 0:
            self.save(self.run_dir / "last.pt")

    # ---- loop --------------------------------------------------------------------------------
    def run(self, progress: bool = True) -> dict:
        cfg = self.cfg
        p, t = cfg["pretrain"], cfg["train"]
        log_path = self.run_dir / "log.csv"
        fields = ["phase", "iteration", "episodes", "reward", "makespan", "success", "entropy", "loss", "lr",
                  "decisions_per_s", "episodes_per_s", "sil_loss", "best_makespan", "lookahead_gain", "changed",
                  "labels", "tasks", "agents", "seconds", "bc_loss", "teacher_makespan", "pool_makespan",
                  "teacher_wins",
                  "val_makespan", "val_success", "greedy_makespan", "wall"]
        new = not log_path.exists()
        f = open(log_path, "a", newline="")
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        if new:
            w.writeheader()
        start = time.time()
        deadline = start + 60 * t["max_minutes"] if t.get("max_minutes") else math.inf
        last, best = self.run_dir / "last.pt", self.run_dir / "best.pt"
        try:
            phase = functools.partial(self._run_phase, w=w, f=f, start=start, deadline=deadline, progress=progress)
            phase(f"pretrain (BC of {p['teacher']})", "bc", p["iterations"], lambda: self.pretrain_done,
                  self.pretrain_step, lambda r: {"loss": f"{r['bc_loss']:.3f}", "best": f"{self.best_val:.2f}"})
            if self.iteration == 0 and self.best_val == math.inf:
                v = self.validate()
                self.best_val = v["val_makespan"]
                w.writerow({**v, "phase": "val", "iteration": 0, "wall": time.time() - start})
                self.save(best)
            phase("lookahead distillation", "distill", cfg["distill"]["iterations"], lambda: self.distill_done,
                  self.distill_step, lambda r: {"mk": f"{r['makespan']:.1f}", "gain": f"{r['lookahead_gain']:.3f}",
                                                "loss": f"{r['loss']:.3f}", "best": f"{self.best_val:.2f}"})
            phase("REINFORCE", "rl", t["iterations"], lambda: self.iteration, self.train_step,
                  lambda r: {"mk": f"{r['makespan']:.1f}", "ent": f"{r['entropy']:.2f}",
                             "dps": f"{r['decisions_per_s']:.0f}", "best": f"{self.best_val:.2f}"})
        finally:
            self.save(last)
            f.close()
        return {"iteration": self.iteration, "episodes": self.episodes, "best_val": self.best_val,
                "greedy_val": self.greedy_val}


def write_config(cfg: dict, path: Path) -> None:
    atomic_write_text(path, yaml.safe_dump(cfg, sort_keys=False))
