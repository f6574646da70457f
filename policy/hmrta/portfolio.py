"""``portfolio``: per mission, the best of several methods, chosen by simulating each one.

Every candidate (by default the learned policy with three shipped checkpoints, greedy-coalition
and greedy) is rolled out on the mission as it is known at the start, and the mission is then run
with the candidate of the shortest makespan. Offline on a static mission this is simply the best of
the candidates, so it is never worse than any of them; the cost is the sum of their solve times
(greedy rules are milliseconds, the learned policy a fraction of a second up to 50 tasks).

Missions that change while they run (tasks released later, timed events of a scenario) are not
known in advance: the choice is made on the initial mission only (the tasks released at time 0,
no events), then the chosen method runs the whole mission without knowing the events before their
time, like every other online method. Ties go to the first candidate listed, and so does the
choice when no task is known at time 0 (every makespan is then 0): the default list is in the order
of the candidates' makespans on missions that change (docs/results.md, "Missions that change"),
so that a choice made on little or nothing falls on the method best at the unknown.

A live mission's choice is made before it starts, with :func:`select`: by the task board (whose
``method`` defaults to ``portfolio``; it names the chosen method in the mission, and agents started
with ``portfolio`` run that one) or by ``hmrta-mission --method portfolio``. The robots then run an
ordinary method under its rules; ``portfolio`` itself has no per-decision form.
"""
from __future__ import annotations

import dataclasses
import logging
import os
from typing import Callable

from .errors import MethodError
from .instance import Instance
from .solution import Solution

def initial_view(inst: Instance) -> Instance:
    """The mission as known at time 0: tasks released at 0, no timed events or added robots."""
    if not inst.dynamic:
        return inst
    return dataclasses.replace(inst, tasks=tuple(t for t in inst.tasks if t.release <= 0), events=(),
                               added_agents=())


def candidate_methods(candidates: str | None) -> list[str]:
    """The candidate methods (default: the method table's default of the ``candidates`` option).
    Each must have a per-decision form, so that a live mission can run the one chosen."""
    from . import methods

    if candidates is None:
        candidates = methods.get("portfolio").option("candidates").default
    names = [c.strip() for c in candidates.split(",") if c.strip()]
    if not names:
        raise MethodError("portfolio: option candidates: expected a comma list of methods, got nothing")
    for c in names:
        try:
            name, _ = methods.parse(c)
        except methods.UnknownMethod:  # (the candidates are the live methods, not every method)
            raise MethodError(f"portfolio: option candidates: unknown method {c.partition('@')[0]!r} (expected "
                              f"one of {', '.join(methods.live_methods())}, or rl-sN; METHOD@CHECKPOINT for "
                              f"an rl method with a checkpoint of its own)") from None
        except MethodError as e:
            raise MethodError(f"portfolio: option candidates: {e}") from None
        _check_checkpoint(f"portfolio: option candidates: {c}: ", methods.parse(c)[1].get("checkpoint"))
        if methods.get(name).decide is None:
            raise MethodError(f"portfolio: option candidates: {c} cannot be a candidate (it has no per-decision "
                              f"form; candidates: {', '.join(methods.live_methods())})")
    return names


def checked(checkpoint: str | None, candidates: str | None) -> list[str]:
    """The candidate methods (:func:`candidate_methods`), once every checkpoint named to the
    portfolio is a file here: its own, or else ``$HMRTA_CHECKPOINT``, and the candidates'
    ``rl@CHECKPOINT`` ones, whether or not a candidate ends up reading them. What a board and the
    agents started with the portfolio check at start, before anything is simulated."""
    names = candidate_methods(candidates)
    _check_checkpoint("portfolio: option checkpoint: ", checkpoint)
    _check_checkpoint("", None if checkpoint else os.environ.get("HMRTA_CHECKPOINT"))  # (the error names it)
    return names


def _check_checkpoint(prefix: str, checkpoint: str | None) -> None:
    """A checkpoint named to the portfolio (its own, or a candidate's ``rl@CHECKPOINT``) is a file
    here, whether or not a candidate ends up reading it: MethodError ``prefix`` + why otherwise."""
    from .rl.checkpoint_info import CheckpointError, checkpoint_path, existing

    if checkpoint:
        try:
            existing(checkpoint_path(checkpoint))
        except CheckpointError as e:
            raise CheckpointError(f"{prefix}{e}") from None


