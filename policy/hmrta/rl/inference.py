"""Inference with a trained policy: RL(g.) (greedy decoding, one rollout) and RL(s.N) (N sampled
rollouts run as one batch, best makespan kept) and RL-lookahead (one-step lookahead over the
policy's own greedy continuations at every decision: slower, better): the entry points of the
methods ``rl``, ``rl-sample`` and ``rl-lookahead`` in :data:`hmrta.methods.METHODS`.

The shipped checkpoint (``hmrta/checkpoints/default.pt``) loads by default; ``HMRTA_CHECKPOINT``
or the ``checkpoint`` option selects another. Loaded models are cached and shared read-only (many
agents in one process use one copy of the weights).
"""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..core import IN_PROGRESS, MissionState, Rules
from ..errors import MethodError
from ..instance import Instance
from ..methods import SAMPLE_TEMPERATURE
from ..solution import Solution, solution_from_state
from .features import batch_observations
from .checkpoint_info import DEFAULT_CHECKPOINT, CheckpointError, checkpoint_path  # noqa: F401 (re-exported)
from .model import ModelConfig, PolicyNet, TracedPolicy
from .rollout import action_costs, best_action, forward_threads, greedy_rows, rollout

_CACHE: dict[str, "LoadedPolicy"] = {}
_LOCK = threading.Lock()


class LoadedPolicy:
    """A checkpoint ready for inference: ``net`` the network, ``model`` its traced form (the same
    logits, bit for bit, at a third less cost per call: :class:`TracedPolicy`), which every
    inference path calls."""

    def __init__(self, model: PolicyNet, config: dict, path: str, meta: dict):
        self.net, self.config, self.path, self.meta = model, config, path, meta
        self.model = TracedPolicy(model)
        self.rules = Rules.from_dict(config.get("rules", {}))
        self._sha256: str | None = None

    @property
    def sha256(self) -> str:
        """The checkpoint file's sha256 (read once; "" for a policy built in memory)."""
        if self._sha256 is None:
            from .checkpoint_info import sha256

            try:
                self._sha256 = sha256(self.path)
            except OSError:
                self._sha256 = ""
        return self._sha256


def _provenance(sol: Solution, pol: LoadedPolicy) -> Solution:
    """``sol`` with the checkpoint that planned it in ``extra["checkpoint"]``: its path and sha256."""
    sol.extra["checkpoint"] = {"path": pol.path, "sha256": pol.sha256}
    return sol


def load_policy(checkpoint: str | Path | None = None) -> LoadedPolicy:
    """Load (once per process) a checkpoint; raises CheckpointError with a clear message.

    The file is unpickled weights-only (it cannot run code); its model config, rules and weights
    (names, shapes, finite values) are checked before the network is built from them."""
    from ..core import parse_rules
    from .checkpoint import check_shapes, load, policy_weights

    path = checkpoint_path(checkpoint)
    key = str(path.resolve())
    with _LOCK:
        if key in _CACHE:
            return _CACHE[key]
        ck = load(path)
        config = ck.get("config")
        if not isinstance(config, dict):
            raise CheckpointError(f"{path}: config: expected a mapping (the training config), got "
                                  f"{type(config).__name__}")
        try:
            cfg = ModelConfig.from_dict(config.get("model"), "config.model")
            rules = config.get("rules", {})
            if not isinstance(rules, dict):
                raise ValueError(f"config.rules: expected a mapping, got {type(rules).__name__}")
            parse_rules({**Rules().to_dict(), **rules}, "config.rules")
        except ValueError as e:
            raise CheckpointError(f"{path}: {e}") from None
        # a training checkpoint with averaged weights (train.ema) is scored, and so used, by those
        which, sd = policy_weights(ck, path)
        with torch.device("meta"):  # the network's shapes, without allocating it
            check_shapes(PolicyNet(cfg), sd, path, which)
        model = PolicyNet(cfg)
        try:
            model.load_state_dict(sd)
        except RuntimeError as e:  # e.g. a dtype that cannot be copied
            first = (str(e).strip().splitlines() or [""])[0]
            raise CheckpointError(f"{path}: {which}: weights do not match the network ({first})") from None
        model.eval()
        for p in model.parameters():
            p.requires_grad_(False)
        meta = {k: ck.get(k) for k in ("code_version", "iteration", "episodes", "best_val", "greedy_val", "summary")}
        lp = LoadedPolicy(model, config, str(path), meta)
        _CACHE[key] = lp
        return lp


