"""Training orchestration: the schedule of the algorithms, validation, checkpoints and logging.

A run has up to three phases, in this order, each until its iteration counter reaches the
configured total: behaviour cloning of a baseline (:mod:`.imitation`, ``pretrain``), lookahead
distillation (:mod:`.distill`, ``distill``) and REINFORCE with the shared baseline and
self-imitation (:mod:`.reinforce`, ``train``). They share one :class:`~.learner.Learner` (network,
optimiser, moving average of the weights, clipped update, random streams); the config is a typed
:class:`~.config.TrainConfig`. Every ``validation.every`` iterations of a phase RL(g.) is scored
on a fixed validation set (the best keeps ``best.pt``); ``last.pt`` is written every
``checkpoint.every`` iterations and on exit; each iteration is a row of ``log.csv``.

Checkpoints (:mod:`.checkpoint`) hold model, optimiser, moving average, counters, RNG states,
the resolved config and the code version; ``--resume`` continues exactly.
"""
from __future__ import annotations

import copy
import csv
import functools
import io
import math
import random
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import yaml

from ..core import MissionState
from ..generators import ScenarioGenerator
from ..instance import atomic_write_text
from ..reading import short
from . import checkpoint
from .checkpoint import check_optimizer, check_shapes, code_version, counter, weights, widen_task_inputs
from .checkpoint_info import CheckpointError
from .config import (CONFIG_VERSION, TEACHERS, TrainConfig, check_config, deep_update, defaults,  # noqa: F401
                     load_config, rules_from)
from .distill import Distill
from .imitation import Imitation, soft_target
from .learner import Learner
from .model import ZERO_INIT_PARAMS, PolicyNet
from .reinforce import Reinforce
from .rollout import makespans, rollout

DEFAULTS = defaults()  # every key with its default (a config file names only what it changes)


def rollout_makespans(net: torch.nn.Module, insts: list, rules, t_max: float) -> list[tuple[float, bool]]:
    """(makespan, success) of RL(g.) of ``net`` on each instance (``t_max`` for a failure)."""
    states = [MissionState(i, seed=0, rules=rules) for i in insts]
    rollout(net, states, sample=False)
    return [(float(m), bool(s.success)) for m, s in zip(makespans(states, t_max), states)]


def validation_makespans(job: tuple) -> list[tuple[float, bool]]:
    """:func:`rollout_makespans` on a part of the validation set; ``job`` is (model config,
    weights, instances, rules, t_max). A Ray task with ``hmrta train --jobs N``."""
    model_cfg, weights, insts, rules, t_max = job
    net = PolicyNet(model_cfg)
    net.load_state_dict(weights)
    return rollout_makespans(net.eval(), insts, rules, t_max)


def validation_set(cfg: TrainConfig) -> list:
    from ..families import BroadGenerator

    v = cfg.validation
    out = []
    for a, s, m, k, n in v.rows:
        out += ScenarioGenerator("MA-AT", a, s, m, k).generate(n, v.seed)
    if v.broad:
        out += BroadGenerator(max_tasks=50).generate(v.broad, v.seed)
    if v.single_skill:
        from .schedules import SingleSkillTraining

        out += SingleSkillTraining(max_tasks=50).generate(v.single_skill, v.seed)
    if v.families:
        from ..families import family_suite

        for row in family_suite(max_tasks=50):
            out += row.generator().generate(v.families, v.seed)
    return out


