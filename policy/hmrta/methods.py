"""Named solution methods: one place that maps a method name to a solver.

``solve(inst, method, seed, **options) -> Solution``. Built in: ``greedy``, ``greedy-coalition``,
``random``; the learned
policy adds ``rl`` (greedy decoding), ``rl-sN`` / ``rl-sample`` (N sampled rollouts, best kept) and
``rl-lookahead`` (one-step lookahead over the policy's own greedy continuations);
the CP-SAT solver adds ``cpsat``. Each solver module registers itself with :func:`register`.
"""
from __future__ import annotations

import functools
import importlib
import re
from typing import Any, Callable

from .instance import Instance
from .solution import Solution

Solver = Callable[..., Solution]
_REGISTRY: dict[str, Solver] = {}
# modules imported lazily the first time one of their methods is asked for
_LAZY = {"rl": "hmrta.rl.inference", "rl-sample": "hmrta.rl.inference", "rl-lookahead": "hmrta.rl.inference",
         "cpsat": "hmrta.solvers.cpsat"}


class MethodError(ValueError):
    """Unknown method name or bad method option (a user error)."""


def register(name: str, fn: Solver) -> None:
    _REGISTRY[name] = fn


def parse(method: str) -> tuple[str, dict[str, Any]]:
    """'rl-s10' -> ('rl-sample', {'samples': 10}); other names map to themselves."""
    m = re.fullmatch(r"rl-s(\d+)", method)
    if m:
        return "rl-sample", {"samples": int(m.group(1))}
    return method, {}


def get(method: str) -> Solver:
    if method not in _REGISTRY and method in _LAZY:
        importlib.import_module(_LAZY[method])
    if method not in _REGISTRY:
        known = sorted(set(_REGISTRY) | set(_LAZY) | {"rl-sN"})
        raise MethodError(f"unknown method {method!r} (expected one of {', '.join(known)})")
    return _REGISTRY[method]


def solve(inst: Instance, method: str, seed: int = 0, **options: Any) -> Solution:
    base, implied = parse(method)
    sol = get(base)(inst, seed=seed, **{**implied, **options})
    sol.method = method
    return sol


def _baseline(name: str, inst: Instance, seed: int = 0, **_: Any) -> Solution:
    from .baselines import BASELINES, GREEDY_RULES
    from .sim import simulate

    return simulate(inst, BASELINES[name](), seed, GREEDY_RULES, name)


def _random(inst: Instance, seed: int = 0, **_: Any) -> Solution:
    from .baselines import RandomPolicy
    from .core import Rules
    from .sim import simulate

    return simulate(inst, RandomPolicy(seed), seed, Rules(), "random")


for _name in ("greedy", "greedy-coalition"):  # = baselines.BASELINES (not imported here: keep start-up lean)
    register(_name, functools.partial(_baseline, _name))
register("random", _random)


def decider(method: str, seed: int = 0, **options: Any):
    """A per-decision policy for live use (ROS agents): returns ``(decide, rules)`` where
    ``decide(state) -> node`` and ``rules`` are the state-machine rules it must run under.

    ``greedy`` / ``greedy-coalition`` -> the baselines; ``rl`` / ``rl-sample`` -> the learned policy (greedy or
    sampled decoding; options: ``checkpoint``, ``seed``); ``rl-lookahead`` -> one-step lookahead
    over the learned policy (option: ``checkpoint``)."""
    base, implied = parse(method)
    if base in ("greedy", "greedy-coalition"):
        from .baselines import BASELINES, GREEDY_RULES

        return BASELINES[base](), GREEDY_RULES
    if base in ("rl", "rl-sample"):
        from .rl.inference import rl_decider

        return rl_decider(sample=base == "rl-sample", seed=seed, **options)
    if base == "rl-lookahead":
        from .rl.inference import lookahead_decider

        return lookahead_decider(**options)
    raise MethodError(f"method {method!r} has no per-decision form (expected greedy, greedy-coalition, rl, rl-sample or rl-lookahead)")
