"""The per-decision fast paths equal straightforward references, decision by decision, on random
seeded missions with mission events (tasks released, added and cancelled, robots added and lost,
scheduled and immediate): the core's masks (:meth:`MissionState._task_mask` against
``_task_mask_reference``, the old full recomputation), greedy's choice, and the rl observation
(window chosen first, features built for its rows only) against features of every task and agent
windowed afterwards."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hmrta.baselines import COALITION_RULES, GREEDY_RULES, CoalitionGreedy, Greedy
from hmrta.core import IN_PROGRESS, LOST, OPEN, TASK, UNRELEASED, EventRejected, MissionState, Rules
from hmrta.generators import SCENARIOS, ScenarioGenerator
from hmrta.instance import Task, instance_from_dict

RULES = [Rules(), Rules(max_open=2), Rules(max_open="team"), Rules(safety=False), Rules(max_open=1, backdate=False)]
FRACTIONS = [0.1, 0.25, 0.3, 0.7, 1.0, 1.5]  # 0.1, 0.3, 0.7: masks take the reference path (inexact sums)


def _instance(rng: np.random.Generator):
    if rng.random() < 0.2:  # fractional traits and requirements
        K, S = int(rng.integers(1, 4)), int(rng.integers(1, 4))
        species = [{"traits": [float(rng.choice(FRACTIONS)) for _ in range(K)], "count": int(rng.integers(1, 4)),
                    "depot": rng.random(2).tolist()} for _ in range(S)]
        team = np.sum([np.array(sp["traits"]) * sp["count"] for sp in species], 0)  # [K]
        tasks = []
        for _ in range(int(rng.integers(2, 12))):
            req = [float(min(team[k], rng.choice(FRACTIONS))) if rng.random() < 0.6 else 0.0 for k in range(K)]
            if not any(req):
                req[int(np.argmax(team))] = float(min(team.max(), 0.3))
            tasks.append({"location": rng.random(2).tolist(), "requirements": req, "duration": float(rng.random() * 3)})
        return instance_from_dict({"format": "hmrta-instance/1", "requirement_type": "additive", "velocity": 0.2,
                                   "skills": K, "species": species, "tasks": tasks})
    scenario = SCENARIOS[int(rng.integers(len(SCENARIOS)))]
    K = int(rng.integers(2, 5))
    S = int(rng.integers(K if scenario.startswith("SA") else 1, min(6, 2 ** K - 1) + 1))
    inst = ScenarioGenerator(scenario, S * int(rng.integers(2, 4)), S, int(rng.integers(3, 25)), K).sample(rng)
    if rng.random() < 0.5:  # some tasks released later
        grid = rng.random() < 0.5  # shared locations on a coarse grid: distance ties
        tasks = tuple(dataclasses.replace(t, release=float(rng.random() * 10) if rng.random() < 0.3 else 0.0,
                                          location=tuple(float(x) for x in rng.integers(0, 3, 2) / 2) if grid
                                          else t.location) for t in inst.tasks)
        inst = dataclasses.replace(inst, tasks=tasks, _cache={})
    return inst


def _event(rng: np.random.Generator, s: MissionState) -> None:
    """A random mission event, now or scheduled for later (rejections are part of the mix)."""
    kind = ("add_task", "cancel_task", "add_agent", "drop_agent")[int(rng.integers(4))]
    rec: dict = {"type": kind, "t": s.clock + (float(rng.random() * 5) if rng.random() < 0.4 else 0.0)}
    if kind == "add_task":
        req = [float(rng.integers(0, 3)) for _ in range(s.K)]
        req[0] = req[0] if any(req) else 1.0
        rec["task"] = {"location": rng.random(2).tolist(), "requirements": req, "duration": float(rng.random() * 4)}
    elif kind == "cancel_task":
        rec["task"] = int(rng.integers(s.M))
    elif kind == "add_agent":
        if rng.random() < 0.7:
            rec["species"] = int(rng.integers(s.inst.n_species))
        else:
            rec["traits"] = [float(rng.integers(0, 3)) for _ in range(s.K)]
            rec["position"] = rng.random(2).tolist()
    else:
        rec["agent"] = int(rng.integers(s.A))
    try:
        if rec["t"] > s.clock:
            s.schedule(rec)
        elif kind == "add_task":
            d = rec["task"]
            s.add_task(Task(tuple(d["location"]), tuple(d["requirements"]), d["duration"]))
        elif kind == "cancel_task":
            s.cancel_task(rec["task"])
        elif kind == "add_agent":
            s.add_agent(rec.get("species"), rec.get("traits"), rec.get("position"))
        else:
            s.drop_agent(rec["agent"])
    except EventRejected:
        pass


def missions(seed: int, n: int):
    """n random missions: (state, rng)."""
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        inst = _instance(rng)
        yield MissionState(inst, seed=int(rng.integers(100)), rules=RULES[int(rng.integers(len(RULES)))]), rng


def drive(s: MissionState, rng: np.random.Generator, check, policy=None) -> None:
    """Run s to the end with random events, calling check(s) before every decision; the policy
    picks at random among the admissible nodes by default."""
    while not s.done:
        if rng.random() < 0.08:
            _event(rng, s)
            if s.done:
                return
        check(s)
        if policy is None:
            cand = np.flatnonzero(s.mask())
            s.step(int(cand[int(rng.integers(len(cand)))]))
        else:
            s.step(policy(s))


def _all_robots_match(s: MissionState) -> None:
    for a in range(s.A):  # every robot, not only the decider: many more states of the check
        if s.mode[a] != LOST:
            assert np.array_equal(s._task_mask(a), s._task_mask_reference(a)), (s.decisions, a)


def _masks_match(s: MissionState) -> None:
    assert np.array_equal(s.mask(), s._mask_reference()), (s.decisions, s.agent)
    _all_robots_match(s)


@pytest.mark.parametrize("seed", [0, 1])
def test_masks_equal_the_reference_at_every_decision(seed):
    exact = inexact = 0
    for s, rng in missions(seed, 35):
        exact += s._exact
        inexact += not s._exact
        drive(s, rng, _masks_match)
    assert exact > 20 and inexact > 3  # both paths of _task_mask ran


def _with_safety(s: MissionState) -> MissionState:
    d = s.snapshot()
    d["rules"]["safety"] = True
    return MissionState.from_snapshot(s.inst, d)  # its pending mask is the one without the rule


@pytest.mark.parametrize("seed", [2, 3])
def test_masks_equal_the_reference_in_unsafe_states(seed):
    """States reached without the deadlock-avoidance rule, checked with it: the fast banker's
    check has branches for open tasks that cannot all complete, which a mission under the rule
    never reaches. Every unsafe state met is checked; one state per mission runs on with the rule."""
    unsafe = 0
    for s, rng in missions(seed, 40):
        s = MissionState(s.inst, seed=s.seed, rules=dataclasses.replace(s.rules, safety=False))
        go_on = int(rng.integers(1, 40))
        while not s.done and s.decisions < go_on:
            o = s.status == 1  # open tasks
            if not s._closure(s.rem[o], s.held[o], s.pool)[0]:
                unsafe += 1
                _all_robots_match(_with_safety(s))
            cand = np.flatnonzero(s.mask()[1:]) + 1  # tasks only: many open at once
            s.step(int(cand[int(rng.integers(len(cand)))]) if len(cand) else 0)
        if not s.done:
            s = _with_safety(s)
            _all_robots_match(s)
            cand = np.flatnonzero(s.mask())
            s.step(int(cand[int(rng.integers(len(cand)))]))
            drive(s, rng, _masks_match)
    assert unsafe >= 5


def test_exact_arithmetic_flag():
    inst = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(1, 0)
    s = MissionState(inst, seed=0)
    assert s._exact
    s.add_agent(traits=[0.5, 0.25, 0], position=[0.5, 0.5])  # dyadic: sums stay exact
    assert s._exact
    s.add_agent(traits=[0.1, 0, 0], position=[0.5, 0.5])  # 0.1 is not: the reference path from now on
    assert not s._exact
    assert not MissionState.from_snapshot(s.inst, s.snapshot())._exact
    assert MissionState.from_snapshot(inst, MissionState(inst, seed=0).snapshot())._exact


def _greedy_reference(state: MissionState) -> int:
    """Greedy by definition: the admissible task nearest the decider, ties to the lowest id."""
    mask = state.mask()[1:]  # [M]
    here = state.position(state.agent)  # [2]
    d = np.hypot(*(state.inst.task_locations - here).T)  # [M]
    return 1 + int(np.argmin(np.where(mask, d, np.inf)))


def test_greedy_equals_its_definition():
    greedy = Greedy()

    def same(s):
        assert greedy(s) == _greedy_reference(s)

    for s, rng in missions(4, 80):
        s = MissionState(s.inst, seed=s.seed, rules=GREEDY_RULES if rng.random() < 0.5 else s.rules)
        drive(s, rng, same, policy=greedy)
    inst = ScenarioGenerator("MA-AT", 150, 10, 500, 5).instance(1, 0)
    s = MissionState(inst, seed=0, rules=GREEDY_RULES)
    while not s.done:
        node = greedy(s)
        assert node == _greedy_reference(s)
        s.step(node)


def _coalition_reference(state: MissionState) -> tuple[np.ndarray, np.ndarray]:
    """greedy-coalition's start estimates by definition: every other usable robot's earliest
    arrival at every admissible task, all of them sorted (stable), the first prefix that covers
    what is left after the decider joins."""
    s, a, t = state, state.agent, state.clock
    cand = np.flatnonzero(s.mask()[1:])
    loc = s.inst.task_locations[cand]
    pos = s.positions()
    on_task = (s.mode == TASK) & (s.target >= 0)
    tgt = np.where(on_task, s.target, 0)
    running = on_task & (s.status[tgt] == IN_PROGRESS)
    free_at = np.where(running, s.finish[tgt], t)
    pos[running] = s.inst.task_locations[tgt[running]]
    usable = (s.mode != LOST) & ~(on_task & (s.status[tgt] == OPEN))
    usable[a] = False
    start = t + np.hypot(*(loc - pos[a]).T) / s.inst.velocity
    for c, j in enumerate(cand):
        if s.members[j]:
            start[c] = max(start[c], s.arrive[s.members[j]].max())
    rem = np.maximum(s.rem[cand] - s.cap[a], 0.0)
    others = np.flatnonzero(usable)
    for c in range(len(cand)):
        if not (rem[c] > 1e-9).any():
            continue
        arr = free_at[others] + np.hypot(*(pos[others] - loc[c]).T) / s.inst.velocity
        order = np.argsort(arr, kind="stable")
        covered = (np.cumsum(s.cap[others][order], 0) >= rem[c] - 1e-9).all(1)
        start[c] = max(start[c], arr[order][np.argmax(covered)]) if covered.any() else np.inf
    return cand, start


@pytest.mark.parametrize("partial,group,grouped", [(2, 1, 0), (3, 2, 0), (16, 4, 0), (2, 4, 64),
                                                    (CoalitionGreedy.PARTIAL, CoalitionGreedy.GROUP,
                                                     CoalitionGreedy.GROUPED)])
def test_coalition_estimates_equal_their_definition(partial, group, grouped, monkeypatch):
    """The partial sort (only the earliest arrivals, the full sort where they do not decide), over
    robots grouped by when and where they are free, gives the full sort's estimates bit for bit;
    small PARTIAL, GROUP and GROUPED values put every branch to work on small missions (distance
    ties on a grid, fractional capabilities, robots lost and added, teams at their depots)."""
    monkeypatch.setattr(CoalitionGreedy, "PARTIAL", partial)
    monkeypatch.setattr(CoalitionGreedy, "GROUP", group)
    monkeypatch.setattr(CoalitionGreedy, "GROUPED", grouped)
    gc = CoalitionGreedy()

    def same(s):
        cand, start, _ = gc.estimates(s)
        ref_cand, ref_start = _coalition_reference(s)
        assert np.array_equal(cand, ref_cand) and np.array_equal(start, ref_start), (s.decisions, s.agent)

    for s, rng in missions(7, 40):
        drive(s, rng, same, policy=gc if rng.random() < 0.5 else None)
    # a team larger than every PARTIAL tried (the shipped value included)
    s = MissionState(ScenarioGenerator("MA-AT", 60, 6, 120, 4).instance(3, 0), seed=0, rules=COALITION_RULES)
    while not s.done:
        same(s)
        s.step(gc(s))


def _completing_arrival_reference(free_at, pos, loc, v, cap, rem):
    """Every robot's arrival at every task, all sorted (stable), the first prefix that covers."""
    last = np.full(len(loc), np.inf)
    for j in range(len(loc)):
        arr = free_at + np.hypot(pos[:, 0] - loc[j, 0], pos[:, 1] - loc[j, 1]) / v
        order = np.argsort(arr, kind="stable")
        covered = (np.cumsum(cap[order], 0) >= rem[j] - 1e-9).all(1)
        if covered.any():
            last[j] = arr[order][np.argmax(covered)]
    return last


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_coalition_completing_arrival_of_large_teams_equals_the_full_sort(seed, exact):
    """Teams above GROUPED (grouped by when and where they are free): many robots at one place
    and time (larger than GROUP), places at equal distances from the tasks (arrival ties across
    groups), or every robot at a place of its own; fractional capabilities (``exact``: multiples
    of 1/4, summed by place), robots with none of the skills a task needs, requirements that take
    most of the team or that it cannot cover."""
    rng = np.random.default_rng(seed)
    B, N, K = CoalitionGreedy.GROUPED + int(rng.integers(1, 200)), int(rng.integers(2, 60)), int(rng.integers(1, 6))
    spots = rng.integers(0, 5, (int(rng.integers(1, 30)), 2)) / 4  # a coarse grid: equal distances
    times = rng.choice([0.0, 0.5, 1.25, 3.0], int(rng.integers(1, 4)))
    pos = spots[rng.integers(len(spots), size=B)] if seed % 3 else rng.random((B, 2))  # [B, 2] (distinct: 0, 3)
    free_at = times[rng.integers(len(times), size=B)]  # [B]
    fractions = [0.25, 0.75, 0.5] if exact else [0.1, 0.3, 0.5]
    cap = rng.choice([0.0, 0.0, *fractions, 1.0, 2.0], (B, K))  # [B, K]
    loc = np.vstack([rng.integers(0, 5, (N // 2, 2)) / 4, rng.random((N - N // 2, 2))])  # [N, 2]
    team = cap.sum(0)  # [K]
    rem = rng.choice([0.0, fractions[1], 1.0, 2.0, 5.0], (N, K)) * (rng.random((N, 1)) < 0.9)  # [N, K]
    rem[:, 0] = np.where((rem > 1e-9).any(1), rem[:, 0], 0.75)  # every task still needs someone
    rem[rng.random(N) < 0.1] = team * rng.choice([0.5, 1.0])  # most of the team, or all of it
    rem[0] = team + 0.5  # more than the team
    if exact:  # what MissionState._exact certifies
        assert all((np.ldexp(x, 24) % 1.0 == 0).all() for x in (cap, rem))
    got = CoalitionGreedy._completing_arrival(free_at, pos, loc, 0.2, cap, rem, exact=exact)
    assert np.array_equal(got, _completing_arrival_reference(free_at, pos, loc, 0.2, cap, rem))
    assert np.isinf(got[0])


@pytest.mark.parametrize("seed", range(8))
def test_coalition_completing_arrival_by_place_with_arrivals_ulps_apart(seed, monkeypatch):
    """Summed by place, the earliest sets are chosen by approximate arrivals (sqrt(dx^2 + dy^2))
    and summed by exact ones (np.hypot): places a few ulps apart and mirror images (equal
    distances), so that the two orders disagree, around the boundary of the sets looked at first
    (small PARTIAL: many boundaries), still give the full sort's answer bit for bit."""
    rng = np.random.default_rng(100 + seed)
    monkeypatch.setattr(CoalitionGreedy, "PARTIAL", int(rng.choice([1, 2, 16])))
    B, N, K = CoalitionGreedy.GROUPED + int(rng.integers(1, 120)), int(rng.integers(2, 40)), int(rng.integers(1, 4))
    loc = rng.random((N, 2))  # [N, 2]
    base = rng.random((int(rng.integers(2, 12)), 2))  # [P, 2]
    ulps = rng.integers(-4, 5, (len(base), 6, 2)) * np.finfo(float).eps  # [P, 6, 2] relative nudges
    spots = np.vstack([(base[:, None, :] * (1 + ulps)).reshape(-1, 2),  # places a few ulps apart
                       np.column_stack([1 - base[:, 0], base[:, 1]]),  # mirrored: equal distances to x = 1/2
                       loc[:3]])  # at a task
    pos = spots[rng.integers(len(spots), size=B)]  # [B, 2]
    free_at = rng.choice([0.0, 0.0, 0.25, 2.0], B) * (1 + rng.integers(-2, 3, B) * np.finfo(float).eps)  # [B]
    cap = rng.choice([0.0, 0.25, 0.5, 1.0], (B, K))  # [B, K]
    rem = rng.choice([0.25, 0.75, 1.5, 4.0], (N, K))  # [N, K]
    rem[0] = cap.sum(0) + 0.5  # more than the team
    got = CoalitionGreedy._completing_arrival(free_at, pos, loc, 0.2, cap, rem, exact=True)
    assert np.array_equal(got, _completing_arrival_reference(free_at, pos, loc, 0.2, cap, rem))
    assert np.isinf(got[0])


@pytest.mark.parametrize("kind", ["apart", "coalitions", "shared x"])
@pytest.mark.parametrize("seed", range(4))
def test_coalition_sets_of_robots_free_at_one_place_and_time(kind, seed):
    """Summed by place, the robots are split into sets of equal (free_at, x, y) by a sort on x
    alone where that suffices (every robot apart; coalitions that finished together, each at an
    x of its own) and by the full sort where it does not (robots at one x but another y or
    time): the same sets as the full sort either way, and the full sort's answer."""
    rng = np.random.default_rng(200 + seed)
    B, N, K = CoalitionGreedy.GROUPED + int(rng.integers(1, 150)), int(rng.integers(2, 30)), int(rng.integers(1, 4))
    if kind == "apart":
        pos, free_at = rng.random((B, 2)), rng.choice([0.0, 0.5, 2.0], B)  # [B, 2], [B]
    else:
        n_sets = int(rng.integers(2, B // 2))
        spots, times = rng.random((n_sets, 2)), rng.choice([0.0, 0.5, 2.0], n_sets)  # [S, 2], [S]
        if kind == "shared x":  # one place at two times (odd seeds), or two places at one x at one time
            spots[1, 0] = spots[0, 0]
            times[1] = times[0] + 1.0 if seed % 2 else times[0]
            spots[1, 1] = spots[0, 1] if seed % 2 else 1.0 - spots[0, 1]
        of = np.concatenate([np.arange(n_sets), rng.integers(n_sets, size=B - n_sets)])  # [B] every set used
        rng.shuffle(of)
        pos, free_at = spots[of], times[of]
    order, first = CoalitionGreedy._sets(free_at, pos)
    full, _, full_first, _ = CoalitionGreedy._places(free_at, pos)

    def sets(o, f):
        return sorted(sorted(o[a:b].tolist()) for a, b in zip(f, np.append(f[1:], len(o))))

    assert sorted(order.tolist()) == list(range(B))
    assert sets(order, first) == sets(full, full_first)
    cap = rng.choice([0.0, 0.25, 0.5, 1.0], (B, K))  # [B, K]
    loc = rng.random((N, 2))  # [N, 2]
    rem = rng.choice([0.25, 0.75, 1.5, 4.0], (N, K))  # [N, K]
    got = CoalitionGreedy._completing_arrival(free_at, pos, loc, 0.2, cap, rem, exact=True)
    assert np.array_equal(got, _completing_arrival_reference(free_at, pos, loc, 0.2, cap, rem))


def test_coalition_completing_arrival_by_place_when_approximate_and_exact_orders_disagree(monkeypatch):
    """Two places whose approximate arrivals (sqrt) and exact ones (np.hypot) are in opposite
    orders, either enough for the task: the one looked at first (approximately earlier) covers,
    but the answer is the other's exact arrival, earlier, which only looking further finds."""
    rng = np.random.default_rng(0)
    loc, v = np.array([[0.5, 0.5]]), 0.2
    p = rng.random((200_000, 2))  # [n, 2]
    q = p * (1 + rng.integers(-3, 4, p.shape) * np.finfo(float).eps)  # [n, 2] a few ulps away
    approx = [np.sqrt(((x - loc) ** 2).sum(1)) / v for x in (p, q)]
    exact = [np.hypot(*(x - loc).T) / v for x in (p, q)]
    i = int(np.flatnonzero((approx[0] < approx[1]) & (exact[1] < exact[0]))[0])
    monkeypatch.setattr(CoalitionGreedy, "PARTIAL", 1)  # one place looked at first
    B = CoalitionGreedy.GROUPED + 8  # summed by place
    pos = np.vstack([p[i], q[i], np.ones((B - 2, 2))])  # [B, 2] the pair, then robots without the skill
    cap = np.zeros((B, 1))
    cap[:2] = 1.0
    got = CoalitionGreedy._completing_arrival(np.zeros(B), pos, loc, v, cap, np.ones((1, 1)), exact=True)
    assert got[0] == exact[1][i] < exact[0][i]


@pytest.mark.parametrize("chunk", [1, 3, CoalitionGreedy.CHUNK])
def test_coalition_choice_is_the_best_of_all_estimates(chunk, monkeypatch):
    """greedy-coalition estimates many admissible tasks nearest first, in chunks, and stops when
    no task left can start earlier: the choice is the earliest start of all (then nearest, then
    lowest id), whatever the chunk size."""
    monkeypatch.setattr(CoalitionGreedy, "CHUNK", chunk)
    gc = CoalitionGreedy()

    def same(s):
        cand, start, mine = gc.estimates(s)
        assert gc(s) == (1 + int(cand[np.lexsort((mine, start))[0]]) if len(cand) else 0), (s.decisions, s.agent)

    for s, rng in missions(8, 30):
        drive(s, rng, same, policy=gc if rng.random() < 0.5 else None)
    s = MissionState(ScenarioGenerator("MA-AT", 60, 6, 120, 4).instance(3, 0), seed=0, rules=COALITION_RULES)
    while not s.done:
        same(s)
        s.step(gc(s))


# ---- the rl observation -------------------------------------------------------------------------
def _observe_reference(state, a, max_tasks, max_agents, scale):
    """Features of every task and agent, then the window (admissible tasks first, then nearest;
    nearest agents, the decider always), by stable sorts."""
    from hmrta.rl.features import _observe_full

    a = state.agent if a is None else a
    pos = state.positions()  # [A, 2]
    tf, af, mask = _observe_full(state, a, pos, scale)
    nodes = np.arange(state.M + 1)
    if state.n_hidden:
        nodes = np.concatenate([[0], np.flatnonzero(state.status != UNRELEASED) + 1])
        tf, mask = tf[nodes], mask[nodes]
    here = pos[a]
    if len(nodes) - 1 > max_tasks:
        d = np.hypot(*(state.inst.task_locations[nodes[1:] - 1] - here).T)
        key = np.where(mask[1:], d, d + 1e6)
        rows = np.concatenate([[0], np.sort(np.argsort(key, kind="stable")[:max_tasks]) + 1])
        tf, mask, nodes = tf[rows], mask[rows], nodes[rows]
    if state.A > max_agents:
        d = np.hypot(*(pos - here).T)
        d[a] = -1.0
        keep = np.sort(np.argsort(d, kind="stable")[:max_agents])
        af, a = af[keep], int(np.flatnonzero(keep == a)[0])
    return tf, af, mask, nodes, a


def test_observation_equals_features_of_everything_windowed():
    pytest.importorskip("torch")
    from hmrta.rl.features import observe

    checked = 0

    def same(s):
        nonlocal checked
        if s.K > 5:
            return
        for max_tasks, max_agents in ((50, 25), (3, 2)):
            for scale in ("fixed", "mission"):
                for a in {s.agent, s.A - 1}:  # the decider, and a robot in any mode
                    got, want = observe(s, a, max_tasks, max_agents, scale), _observe_reference(
                        s, a, max_tasks, max_agents, scale)
                    for x, y in zip(got[:4], want[:4]):
                        assert x.dtype == y.dtype and np.array_equal(x, y)
                    assert got[4] == want[4]
                    checked += 1

    for s, rng in missions(5, 20):
        drive(s, rng, same)
    assert checked > 1000
    inst = ScenarioGenerator("MA-AT", 150, 10, 500, 5).instance(1, 0)  # the real window (50 / 25)
    s = MissionState(inst, seed=0, rules=Rules(max_open="team"))
    rng = np.random.default_rng(0)
    for _ in range(40):
        same(s)
        cand = np.flatnonzero(s.mask())
        s.step(int(cand[int(rng.integers(len(cand)))]))


def test_smallest_is_the_stable_sort_prefix():
    from hmrta.rl.features import _smallest

    rng = np.random.default_rng(0)
    for n in (0, 1, 5, 60, 400):
        for k in (1, 3, 25, 50):
            key = rng.integers(0, 7, n).astype(float) if n % 2 else rng.random(n)
            key[rng.random(n) < 0.2] = -1.0
            assert np.array_equal(_smallest(key, k), np.sort(np.argsort(key, kind="stable")[:k]))