class Trainer:
    """One training run: the learner, the three algorithms, their counters and the run folder.
    ``cfg``: a TrainConfig, or a complete config mapping (validated here: ValueError naming the key).
    ``jobs`` > 1 or ``ray_address``: the teachers' labels are computed as Ray tasks
    (:mod:`hmrta.fanout`: a local Ray with ``jobs`` CPUs, or a cluster); the results are the same
    as in this process. :meth:`close` (or the end of :meth:`run`) shuts a local Ray down."""

    def __init__(self, cfg: TrainConfig | dict, run_dir: str | Path, device: str | None = None, log=print,
                 jobs: int = 1, ray_address: str | None = None):
        from ..fanout import Fanout

        self.cfg = TrainConfig.coerce(cfg)
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.log = log
        self.learner = Learner(self.cfg, self.device, log=lambda s: self.log(s))
        self.iteration = 0
        self.pretrain_done = 0
        self.distill_done = 0
        self.episodes = 0
        self.decisions = 0
        self.best_val = math.inf
        self.started_from: Path | None = None  # the checkpoint of another run it started from (--init)
        self.stopped_by_time = False  # run() ended at train.max_minutes, its iterations not all done
        self.greedy_val: float | None = None
        self._coalition_val: np.ndarray | None = None
        self.val_set = validation_set(self.cfg)
        self._schedules: dict = {}  # {path: (file size, ScheduleSet)} of pretrain.schedules, reloaded as they grow
        self.train_rules = self.eval_rules = self.cfg.rule_set()
        self.fanout = Fanout(jobs, ray_address)
        # the whole trainer state after the latest finished iteration (a copy): what last.pt gets when
        # a run is cut short within an iteration (Ctrl-C, SIGTERM, an error), so that --resume
        # continues exactly, the iteration under way done again
        self._boundary: dict | None = None
        self.saved_last: dict | None = None  # the counters of the state the latest run() wrote to last.pt, if any
        self.loaded_config: dict = {}  # the config of the checkpoint last loaded
        self.lineage: list = []  # how the weights began: a checkpoint of another run (--init), with its own
        self.imitation = Imitation(self)
        self.distill = Distill(self)
        self.reinforce = Reinforce(self)

    def note_teacher(self, pol) -> None:
        """Record a checkpoint teacher (``pretrain.teacher: rl@CHECKPOINT``, a LoadedPolicy) in the
        lineage, once per file: its path, sha256 and code version, as ``--init`` records a source."""
        for e in self.lineage:
            src = e.get("sources") if isinstance(e, dict) and e.get("op") == "teacher" else None
            if isinstance(src, list) and src and isinstance(src[0], dict) and src[0].get("sha256") == pol.sha256:
                return
        code = pol.meta.get("code_version")
        self.lineage.insert(0, {"op": "teacher", "sources": [{  # (newest step first)
            "path": pol.path, "sha256": pol.sha256, "weights": "model",
            "code_version": code if isinstance(code, str) else None, "lineage": []}]})

    # ---- the learner's state, by its old names -------------------------------------------------
    model = property(lambda self: self.learner.model)
    opt = property(lambda self: self.learner.opt)
    np_rng = property(lambda self: self.learner.np_rng)
    torch_gen = property(lambda self: self.learner.torch_gen)
    sil_buffer = property(lambda self: self.reinforce.sil_buffer)
    distill_buffer = property(lambda self: self.distill.buffer)

    @property
    def ema(self) -> dict[str, torch.Tensor] | None:
        return self.learner.ema

    @ema.setter
    def ema(self, value: dict[str, torch.Tensor] | None) -> None:
        self.learner.ema = value

    def policy_weights(self) -> dict[str, torch.Tensor]:
        return self.learner.policy_weights()

    def eval_model(self) -> PolicyNet:
        return self.learner.eval_model()

    # ---- one iteration of each algorithm -------------------------------------------------------
    def pretrain_step(self) -> dict:
        return self.imitation.step()

    def distill_step(self) -> dict:
        return self.distill.step()

    def train_step(self) -> dict:
        return self.reinforce.step()

    def _pool(self, pool: list, obs: list, deciders: list, acts: list) -> dict:
        return self.imitation.pool(pool, obs, deciders, acts)

    _soft_target = staticmethod(soft_target)

    # ---- checkpoints ---------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "config": self.cfg.to_dict(),
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
            "lineage": self.lineage,
        }

    def save(self, path: Path) -> None:
        checkpoint.save(path, self.state_dict())

    def load(self, path: Path, reseed: bool = False, same_run: bool = False) -> None:
        """Restore a checkpoint (model, optimiser, averaged weights, counters, RNG streams, best
        validation). ``reseed``: keep this trainer's fresh RNG streams (from the config's seed) and
        its unset validation scores instead, for a second, independent continuation of the same
        checkpoint (possibly under other rules or another validation set). Without ``reseed`` the
        checkpoint's validation set and rules must be this config's (:meth:`_check_same_yardstick`).

        The file is unpickled weights-only (it cannot run code); anything missing, mistyped or not
        fitting this network is a CheckpointError naming the file and the field, raised before the
        trainer is changed. ``same_run``: the checkpoint is this run's own (``--resume`` without
        ``--init``), so its seed must be this config's too (the random streams continue); without
        it, the checkpoint is another run's (``--init``): :meth:`run` scores its weights before the
        first iteration and keeps them as the first best.pt."""
        ck = checkpoint.load(path, map_location=self.device)
        if not reseed:
            self._check_same_yardstick(ck, path, same_run)
        loaded_config = ck.get("config") if isinstance(ck.get("config"), dict) else {}
        before = ck.get("lineage") if isinstance(ck.get("lineage"), list) else []
        # a run's own checkpoint carries its lineage on; another run's (--init) becomes its source
        lineage = before if same_run else [
            {"op": "init", "sources": [{"path": str(path), "sha256": checkpoint.sha256(path), "weights": "model",
                                        "code_version": ck.get("code_version") if isinstance(ck.get("code_version"),
                                                                                             str) else None,
                                        "lineage": before}],
             **({"reseed": True} if reseed else {})}]
        sd = weights(ck, "model", path)
        widened = widen_task_inputs(self.model, sd)  # e.g. a "mission" checkpoint into "mission+coalition"
        try:
            check_shapes(self.model, sd, path, "model", optional=ZERO_INIT_PARAMS)
        except CheckpointError:  # say which setting of the network differs, where the checkpoint says
            theirs = loaded_config.get("model") if isinstance(loaded_config.get("model"), dict) else {}
            diff = [k for k in ("d_model", "heads", "ff_hidden") if k in theirs and theirs[k] != getattr(self.cfg.model, k)]
            if not diff:
                raise
            raise CheckpointError(f"{path}: a network of {', '.join(f'{k} {theirs[k]}' for k in diff)}, this config "
                                  f"has {', '.join(f'model.{k} {getattr(self.cfg.model, k)}' for k in diff)} (give "
                                  f"the config the checkpoint's model section: hmrta checkpoint info {path})") from None
        added = widened or any(n not in sd for n in ZERO_INIT_PARAMS & set(self.model.state_dict()))  # e.g. travel_bias
        ema = weights(ck, "ema", path, required=False)
        if ema is not None and not added:
            check_shapes(self.model, ema, path, "ema")
        counters = {k: counter(ck, k, path) for k in checkpoint.COUNTERS}
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
        self.ema = ema if self.cfg.train.ema > 0 and not added else None
        self.loaded_config, self.lineage = loaded_config, lineage
        self.started_from = None if same_run else Path(path)  # --init: another run's weights
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

    # what a validation score depends on, besides the weights (validation.every only says when)
    YARDSTICK = (("validation", ("every",)), ("rules", ()))

    def _check_same_yardstick(self, ck: dict, path: Path, same_run: bool = False) -> None:
        """A continuation keeps the checkpoint's best validation score, so it must be scored as
        the checkpoint was: same validation set and rules. Otherwise a CheckpointError naming
        the first key that differs (keys only one side has are not compared)."""
        theirs = ck.get("config") if isinstance(ck.get("config"), dict) else {}
        mine = self.cfg.to_dict()
        for section, skip in self.YARDSTICK:
            a, b = theirs.get(section), mine[section]
            if not isinstance(a, dict):
                continue
            for k in sorted(set(a) & set(b)):
                if k not in skip and a[k] != b[k]:
                    where, x, y = _first_difference(f"{section}.{k}", a[k], b[k])
                    raise CheckpointError(
                        f"{path}: was trained with {where} = {short(x)}, this config has {short(y)}: "
                        f"its best validation score does not compare; pass --reseed to continue its weights with "
                        f"fresh validation scores and random streams")
        if same_run and "seed" in theirs and theirs["seed"] != mine["seed"]:
            raise CheckpointError(f"{path}: was trained with seed {short(theirs['seed'])}, this config has "
                                  f"{short(mine['seed'])}: a resumed run continues the checkpoint's random streams, "
                                  f"so the new seed would be recorded but not used; keep the seed, or pass --reseed "
                                  f"to draw fresh streams from the new one")

    # keys a continuation is expected to change: how long it runs
    RUN_LENGTH = {"train.iterations", "train.max_minutes", "pretrain.iterations", "distill.iterations"}

    def changed_keys(self) -> list[str]:
        """``key: old -> new`` for each setting of this config that differs from the config of the
        checkpoint last loaded (a resumed run trains on under the new ones from here on), run
        lengths left out."""
        theirs = self.loaded_config
        out: list[str] = []

        def walk(prefix: str, a, b) -> None:
            if isinstance(a, dict) and isinstance(b, dict):
                for k in sorted(set(a), key=str):  # keys the checkpoint lacks: written by an older version
                    walk(f"{prefix}.{k}" if prefix else str(k), a[k], b.get(k))
            elif a != b and prefix not in self.RUN_LENGTH:
                out.append(f"{prefix}: {short(a)} -> {short(b)}")

        walk("", theirs, self.cfg.to_dict())
        return out

    def export(self, path: Path, summary: dict | None = None) -> None:
        """Small inference checkpoint of this trainer's state (:func:`checkpoint.export_checkpoint`)."""
        checkpoint.export_checkpoint({**self.state_dict(), "summary": summary}, path, "trainer")

    # ---- data --------------------------------------------------------------------------------
    def schedule_items(self, n: int) -> list[tuple]:
        """``n`` (instance, routes) of the ``pretrain.schedules`` datasets (one or a list, drawn from
        as one), drawn uniformly with the run's random stream. A file is read again when it has
        grown (generation may still run)."""
        from .schedules import ScheduleError, ScheduleSet

        paths = [Path(x) for x in self.cfg.pretrain.schedule_files]
        pool = []  # (dataset, index) of every schedule, file after file
        for path in paths:
            try:
                size = path.stat().st_size
            except OSError as e:
                raise ScheduleError(f"pretrain.schedules: {path}: cannot read ({e.strerror})") from None
            if path not in self._schedules or self._schedules[path][0] != size:
                self._schedules[path] = (size, ScheduleSet(path))
            ss = self._schedules[path][1]
            pool += [(ss, i) for i in ss.indices()]
        if not pool:
            raise ScheduleError(f"pretrain.schedules: {', '.join(map(str, paths))}: no schedules yet")
        out = []
        for j in self.np_rng.integers(0, len(pool), size=n):
            ss, i = pool[int(j)]
            inst, routes, _ = ss.item(i)
            out.append((inst, routes))
        return out

    def _task_range(self) -> tuple[int, int]:
        t = self.cfg.train
        for stage in t.curriculum:
            if stage.get("until") is None or self.iteration < stage["until"]:
                return tuple(stage["tasks"])  # type: ignore[return-value]
        return tuple(t.distribution.tasks)  # type: ignore[return-value]

    def _instances(self, n: int, task_range: tuple[int, int] | None = None) -> list:
        dist = self.cfg.train.distribution
        lo, hi = task_range or self._task_range()
        rng = self.np_rng
        if dist.generator == "ma-at":  # one team shape and size for the whole batch
            return self._ma_at(n, lo, hi)
        from ..families import BroadGenerator
        from .schedules import SingleSkillTraining

        broad = BroadGenerator(max_tasks=hi, min_tasks=lo, team_scale=tuple(map(float, dist.team_scale)))
        if dist.generator == "broad":  # a mission family per instance, every axis of the suite
            return [broad.sample(rng) for _ in range(n)]
        single = SingleSkillTraining(max_tasks=hi, min_tasks=lo)
        out = []
        for kind in rng.integers(0, 3, size=n):  # mixed: broad, ma-at or single-skill, equal odds
            if kind == 0:
                out.append(broad.sample(rng))
            elif kind == 1:
                out += self._ma_at(1, lo, hi)
            else:
                out.append(single.sample(rng))
        return out

    def _ma_at(self, n: int, lo: int, hi: int) -> list:
        """``n`` missions of the paper's distribution (``train.distribution``'s species, robots per
        species and skills; ``lo..hi`` tasks), one team shape and size for all of them."""
        dist, rng = self.cfg.train.distribution, self.np_rng
        s = int(rng.integers(dist.species[0], dist.species[1] + 1))
        per = int(rng.integers(dist.per_species[0], dist.per_species[1] + 1))
        m = int(rng.integers(lo, hi + 1))
        gen = ScenarioGenerator("MA-AT", s * per, s, m, dist.skills)
        return [gen.sample(rng) for _ in range(n)]

    # ---- validation ----------------------------------------------------------------------------
    def validate(self) -> dict:
        from ..methods import solve

        if self.greedy_val is None:
            self.greedy_val = float(np.mean([solve(i, "greedy", 0).makespan for i in self.val_set]))
        t_max = self.cfg.train.t_max
        if self.fanout.distributed:  # a part of the set per Ray CPU, each rolled out as one batch
            weights = {k: v.detach().cpu() for k, v in self.eval_model().state_dict().items()}
            parts = np.array_split(np.arange(len(self.val_set)), min(self.fanout.slots(), len(self.val_set)))
            jobs = [(self.cfg.model, weights, [self.val_set[i] for i in part], self.eval_rules, t_max)
                    for part in parts]
            res = [r for part in self.fan_out(validation_makespans, jobs) for r in part]
        else:
            res = rollout_makespans(self.eval_model(), self.val_set, self.eval_rules, t_max)
        mk = np.array([m for m, _ in res])  # [V]
        out = {"val_makespan": float(mk.mean()), "val_success": float(np.mean([ok for _, ok in res])),
               "greedy_makespan": self.greedy_val}
        if self.cfg.validation.metric == "ratio":  # scored by the ratio to greedy-coalition per mission
            if self._coalition_val is None:
                self._coalition_val = np.array([solve(i, "greedy-coalition", 0).makespan for i in self.val_set])
            out["val_ratio"] = float(np.mean(mk / np.maximum(self._coalition_val, 1e-9)))
            out["val_makespan"], out["val_mean_makespan"] = out["val_ratio"], out["val_makespan"]
        return out

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
            self._mark_boundary()
        bar.close()

    def _periodic(self, it: int, phase: str, w, f, start: float) -> None:
        """Validation (keeping best.pt) and last.pt checkpoints every few iterations of a phase."""
        cfg = self.cfg
        if it % cfg.validation.every == 0:
            v = self.validate()
            w.writerow({**v, "phase": "val", "iteration": it, "wall": time.time() - start})
            f.flush()
            what = "ratio to greedy-coalition" if "val_ratio" in v else "makespan"
            self.log(f"{phase} iteration {it}: validation {what} {v['val_makespan']:.3f} "
                     f"(greedy makespan {v['greedy_makespan']:.3f}, best {min(self.best_val, v['val_makespan']):.3f})")
            if v["val_makespan"] < self.best_val:
                self.best_val = v["val_makespan"]
                self.save(self.run_dir / "best.pt")
        if it % cfg.checkpoint.every == 0:
            self.save(self.run_dir / "last.pt")

    # ---- loop --------------------------------------------------------------------------------
    def run(self, progress: bool = True) -> dict:
        cfg = self.cfg
        p, t = cfg.pretrain, cfg.train
        log_path = self.run_dir / "log.csv"
        fields = ["phase", "iteration", "episodes", "reward", "makespan", "success", "entropy", "loss", "lr",
                  "decisions_per_s", "episodes_per_s", "sil_loss", "best_makespan", "lookahead_gain", "changed",
                  "labels", "tasks", "agents", "seconds", "bc_loss", "teacher_makespan", "pool_makespan",
                  "teacher_wins",
                  "val_makespan", "val_success", "greedy_makespan", "wall", "route_share", "val_mean_makespan",
                  "dagger_plan_ratio"]
        # a new run (nothing trained, no last.pt) starts a new log: one left by a run that never
        # finished an iteration is not continued
        new = not log_path.exists() or (self._counters() == (0, 0, 0) and not (self.run_dir / "last.pt").exists())
        if not new:  # a resumed run keeps its log's columns (one written by an older version has fewer)
            with open(log_path, newline="") as old:
                fields = next(csv.reader(old), None) or fields
            self._trim_log(log_path)
        f = open(log_path, "w" if new else "a", newline="")
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        if new:
            w.writeheader()
        start = time.time()
        deadline = start + 60 * t.max_minutes if t.max_minutes else math.inf
        last, best = self.run_dir / "last.pt", self.run_dir / "best.pt"
        counters = self._counters()
        self._mark_boundary()

        def score_as_best() -> dict:  # the weights as they are: validated, logged, kept as best.pt
            v = self.validate()
            self.best_val = v["val_makespan"]
            w.writerow({**v, "phase": "val", "iteration": self.iteration, "wall": time.time() - start})
            self.save(best)
            self._mark_boundary()
            return v

        try:
            if self.started_from is not None:
                # weights from another run (--init), scored here, are this run's first best.pt, so
                # that neither it nor an export is ever worse than what the run started from
                v = score_as_best()
                self.log(f"the starting weights ({self.started_from}): validation {v['val_makespan']:.3f}")
                self.started_from = None
            phase = functools.partial(self._run_phase, w=w, f=f, start=start, deadline=deadline, progress=progress)
            phase(f"pretrain (BC of {'schedules' if p.schedules else p.teacher})", "bc", p.iterations, lambda: self.pretrain_done,
                  self.pretrain_step, lambda r: {"loss": f"{r['bc_loss']:.3f}", "best": f"{self.best_val:.2f}"})
            if self.best_val == math.inf:  # no score yet (a new run, or --reseed of its own checkpoint)
                score_as_best()
            phase("lookahead distillation", "distill", cfg.distill.iterations, lambda: self.distill_done,
                  self.distill_step, lambda r: {"mk": f"{r['makespan']:.1f}", "gain": f"{r['lookahead_gain']:.3f}",
                                                "loss": f"{r['loss']:.3f}", "best": f"{self.best_val:.2f}"})
            phase("REINFORCE", "rl", t.iterations, lambda: self.iteration, self.train_step,
                  lambda r: {"mk": f"{r['makespan']:.1f}", "ent": f"{r['entropy']:.2f}",
                             "dps": f"{r['decisions_per_s']:.0f}", "best": f"{self.best_val:.2f}"})
            # the time limit (train.max_minutes) ended the run before its iterations
            totals = (p.iterations, cfg.distill.iterations, t.iterations)
            self.stopped_by_time = time.time() >= deadline and any(
                done < total for done, total in zip(self._counters(), totals))
        finally:
            # last.pt: the state after the latest finished iteration (cut short within one, the
            # weights may have moved while the counters and random streams have not), and only once
            # this run did something (a run that failed at once leaves no last.pt to block a new one)
            b = self._boundary
            self.saved_last = None
            if b is not None and (self._counters(b) != counters or last.exists()):
                checkpoint.save(last, b)
                self.saved_last = {k: b[k] for k in checkpoint.COUNTERS}
            f.close()
            self.close()
        return {"iteration": self.iteration, "episodes": self.episodes, "best_val": self.best_val,
                "greedy_val": self.greedy_val}

    def _mark_boundary(self) -> None:
        """Keep a copy of the trainer's whole state, between two iterations."""
        self._boundary = copy.deepcopy(self.state_dict())

    def _counters(self, state: dict | None = None) -> tuple[int, int, int]:
        """(cloning, distillation, REINFORCE) iterations done: this trainer's, or a state_dict's."""
        d = vars(self) if state is None else state
        return d["pretrain_done"], d["distill_done"], d["iteration"]

    def _trim_log(self, path: Path) -> None:
        """Drop the rows of ``log.csv`` past this trainer's counters: the iterations a run did after
        its last checkpoint (killed, then resumed from the checkpoint) are done again and logged again.
        A validation row belongs to the phase of the row before it."""
        limit = {"bc": self.pretrain_done, "distill": self.distill_done, "rl": self.iteration}
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
        if len(rows) < 2 or "phase" not in rows[0] or "iteration" not in rows[0]:
            return
        ph, it = rows[0].index("phase"), rows[0].index("iteration")
        keep, current = [rows[0]], None
        for r in rows[1:]:
            if len(r) > max(ph, it):
                if r[ph] != "val":
                    current = r[ph]
                try:
                    if current in limit and int(float(r[it])) > limit[current]:
                        continue
                except ValueError:
                    pass  # a row it cannot read is kept as it is
            keep.append(r)
        if len(keep) < len(rows):
            buf = io.StringIO()
            csv.writer(buf).writerows(keep)
            atomic_write_text(path, buf.getvalue())


    def fan_out(self, fn: Callable, jobs: list) -> list:
        """``[fn(job) for job in jobs]``: as Ray tasks when the run fans out (``jobs`` > 1 or a
        cluster), else here, with the run's own torch threads left as they are."""
        return self.fanout.map(fn, jobs) if self.fanout.distributed else [fn(j) for j in jobs]

    def close(self) -> None:
        """Shut down the local Ray this run started, if any (a later step starts it again)."""
        self.fanout.close()


def _first_difference(where: str, a, b) -> tuple[str, object, object]:
    """(path, a's part, b's part) of the first place where two config values differ: inside lists
    and mappings, so that a message shows what differs rather than two long values cut alike."""
    while True:
        if isinstance(a, list) and isinstance(b, list):
            i = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), None)
            if i is None:
                return f"{where} (length)", len(a), len(b)
            where, a, b = f"{where}[{i}]", a[i], b[i]
        elif isinstance(a, dict) and isinstance(b, dict):
            k = next((k for k in sorted(set(a) | set(b), key=str) if a.get(k) != b.get(k)), None)
            if k is None:
                return where, a, b
            where, a, b = f"{where}.{k}", a.get(k), b.get(k)
        else:
            return where, a, b


def write_config(cfg: TrainConfig | dict, path: Path) -> None:
    atomic_write_text(path, yaml.safe_dump(cfg.to_dict() if isinstance(cfg, TrainConfig) else cfg, sort_keys=False))