def solve_rl(inst: Instance, seed: int = 0, checkpoint: str | None = None) -> Solution:
    pol = load_policy(checkpoint)
    t0 = time.perf_counter()
    state = MissionState(inst, seed=seed, rules=pol.rules)
    rollout(pol.model, [state], sample=False)
    return _provenance(solution_from_state(state, "rl", seed, time.perf_counter() - t0), pol)


def solve_rl_sample(inst: Instance, seed: int = 0, samples: int = 10,
                    temperature: float = SAMPLE_TEMPERATURE, checkpoint: str | None = None) -> Solution:
    """RL(s.N): ``samples`` rollouts sampled from softmax(logits / ``temperature``), one batch,
    the shortest successful one kept."""
    if samples < 1:
        raise MethodError(f"samples: expected a positive integer, got {samples}")
    if not temperature > 0:
        raise MethodError(f"temperature: expected a positive number, got {temperature}")
    pol = load_policy(checkpoint)
    t0 = time.perf_counter()
    states = [MissionState(inst, seed=seed + k, rules=pol.rules) for k in range(samples)]
    gen = torch.Generator().manual_seed(seed)
    rollout(pol.model, states, sample=True, generator=gen, temperature=temperature)
    ok = [s for s in states if s.success]
    best = min(ok, key=lambda s: s.makespan) if ok else states[0]
    sol = _provenance(solution_from_state(best, f"rl-s{samples}", best.seed, time.perf_counter() - t0), pol)
    sol.extra["samples"] = samples
    sol.extra["temperature"] = temperature
    return sol


def lookahead_choices(model: torch.nn.Module, states: list[MissionState], t_max: float = 1000.0) -> list[int]:
    """The next node of every state by one-step lookahead (the rollout algorithm): each admissible
    action is tried on a clone, the mission completed by the policy's greedy decoding (all branches
    of all states as one batch), and the action with the lowest final cost T + W is chosen; ties go
    to the policy's own choice. Never worse than the policy alone (Bertsekas' cost improvement).
    The states themselves are not changed."""
    obs, nodes = batch_observations(states, **model.cfg.view())
    with torch.inference_mode(), forward_threads(len(states)):  # threaded as a rollout of these states
        own = greedy_rows(model(**obs), model.cfg.greedy_depot).tolist()  # [b] the policy's choice (action rows)
    mask = obs["action_mask"].numpy()  # [b, T]
    multi = [j for j in range(len(states)) if mask[j].sum() > 1]  # nothing to compare elsewhere
    costs, _ = action_costs(model, [(states[j], nodes[j], mask[j]) for j in multi], t_max)
    choice = list(own)
    for j, c in zip(multi, costs):
        choice[j] = best_action(c, own[j])
    return [int(nodes[j][choice[j]]) for j in range(len(states))]


def lookahead_step(model: torch.nn.Module, states: list[MissionState], t_max: float = 1000.0) -> None:
    """Advance every state by one lookahead decision."""
    for s, n in zip(states, lookahead_choices(model, states, t_max)):
        s.step(n)


