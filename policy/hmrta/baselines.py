"""Baseline decision functions: the paper's greedy and a seeded random policy.

Greedy (exact rule): the current decider takes the admissible task nearest to its current
position (travel time; ties broken by the lowest task id). Admissible means the state machine's
mask: the ability mask, the max-open-task rule (``GREEDY_RULES.max_open``) and the
deadlock-avoidance mask; an agent with no admissible task postpones (flashforward), and one with
no empty or open task left goes home. Greedy never picks the depot while a task is admissible.
With these rules it completes every feasible instance (tested on every paper row).
"""
from __future__ import annotations

import random

import numpy as np

from .core import MissionState, Rules

# max_open=2 was the best of {1, 2, 3, 5, none} on seed-1 sets of six paper rows (README, "Greedy").
GREEDY_RULES = Rules(max_open=2, safety=True)


class Greedy:
    name = "greedy"

    def __call__(self, state: MissionState) -> int:
        mask = state.mask()[1:]  # [M]
        here = state.position(state.agent)  # [2]
        d = np.hypot(*(state.inst.task_locations - here).T)  # [M]
        d = np.where(mask, d, np.inf)
        return 1 + int(np.argmin(d))


class RandomPolicy:
    """Uniform over admissible nodes (depot included when allowed); seeded, for tests."""

    name = "random"

    def __init__(self, seed: int = 0, depot_weight: float = 1.0):
        self.rng = random.Random(seed)
        self.depot_weight = depot_weight

    def __call__(self, state: MissionState) -> int:
        nodes = np.flatnonzero(state.mask())
        w = [self.depot_weight if n == 0 else 1.0 for n in nodes]
        return int(self.rng.choices(list(nodes), weights=w)[0])
