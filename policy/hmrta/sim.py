"""The event-driven simulator: runs a decision function on the SPEC §3 state machine."""
from __future__ import annotations

import time
from typing import Protocol

from .core import MissionState, Rules
from .instance import Instance
from .solution import Solution, solution_from_state


class Policy(Protocol):
    """A decision function: given the state (current decider ``state.agent``, admissible nodes
    ``state.mask()``), return a node (0 = depot, 1 + m = task m)."""

    def __call__(self, state: MissionState) -> int: ...


def run(inst: Instance, policy: Policy, seed: int = 0, rules: Rules = Rules()) -> MissionState:
    """Roll out one episode; returns the finished state."""
    state = MissionState(inst, seed=seed, rules=rules)
    while not state.done:
        state.step(policy(state))
    return state


def simulate(inst: Instance, policy: Policy, seed: int = 0, rules: Rules = Rules(),
             method: str | None = None) -> Solution:
    """Roll out one episode and return its Solution (compute_seconds = wall time of the rollout)."""
    t0 = time.perf_counter()
    state = run(inst, policy, seed, rules)
    dt = time.perf_counter() - t0
    return solution_from_state(state, method or getattr(policy, "name", "policy"), seed, dt)
