"""Baseline decision functions: the paper's greedy, greedy-coalition and a seeded random policy.

Greedy (exact rule): the current decider takes the admissible task nearest to its current
position (travel time; ties broken by the lowest task id). Admissible means the state machine's
mask: the ability mask, the max-open-task rule (``GREEDY_RULES.max_open``; greedy-coalition runs
under ``COALITION_RULES``, the team-scaled cap) and the
deadlock-avoidance mask; an agent with no admissible task postpones (flashforward), and one with
no empty or open task left goes home. Greedy never picks the depot while a task is admissible.
With these rules it completes every feasible instance (tested on every paper row).
"""
from __future__ import annotations

import random

import numpy as np

from .core import EMPTY, IN_PROGRESS, LOST, OPEN, TASK, MissionState, Rules
from .sim import simulate

# max_open=2 was greedy's best of {1, 2, 3, 5, none} on seed-1 sets of six paper rows, and still is
# against the team-scaled cap on the dev sets of every family and paper row (docs/semantics.md).
GREEDY_RULES = Rules(max_open=2, safety=True)
# greedy-coalition's cap scales with the team (core.team_cap): on the same dev sets it is 1.3% below
# a cap of 2 on average (27 rows) and 12% below it on 150-robot missions, where 2 holds the team back.
COALITION_RULES = Rules(max_open="team", safety=True)


class Greedy:
    name = "greedy"

    def __call__(self, state: MissionState) -> int:
        cand = np.flatnonzero(state.mask()[1:])  # [C] admissible tasks
        if len(cand) == 0:
            return 1  # (never asked: a decider always has an admissible task)
        here = state.position(state.agent)  # [2]
        loc = state.inst.task_locations
        rel = loc[cand] - here  # [C, 2]
        if len(cand) > 64:
            # the squared distance is within a few ulps of the distance squared: only candidates
            # within a relative 1e-9 of the nearest can be nearest by np.hypot (ties: lowest id)
            d2 = rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1]  # [C]
            near = d2 <= d2.min() * (1.0 + 1e-9) + 1e-300  # [C]
            cand, rel = cand[near], rel[near]  # [C'] ascending ids
        return 1 + int(cand[np.argmin(np.hypot(rel[:, 0], rel[:, 1]))])