def _cannot_run(inst: Instance, spec: str) -> str | None:
    """Why candidate ``spec`` cannot run here or on ``inst`` (its optional dependency missing, or a
    mission with more skills than the learned policy takes), or None."""
    from . import methods
    from .deps import MissingDependency

    try:
        methods.check_runnable(spec, inst)
    except (MissingDependency, MethodError) as e:
        return str(e)
    return None


def evaluate(inst: Instance, seed: int = 0, checkpoint: str | None = None,
             candidates: str | None = None, left_out: dict[str, str] | None = None,
             progress: Callable[..., None] | None = None) -> dict[str, Solution]:
    """Each candidate's solution on the initial view of ``inst``. Of the default candidates, those
    that cannot run here (torch missing for rl) or on this mission (more skills than the learned
    policy takes) are left out, with the reason put in ``left_out``; a candidate the caller named
    that cannot run raises, and so does any other error (a checkpoint that cannot be read: the
    ``checkpoint`` option, $HMRTA_CHECKPOINT or a damaged shipped file). ``progress(done, total,
    unit, note)``, if given, is called before and after each candidate (a large mission takes
    seconds to minutes per learned candidate)."""
    from . import methods

    view = initial_view(inst)
    out: dict[str, Solution] = {}
    missing: dict[str, str] = {}
    names = checked(checkpoint, candidates)
    for i, c in enumerate(names):
        why = None if candidates is not None else _cannot_run(view, c)  # named candidates: their own error
        if why is not None:
            missing[c] = why
            continue
        if progress is not None:
            progress(i, len(names), "candidate", f"simulating {c}")
        out[c] = methods.solve(view, c, seed=seed, **methods.options_for(c, {"checkpoint": checkpoint}))
        if progress is not None:
            progress(i + 1, len(names), "candidate", f"{c} {out[c].makespan:.2f}")
    if not out:
        raise MethodError(f"portfolio: no candidate could run ({'; '.join(missing.values())})")
    if left_out is not None:
        left_out.update(missing)
    return out


def choose(results: dict[str, Solution]) -> str:
    """The candidate with the shortest makespan among the successful ones (ties: the first listed)."""
    ok = [(s.makespan, i, c) for i, (c, s) in enumerate(results.items()) if s.success]
    return min(ok)[2] if ok else next(iter(results))


def select(inst: Instance, seed: int = 0, checkpoint: str | None = None, candidates: str | None = None,
           progress: Callable[..., None] | None = None) -> tuple[str, dict[str, float]]:
    """(the method to run a live mission with, makespan of every candidate on the initial view).
    A candidate whose live form is not the one simulated (rl-sN: live, one sampled decision per
    turn) is refused. With no task known at time 0 every candidate's makespan is 0 and the first
    listed that can run is chosen. Default candidates left out are logged as a warning (a live
    mission has no summary)."""
    from . import methods

    for c in candidate_methods(candidates):  # what the choice simulates is what runs live
        if methods.parse(c)[0] == "rl-sample":
            raise MethodError(f"portfolio: option candidates: {c} cannot be a candidate of a live mission: live, "
                              f"rl-sample decodes one sampled decision per turn, not the best of several rollouts "
                              f"that the choice would simulate (rl, its greedy decoding, can)")
    left_out: dict[str, str] = {}
    results = evaluate(inst, seed, checkpoint, candidates, left_out, progress)
    for c, why in left_out.items():
        logging.getLogger(__name__).warning("portfolio: left out %s (%s)", c, why)
    return choose(results), {c: s.makespan for c, s in results.items()}


def solve_portfolio(inst: Instance, seed: int = 0, checkpoint: str | None = None,
                    candidates: str | None = None, progress: Callable[..., None] | None = None) -> Solution:
    from . import methods

    left_out: dict[str, str] = {}
    results = evaluate(inst, seed, checkpoint, candidates, left_out, progress)
    chosen = choose(results)
    sol = results[chosen]
    spent = sum(s.compute_seconds for s in results.values())  # each without loading its model, as for any method
    if inst.dynamic:  # the choice saw only the initial mission: now run the real one, events and all
        sol = methods.solve(inst, chosen, seed=seed, **methods.options_for(chosen, {"checkpoint": checkpoint}))
        spent += sol.compute_seconds
    sol.compute_seconds = spent
    sol.extra["portfolio"] = {"chosen": chosen, "candidates": {c: s.makespan for c, s in results.items()}}
    if inst.dynamic:  # what the candidates' makespans are of
        sol.extra["portfolio"]["tasks_known_at_start"] = initial_view(inst).n_tasks
    if left_out:  # default candidates that could not run here (e.g. rl without torch), with the reason
        sol.extra["portfolio"]["left_out"] = left_out
    return sol