def solve_rl_lookahead(inst: Instance, seed: int = 0, checkpoint: str | None = None,
                       progress: Callable[..., None] | None = None) -> Solution:
    """``progress(done, total, unit, note)``, if given, is called after every decision with the
    number of tasks started (unit "task") out of all tasks."""
    pol = load_policy(checkpoint)
    t0 = time.perf_counter()
    state = MissionState(inst, seed=seed, rules=pol.rules)
    decisions = 0
    if progress is not None:  # before the first decision, the slowest (every branch runs the whole mission)
        progress(0, inst.n_tasks, "task", "0 decisions")
    while not state.done:
        lookahead_step(pol.model, [state])
        decisions += 1
        if progress is not None:
            progress(int((state.status >= IN_PROGRESS).sum()), inst.n_tasks, "task", f"{decisions} decisions")
    return _provenance(solution_from_state(state, "rl-lookahead", seed, time.perf_counter() - t0), pol)


class RLDecider:
    """Per-decision form of the policy (one forward per decision), for live agents."""

    def __init__(self, pol: LoadedPolicy, sample: bool, seed: int, temperature: float = 1.0):
        if not temperature > 0:
            raise MethodError(f"temperature: expected a positive number, got {temperature}")
        self.pol, self.sample, self.temperature = pol, sample, temperature
        self.gen = torch.Generator().manual_seed(seed)
        self.name = "rl-sample" if sample else "rl"

    def scores(self, state: MissionState) -> tuple[np.ndarray, torch.Tensor]:
        """(the nodes the policy observes at ``state`` [T], its logits over them [T])."""
        with torch.inference_mode(), forward_threads(1):  # the same bits as a rollout of one mission
            obs, nodes = batch_observations([state], **self.pol.model.cfg.view())
            return nodes[0], self.pol.model(**obs)[0]

    def __call__(self, state: MissionState) -> int:
        nodes, logits = self.scores(state)  # [T], [T]
        with torch.inference_mode():
            if self.sample:
                probs = torch.softmax(logits / self.temperature, -1)  # [T] as in a sampled rollout
                row = int(torch.multinomial(probs, 1, generator=self.gen)[0])
            else:
                row = int(greedy_rows(logits[None], self.pol.model.cfg.greedy_depot)[0])
        return int(nodes[row])


class CheckpointTeacher(RLDecider):
    """A trained policy as a behaviour-cloning teacher (``pretrain.teacher: rl@CHECKPOINT``): its
    greedy decoding, as a live agent's; for soft targets, :meth:`distribution` gives its
    probabilities at a state from the forward pass of its choice there."""

    def __init__(self, pol: LoadedPolicy):
        super().__init__(pol, sample=False, seed=0)
        self._last: tuple | None = None  # (state, its decision count, nodes [T], logits [T]) of the latest call

    def scores(self, state: MissionState) -> tuple[np.ndarray, torch.Tensor]:
        nodes, logits = super().scores(state)
        self._last = (state, state.decisions, nodes, logits)
        return nodes, logits

    def distribution(self, state: MissionState, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """(the nodes it observes [T], ascending; softmax(logits / tau) over them [T]) at ``state``."""
        if self._last is None or self._last[0] is not state or self._last[1] != state.decisions:
            self.scores(state)
        _, _, nodes, logits = self._last
        return nodes, torch.softmax(logits / tau, dim=-1).numpy()


def rl_decider(seed: int = 0, checkpoint: str | None = None) -> RLDecider:
    return RLDecider(load_policy(checkpoint), False, seed)


def sample_decider(seed: int = 0, temperature: float = SAMPLE_TEMPERATURE, checkpoint: str | None = None) -> RLDecider:
    return RLDecider(load_policy(checkpoint), True, seed, temperature)


class LookaheadDecider:
    """Per-decision form of ``rl-lookahead`` for live agents (branches clones, never the state)."""

    name = "rl-lookahead"

    def __init__(self, pol: LoadedPolicy):
        self.pol = pol

    def __call__(self, state: MissionState) -> int:
        return lookahead_choices(self.pol.model, [state])[0]


def lookahead_decider(seed: int = 0, checkpoint: str | None = None) -> LookaheadDecider:
    return LookaheadDecider(load_policy(checkpoint))