class CoalitionGreedy:
    """Coalition-aware greedy (project addition, not in the paper): the decider takes the
    admissible task whose coalition can *start* earliest, ties to the nearest.

    Start estimate for task j if agent a joins now: the latest of a's arrival, the arrivals of the
    members already committed, and - while a requirement remains after a - the arrivals of the other
    agents that would cover it, taken in order of their earliest possible arrival at j. An agent's
    earliest arrival is (when it is next free) + travel: an agent on an in-progress task is free at
    that task's finish, at its location; an agent committed to an open task is not counted (it is
    held there); free, parked and postponed agents are free now, where they are. A task whose
    requirement the counted agents cannot cover gets an infinite estimate. It uses only what the
    task board knows (commitments, arrivals, finish times), so it runs decentralised like greedy.
    """

    name = "greedy-coalition"

    # admissible tasks estimated at once; with more, the nearest first (below)
    CHUNK = 64

    def __call__(self, state: MissionState) -> int:
        """The admissible task of the earliest estimated start, ties to the nearest, then to the
        lowest id; 0 (the depot) when none is admissible.

        A start is never before the decider's own arrival, so with many admissible tasks they are
        estimated nearest first, in chunks (CHUNK, then twice as many, ...), until the best start
        found is earlier than the arrival at every task not yet estimated: the same choice as
        estimating them all (each task's estimate does not depend on the others)."""
        cand = np.flatnonzero(state.mask()[1:])  # [C]
        if len(cand) <= self.CHUNK:
            cand, start, mine = self.estimates(state, cand)
            if len(cand) == 0:
                return 0
            return 1 + int(cand[np.lexsort((mine, start))[0]])  # earliest start, then nearest, then lowest id
        own = self._arrival(state, state.positions()[state.agent], cand)  # [C] the estimates' own arrival
        order = np.argsort(own, kind="stable")  # [C] nearest first
        best, lo, size = None, 0, self.CHUNK
        while lo < len(order) and (best is None or best[0] >= own[order[lo]]):
            part, start, mine = self.estimates(state, np.sort(cand[order[lo:lo + size]]))  # ascending ids
            k = np.lexsort((part, mine, start))[0]
            if best is None or (start[k], mine[k], part[k]) < best:
                best = (start[k], mine[k], part[k])
            lo, size = lo + size, 2 * size
        return 1 + int(best[2])

    def estimates(self, state: MissionState, tasks: np.ndarray | None = None,
                  positions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(admissible tasks [C], estimated coalition start if the decider joins [C], the decider's
        own arrival [C]) for the current decider; ``tasks`` (ids): only the admissible ones among them;
        ``positions``: ``state.positions()`` if the caller has it (not changed here)."""
        mask = state.mask()[1:]  # [M]
        cand = np.flatnonzero(mask) if tasks is None else tasks[mask[tasks]]  # [C]
        if len(cand) == 0:
            return cand, np.zeros(0), np.zeros(0)
        s, a, t = state, state.agent, state.clock
        v = s.inst.velocity
        loc = s.inst.task_locations[cand]  # [C, 2]
        pos = s.positions() if positions is None else positions.copy()  # [A, 2]
        free_at = np.full(s.A, t)  # [A]
        usable = s.mode != LOST  # [A]
        usable[a] = False
        on_task = (s.mode == TASK) & (s.target >= 0)  # [A]
        tgt = np.where(on_task, s.target, 0)  # [A]
        running = on_task & (s.status[tgt] == IN_PROGRESS)  # [A]
        free_at[running] = s.finish[tgt[running]]
        pos[running] = s.inst.task_locations[tgt[running]]
        usable &= ~(on_task & (s.status[tgt] == OPEN))
        mine = self._arrival(s, pos[a], cand)  # [C] a's arrival (a is free now)
        start = mine.copy()  # [C]
        for c in np.flatnonzero(s.status[cand] != EMPTY):  # an empty task has no members
            mem = s.members[cand[c]]
            if mem:
                start[c] = max(start[c], s.arrive[mem].max())
        rem = s._remaining(s.rem[cand] - s.cap[a])  # [C, K] left after a joins
        need = (rem > 1e-9).any(1)  # [C]
        others = np.flatnonzero(usable)  # [B]
        if need.any() and len(others) == 0:
            start = np.where(need, np.inf, start)  # nobody left to complete those coalitions
        elif need.any():
            col = np.flatnonzero(need)  # [N] the tasks a still needs others for
            last = self._completing_arrival(free_at[others], pos[others], loc[col], v, s.cap[others], rem[col],
                                            exact=s._exact)  # [N]
            start[col] = np.maximum(start[col], last)
        return cand, start, mine

    @staticmethod
    def _arrival(state: MissionState, here: np.ndarray, tasks: np.ndarray) -> np.ndarray:
        """[C] when a robot free now at ``here`` [2] arrives at ``tasks`` [C] (ids)."""
        return state.clock + np.hypot(*(state.inst.task_locations[tasks] - here).T) / state.inst.velocity

    # robots free at the same time at the same place (a coalition that finished together, a team
    # parked at its depot) arrive together at every task: the estimates compute one arrival per
    # group of such robots (at most GROUP robots in a group; a larger one is split), and look at the
    # earliest groups first, PARTIAL robots' worth on average (a coalition rarely needs more), then
    # four times as many, and so on
    PARTIAL = 16
    GROUP = 4
    GROUPED = 64  # teams of more robots than this are grouped

    @classmethod
    def _completing_arrival(cls, free_at: np.ndarray, pos: np.ndarray, loc: np.ndarray, v: float,
                            cap: np.ndarray, rem: np.ndarray, exact: bool = False) -> np.ndarray:
        """[N] for each task at ``loc`` [N, 2], the arrival time at which the robots free at
        ``free_at`` [B] at ``pos`` [B, 2] (speed ``v``, capabilities ``cap`` [B, K]), taken in order
        of arrival ``free_at + |pos - loc| / v`` (ties: lowest robot first), first cover ``rem``
        [N, K]; inf where all of them do not. Every row of ``rem`` needs something (an entry above
        1e-9: the tasks the decider cannot complete alone).

        Robots with the same (free_at, position) have the same arrival at every task, computed once
        per group. A group with none of the skills a task still needs is left out of that task
        (its arrival set to inf). Of the others only the earliest groups are expanded into their
        robots, which are sorted as the full sort does (by arrival, then index). Where they cover
        the requirement, the answer is the full sort's, bit for bit: every robot arriving before
        the latest of those groups (L) is among them, in the same order, so a cover before L is
        the full sort's; a cover at L is too, since the full sort, taking every robot arriving at
        L, has running sums at least as large by the end of them (capabilities are non-negative
        and rounding is monotone) and none that covered earlier. A robot of those groups that has
        none of the skills still needed changes no running sum of those skills (adding 0.0 is
        exact), so it never completes the cover, as if it were left out. Where the earliest groups
        include a left-out one, they hold every robot that counts, and an uncovered requirement
        stays uncovered. The other tasks (a coalition of many robots) look at four times as many
        groups, and so on up to all of them: the full sort, robot by robot.

        ``exact``: every capability and remaining requirement is a multiple of 2^-24 and their
        sums stay below 2^28 (``MissionState._exact``), so every running sum is exact whatever the
        order of its terms. A large team then takes :meth:`_completing_arrival_by_place`."""
        B, N, K = len(free_at), len(loc), cap.shape[1]
        if exact and B > cls.GROUPED:
            return cls._completing_arrival_by_place(free_at, pos, loc, v, cap, rem)
        idx = np.arange(B)  # [B]
        if B <= cls.GROUPED:  # a small team: each robot a group of its own
            width, gof = 1, idx  # gof [B]: the group of each robot
            members = idx[:, None]  # [G = B, 1]
            arr = free_at + np.hypot(pos[:, 0] - loc[:, 0:1], pos[:, 1] - loc[:, 1:2]) / v  # [N, B]
            has = cap > 0  # [B, K]
        else:
            order, new, first, arr = cls._places(free_at, pos, loc, v)  # [B], [B], [S], [N, S]
            same = np.cumsum(new) - 1  # [B] set of order[i]
            width = min(cls.GROUP, int(np.diff(first, append=B).max()))  # robots in a group, at most
            new[(idx - first[same]) % width == 0] = True  # split the sets: at most width robots a group
            first = np.flatnonzero(new)  # [G]
            group = np.cumsum(new) - 1  # [B] group of order[i]
            members = np.full((len(first), width), B)  # [G, width] robots of each group, by index (B: none)
            members[group, idx - first[group]] = order
            gof = np.empty(B, dtype=np.int64)
            gof[order] = group
            if len(first) > arr.shape[1]:
                arr = arr[:, same[first]]  # [N, G]
            has = np.logical_or.reduceat(cap[order] > 0, first, axis=0)  # [G, K] skills of each group
        useful = has.astype(np.float64) @ (rem > 1e-9).T.astype(np.float64) > 0  # [G, N]
        arr = np.where(useful.T, arr, np.inf)  # [N, G]
        cap = np.vstack([cap, np.zeros((1, K))])  # [B + 1, K] (row B: no robot)

        def robots_in_order(rows, part, ga):  # the robots of the groups looked at, by arrival, then index
            if part is not None:  # the earliest groups, expanded into their robots
                robots = members[part].reshape(len(ga), -1)  # [R, q width]
                ra = np.where(robots < B, np.repeat(ga, width, axis=1), np.inf) if width > 1 else ga  # [R, q width]
                o = np.lexsort((robots, ra), axis=1)  # [R, q width] (as the full sort)
            else:  # every robot: the full sort
                robots, ra = np.broadcast_to(idx, (len(ga), B)), ga[:, gof]  # [R, B] each, by index
                o = np.argsort(ra, axis=1, kind="stable")  # [R, B]
            return np.take_along_axis(ra, o, 1), cap[np.take_along_axis(robots, o, 1)]

        return cls._earliest_cover(arr, -(-cls.PARTIAL * len(members) // B), rem, robots_in_order)

    @staticmethod
    def _places(free_at: np.ndarray, pos: np.ndarray, loc: np.ndarray | None = None, v: float = 1.0):
        """The robots [B] sorted by (free_at, x, y), ties by index (``order``), where each set of
        equal (free_at, x, y) starts (``new`` [B] over the order, ``first`` [S]), and each set's
        arrival at each task at ``loc`` [N, 2] (``arr`` [N, S]; None without ``loc``)."""
        order = np.lexsort((pos[:, 1], pos[:, 0], free_at))  # [B] (lexsort is stable: ties by index)
        f, x, y = free_at[order], pos[order, 0], pos[order, 1]  # [B] each
        new = np.ones(len(order), dtype=bool)  # [B] order[i] starts a set
        new[1:] = (f[1:] != f[:-1]) | (x[1:] != x[:-1]) | (y[1:] != y[:-1])
        first = np.flatnonzero(new)  # [S]
        arr = None if loc is None else f[first] + np.hypot(x[first] - loc[:, 0:1], y[first] - loc[:, 1:2]) / v
        return order, new, first, arr  # arr [N, S]

    @classmethod
    def _sets(cls, free_at: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The robots [B] in an order where each set of equal (free_at, x, y) is a run (``order``),
        and where each run starts (``first`` [S]); the order of the sets is left open. With every
        robot a set of its own, ``order`` is the identity. Robots sorted by x alone are in such an
        order when every two neighbours of equal x are at the same y and free at the same time
        (a coalition that finished together), which :meth:`_places`' full sort then need not
        find."""
        B = len(free_at)
        o = np.argsort(pos[:, 0])  # [B]
        xs, ys, fs = pos[o, 0], pos[o, 1], free_at[o]  # [B] each
        same_x = xs[1:] == xs[:-1]  # [B - 1]
        if not same_x.any():
            return np.arange(B), np.arange(B)
        if (~same_x | ((ys[1:] == ys[:-1]) & (fs[1:] == fs[:-1]))).all():
            return o, np.flatnonzero(np.concatenate([[True], ~same_x]))
        order, _, first, _ = cls._places(free_at, pos)
        return order, first

    # the approximate arrivals of _completing_arrival_by_place are within a relative few 1e-16 of
    # the exact ones (coordinates in the unit square, speed at least MIN_VELOCITY: no overflow, and
    # an underflow moves an arrival by under 1e-144); the search allows a relative 1e-9
    APPROX_RTOL = 1e-9
    APPROX_ATOL = 1e-40

    @classmethod
    def _completing_arrival_by_place(cls, free_at: np.ndarray, pos: np.ndarray, loc: np.ndarray, v: float,
                                     cap: np.ndarray, rem: np.ndarray) -> np.ndarray:
        """:meth:`_completing_arrival` when the arithmetic is exact: over the sets of robots free
        at the same (free_at, position), each counted as one robot with the sum of their
        capabilities, taken in order of arrival (ties in any order).

        The same result bit for bit: with exact sums, the full sort's answer is the earliest
        arrival t at which the robots arriving by t cover the requirement (its covering robot
        arrives at t, and every robot before it arrives by t; no robot arriving before t is
        preceded by one arriving later, so by any earlier time the robots arriving are a prefix
        that does not cover). Summing by sets, in order of arrival, finds that t: the running sum
        after every set arriving by t is the sum of the robots arriving by t, whatever the order
        among sets of equal arrival, and a set that covers midway through a run of sets of
        equal arrival covers at that arrival. Sets with none of the skills still needed are left
        out (their arrival set to inf): they add nothing to what is needed.

        The earliest sets are looked at first (PARTIAL robots' worth on average, then four times
        as many), chosen by approximate arrivals (distances as sqrt(dx^2 + dy^2), a quarter of
        np.hypot's cost, within ``d`` of the exact arrival: APPROX_RTOL x |arrival| +
        APPROX_ATOL, since with free_at >= 0 an arrival is at least each of its two terms; with a
        negative free_at, APPROX_RTOL x (|arrival| + the largest |free_at|) + APPROX_ATOL), and
        summed in order of their exact arrivals (the full
        sort's ``free_at + np.hypot(dx, dy) / v``, bit for bit). A cover at t by the sets looked
        at is the answer when every other set arrives (exactly) at t or later, which holds when
        the earliest of them arrives at t + d or later by its approximate arrival; otherwise four
        times as many sets are looked at, up to all of them."""
        B = len(free_at)
        order, first = cls._sets(free_at, pos)  # [B], [S]
        S = len(first)
        if S == B:  # every robot a set of its own
            f, x, y, cap_s = free_at, pos[:, 0], pos[:, 1], cap  # [S] each, [S, K]
        else:
            f, x, y = free_at[order[first]], pos[order[first], 0], pos[order[first], 1]  # [S] each
            cap_s = np.add.reduceat(cap[order], first, axis=0)  # [S, K] capability of each set (exact sums)
        # f + sqrt(dx^2 + dy^2) / v, in place (the same operations, in the same order)
        arr = x - loc[:, 0:1]  # [N, S] dx
        arr *= arr
        dy = y - loc[:, 1:2]  # [N, S]
        dy *= dy
        arr += dy
        np.sqrt(arr, out=arr)
        arr /= v
        arr += f  # [N, S] approximate arrivals
        useless = (rem > 1e-9).astype(np.float64) @ (cap_s > 0).T.astype(np.float64) == 0  # [N, S]
        arr[useless] = np.inf
        big = 0.0 if f.min() >= 0 else float(np.abs(f).max())  # (times in a mission are never negative)

        def sets_in_order(rows, part, ga):  # the sets looked at, by exact arrival (ties in any order)
            part = np.broadcast_to(np.arange(S), ga.shape) if part is None else part  # [R, q]
            ex = f[part] + np.hypot(x[part] - loc[rows, 0:1], y[part] - loc[rows, 1:2]) / v  # [R, q]
            ex = np.where(np.isfinite(ga), ex, np.inf)  # sets left out stay out
            o = np.argsort(ex, axis=1)  # [R, q]
            return np.take_along_axis(ex, o, 1), cap_s[np.take_along_axis(part, o, 1)]

        def slack(after):  # [R] how much earlier than ``after`` (approximate) a set may arrive exactly
            return cls.APPROX_RTOL * (np.abs(after) + big) + cls.APPROX_ATOL

        return cls._earliest_cover(arr, -(-cls.PARTIAL * S // B), rem, sets_in_order, slack, distinct=True)

    @classmethod
    def _earliest_cover(cls, arr: np.ndarray, q: int, rem: np.ndarray, in_order, slack=None,
                        distinct: bool = False) -> np.ndarray:
        """[N] for each task (row of ``arr`` [N, G], the arrival of each group, inf for one left
        out) the arrival at which the groups looked at first cover ``rem`` [N, K], inf where they
        do not: first the ``q`` earliest groups, then four times as many for the tasks they leave
        uncovered while groups remain, up to all of them. ``in_order(rows [R], part [R, q] or None
        for all, their arrivals [R, q])`` gives the arrivals and capabilities ([R, n], [R, n, K])
        of what those groups hold at those tasks, in the order their capabilities are summed.

        ``slack``: the arrivals ``arr`` are approximate (``slack(a)`` [R] bounds how much earlier
        than a the exact arrival of a group approximately at a [R] may be) and ``in_order`` gives
        exact ones; a cover is then taken only where the earliest group not looked at arrives no
        earlier (exactly) than it, else more groups are looked at.

        ``distinct``: equal arrivals of different groups are rare (they are common among the
        groups of one set of robots split by GROUP): the q earliest are found by a partition of the
        values, which costs less than the argument partition it falls back on at a tie."""
        N, G = arr.shape
        last = np.full(N, np.inf)  # [N]
        rows = np.arange(N)  # [R] the tasks still undecided
        while len(rows):
            a = arr if len(rows) == N else arr[rows]  # [R, G] (not written to)
            if q < G:  # the q earliest groups, and the earliest of the others
                part = None
                if distinct:
                    after = np.partition(a, q, axis=1)[:, q]  # [R] the earliest not looked at
                    at = np.flatnonzero(a < after[:, None])  # [<= R q] at most q a row, flat, row by row
                    if len(at) == q * len(rows):  # q in every row: the q earliest
                        part = at.reshape(len(rows), q) - (G * np.arange(len(rows)))[:, None]  # [R, q]
                        ga = a.reshape(-1)[at].reshape(len(rows), q)  # [R, q] their arrivals
                if part is None:  # (or a tie at the q-th arrival: q of the earliest, any of the tied ones)
                    part = np.argpartition(a, q, axis=1)  # [R, G]
                    after = np.take_along_axis(a, part[:, q:q + 1], 1)[:, 0]  # [R] the earliest not looked at
                    part = part[:, :q]  # [R, q]
                    ga = np.take_along_axis(a, part, 1)  # [R, q] their arrivals
                more = np.isfinite(after)  # [R] groups not looked at yet may still count
            else:
                part, ga, more = None, a, np.zeros(len(rows), dtype=bool)
            t, ok = cls._first_cover(*in_order(rows, part, ga), rem[rows])
            if slack is not None and more.any():  # every group not looked at arrives at t or later
                after = np.where(more, after, 0.0)
                ok &= ~more | (t <= after - slack(after))
            last[rows[ok]] = t[ok]
            rows = rows[~ok & more]  # undecided, with groups not looked at yet
            q *= 4
        return last

    @staticmethod
    def _first_cover(arr_sorted: np.ndarray, cap_sorted: np.ndarray, rem: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(arrival time of the robot that first covers ``rem``, whether any prefix does) [N] each, for
        arrivals sorted per row ([N, n]) with their capabilities ([N, n, K])."""
        cum = np.cumsum(cap_sorted, axis=1)  # [N, n, K] capability of the first i arrivals
        covered = (cum >= rem[:, None] - 1e-9).all(2)  # [N, n]
        first = np.argmax(covered, axis=1)  # [N]
        return arr_sorted[np.arange(arr_sorted.shape[0]), first], covered.any(1)


# the deterministic baselines by method name (solvers, live deciders and training teachers); as
# methods they run under their own rules (hmrta.methods), as training teachers under the student's
BASELINES = {"greedy": Greedy, "greedy-coalition": CoalitionGreedy}


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


RANDOM_RULES = Rules()  # the random policy explores the unrestricted state machine


# --- entry points of the method table (hmrta.methods.METHODS) ---------------------------------
def solve_greedy(inst, seed: int = 0):
    return simulate(inst, Greedy(), seed, GREEDY_RULES, "greedy")


def solve_greedy_coalition(inst, seed: int = 0):
    return simulate(inst, CoalitionGreedy(), seed, COALITION_RULES, "greedy-coalition")


def solve_random(inst, seed: int = 0):
    return simulate(inst, RandomPolicy(seed), seed, RANDOM_RULES, "random")


def greedy_decider(seed: int = 0) -> Greedy:
    return Greedy()


def coalition_decider(seed: int = 0) -> CoalitionGreedy:
    return CoalitionGreedy()


def random_decider(seed: int = 0) -> RandomPolicy:
    return RandomPolicy(seed)
