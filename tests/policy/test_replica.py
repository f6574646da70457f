"""hmrta.replica without ROS: an agent's replica of the board's state machine, kept by applying the
events the board publishes (hmrta-board/2 headers, through their JSON), equals the board after
every version of random seeded missions with dynamic events (tasks added and cancelled, robots
joining and lost, scheduled scenario events, arrival confirmations); a lost message is a gap
recovered from a keyframe; a diverged replica resynchronises; a keyframe that may be old is not
acted on until the board confirms it."""
from __future__ import annotations

import dataclasses
import json
import math
import random

import numpy as np
import pytest

from hmrta.board import KEYFRAME_REPEAT, LOST, BoardState, MissionBoard, board_header, state_digest
from hmrta.core import MissionState
from hmrta.generators import ScenarioGenerator
from hmrta.instance import instance_from_dict
from hmrta.methods import decider, rules, solve
from hmrta.replica import Frame, Replica
from test_board import position  # sim_robot kinematics, shared with the board tests

RULES = rules("greedy")


@pytest.fixture(autouse=True)
def check_gate(monkeypatch):
    """Every incremental arrival gate of these tests is compared with the full scan."""
    monkeypatch.setattr("hmrta.board.CHECK_GATE", True)


class FakeTime:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Choice:  # what hmrta_msgs_py.codec.choice_from_msg gives the board
    def __init__(self, robot, session, version, node):
        self.robot, self.session, self.version, self.node, self.compute_ms, self.payload = \
            robot, session, version, node, 0.0, None


def mission_instance(b: MissionBoard):
    """The instance the node (re)publishes, through its wire round trip (the robots added)."""
    grown = dataclasses.replace(b.state.inst, tasks=b.inst.tasks, _cache={})
    return instance_from_dict(json.loads(json.dumps(grown.to_dict())))


def wire(v):
    """What a subscriber decodes from a published View: the header (through JSON) and, for a
    keyframe, a function giving its legs and state."""
    f = Frame.from_header(json.loads(json.dumps(board_header(v))))
    kf = (lambda: (json.loads(json.dumps(v.legs)), json.loads(v.state_json))) if v.keyframe else None
    return f, kf


def same_state(rep: Replica, b: MissionBoard) -> None:
    """The replica equals the board: the full snapshot, the revision, the lost robots and every
    live robot's legs."""
    assert json.dumps(rep.state.snapshot()) == json.dumps(b.state.snapshot())
    assert rep.rev == b.rev and set(rep.lost) == set(b.lost) and rep.digest == state_digest(b.state)
    for a in range(b.state.A):
        assert rep.legs(a) == b.state.legs(a), a
    for st in (rep.state, b.state):  # the leg counter the digest reads follows the logs
        assert st.leg_seqs.tolist() == [n + len(log) for n, log in zip(st.leg_base, st.leg_log)]


class Mission:
    """A board driven offline, robots that arrive at once, agents deciding greedily on a replica.
    ``drop``: versions whose messages the replica never gets; ``rng``: random operator events,
    joins and losses."""

    def __init__(self, inst, seed: int, rng: random.Random | None = None, drop=(), check=True):
        self.now = FakeTime()
        self.b = MissionBoard(inst, seed=seed, rules=RULES, wait_for_robots=False, now=self.now,
                              heartbeat_timeout=0.0, decision_timeout=0.0, leg_timeout_factor=0.0,
                              leg_timeout_floor=0.0)
        self.rep = Replica(now=self.now)
        self.decide = decider("greedy", seed)[0]
        self.rng, self.drop, self.check = rng, set(drop), check
        self.checked = self.dropped = 0
        self.ops: list[str] = []
        self.refused = 0  # refused requests (an add, a join) sent
        self.kinds: set[str] = set()  # the kinds of event the board published
        self.last_keyframe = None  # what a latched keyframe topic holds

    def pump(self) -> None:
        b, rep = self.b, self.rep
        v = b.poll()
        if v is not None:
            self.kinds |= {ev["type"] for ev in v.events}
            self.last_keyframe = v if v.keyframe else self.last_keyframe
        if v is not None and v.version in self.drop:  # lost once (a repeat of it gets through)
            self.drop.discard(v.version)
            self.dropped += 1
        elif v is not None:
            f, kf = wire(v)
            rep.receive(f, kf, mission_instance(b) if kf else None)
        if self.check and rep.current and rep.version == b.version:
            same_state(rep, b)
            self.checked += 1
        ask = rep.request()
        if ask is not None:
            b.request(*ask)

    def events(self) -> None:
        b, rng = self.b, self.rng
        if rng is None or not b.started or b.state.done:
            return
        r = rng.random()
        K = b.state.K
        if r < 0.06:
            req = [0.0] * K
            req[rng.randrange(K)] = 1.0
            task = {"location": [rng.random(), rng.random()], "requirements": req, "duration": rng.uniform(0.5, 3)}
            rid = f"op-{len(self.ops)}"
            if b.task_request("add", rid, task)["event"] == "accepted":
                self.ops.append(rid)
        elif r < 0.08 and self.ops:
            b.task_request("cancel", self.ops.pop(rng.randrange(len(self.ops))))
        elif r < 0.085:  # a task of the mission, by its index (refused when it is done or cancelled)
            b.task_request("cancel", str(rng.randrange(b.inst.n_tasks)))
        elif r < 0.10:
            b.join(f"new_{b.state.A}", rng.randrange(b.state.inst.n_species),
                   position=(rng.random(), rng.random()) if rng.random() < 0.5 else None)
        elif r < 0.105:  # requests the board refuses: nothing changes, so the replica stays equal
            bad = rng.choice(({"location": [0.5, 0.5], "requirements": [99.0] * K, "duration": 1.0},
                              {"location": [0.5, 0.5], "requirements": [1.0] * K, "duration": math.nan}))
            before = (state_digest(b.state), b.rev, b.state.clock)
            assert b.task_request("add", "bad", bad)["event"] == "rejected"
            assert (state_digest(b.state), b.rev, b.state.clock) == before
            self.refused += 1
            assert "cannot join" in b.join(f"odd_{self.refused}", b.state.inst.n_species + 2)
        elif r < 0.12:
            alive = [a for a in range(b.state.A) if a not in b.lost]
            if len(alive) > b.inst.n_agents // 2:
                b.lose(rng.choice(alive), "test: lost")

    def run(self, until: int | None = None, max_iter: int = 50000) -> MissionBoard:
        """Until the mission is over (or the board reached version ``until``)."""
        b, rep = self.b, self.rep
        for _ in range(max_iter):
            self.pump()
            if b.finished or (until is not None and b.version >= until):
                return b
            self.events()
            if b.phase == "decide":
                for _ in range(20):  # an agent that missed a version asks for a keyframe and waits for it
                    if rep.current and rep.version == b.version:
                        break
                    self.now.t += KEYFRAME_REPEAT
                    self.pump()
                if b.phase != "decide":
                    continue
                assert rep.current and rep.version == b.version, rep.why
                assert b.choice(Choice(b.names[b.state.agent], b.session, b.version,
                                       int(self.decide(rep.state)))) is None
                continue
            b.set_clock(b._key[3])
            st = b.state
            added = {r["id"]: r["position"] for r in st.log if r["type"] == "add_agent" and "position" in r}
            for a in range(st.A):
                if a not in b.lost:
                    x, y = added.get(a, st.inst.depots[a])
                    b.pose(a, *_position(st, a, (float(x), float(y)), b.clock))
        raise AssertionError(f"stuck: {b.waiting_for()}")


def _position(st: BoardState, a: int, home, t: float):
    """Where robot a, driving its legs from ``home`` (sim_robot's kinematics), is at time t."""
    return position(st.inst, [(0, home[0], home[1], 0.0), *st.leg_log[a]], t)


def scenario(inst, rng: random.Random, at_start: bool = False):
    """``inst`` with scheduled events: a task released late, tasks added and cancelled, a robot
    added and one lost, at random times (``at_start``: a robot added and one lost at time 0 too,
    applied as the state is built)."""
    K = inst.skills
    req = [0.0] * K
    req[rng.randrange(K)] = 1.0
    tasks = list(inst.tasks)
    tasks[-1] = dataclasses.replace(tasks[-1], release=rng.uniform(1, 6))
    events = ({"type": "add_task", "t": rng.uniform(0.5, 5), "name": "sc-add",
               "task": {"location": [rng.random(), rng.random()], "requirements": req, "duration": 1.5}},
              {"type": "cancel_task", "t": rng.uniform(0.5, 5), "task": rng.randrange(len(tasks) - 1)},
              {"type": "add_agent", "t": rng.uniform(0.5, 5), "species": rng.randrange(inst.n_species)},
              {"type": "drop_agent", "t": rng.uniform(2, 8), "agent": rng.randrange(inst.n_agents)})
    if at_start:
        events += ({"type": "add_agent", "t": 0.0, "species": 0}, {"type": "drop_agent", "t": 0.0, "agent": 0})
    return dataclasses.replace(inst, tasks=tuple(tasks), events=events, _cache={})


# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 5])
def test_the_replica_equals_the_board_after_every_version_of_random_dynamic_missions(seed):
    rng = random.Random(seed)
    inst = ScenarioGenerator("MA-AT", 9, 3, 16, 3).instance(seed, 0)
    if seed % 2:
        inst = scenario(inst, rng, at_start=seed == 5)  # (robots added at time 0: the board crashed)
    m = Mission(inst, seed, rng=rng)
    b = m.run()
    print(f"seed {seed}: {b.version} versions, {m.checked} checked, keyframes {dict(b.keyframes)}, "
          f"replica {m.rep.counts}, events {sorted(m.kinds)}, operator tasks {len(b.requests)}, lost {len(b.lost)}")
    assert m.checked >= b.version * 0.9  # nearly every version (the replica skips none: it is only behind
    assert m.rep.counts.get("diverged", 0) == 0 and m.rep.counts.get("ahead", 0) == 0  # ... while it waits)
    assert m.rep.counts["loaded"] == 1  # one keyframe at the start, then only events
    same_state(m.rep, b)
    assert b.finished


@pytest.mark.parametrize("seed", [0, 1, 5])
def test_a_replica_without_any_keyframe_starts_from_version_0_of_the_mission(seed):
    """A reader holding the stream from version 1 and the mission (instance, seed, rules) but no
    keyframe: from the board's version 0 it follows every version (scenario events included, at
    time 0 too); a version 0 built from another instance diverges at version 1."""
    rng = random.Random(seed)
    inst = ScenarioGenerator("MA-AT", 9, 3, 16, 3).instance(seed, 0)
    if seed % 2:
        inst = scenario(inst, rng, at_start=seed == 5)
    m = Mission(inst, seed, rng=None)
    heads = []
    poll = m.b.poll

    def recorded():
        v = poll()
        if v is not None and (not heads or v.version > heads[-1][0].version):
            heads.append((wire(v)[0], v))
        return v

    m.b.poll = recorded
    b = m.run()
    assert heads[0][0].version == 1 and [f.version for f, _ in heads] == list(range(1, b.version + 1))
    rep = Replica()
    rep.genesis(b.session, inst, seed, RULES)
    assert rep.version == 0 and not rep.current
    for f, v in heads:
        assert rep.receive(f) == "applied", rep.why
        assert rep.current and rep.version == f.version and rep.digest == v.digest
    same_state(rep, b)
    other = Replica()
    other.genesis(b.session, ScenarioGenerator("MA-AT", 9, 3, 16, 3).instance(seed + 10, 0), seed, RULES)
    assert other.receive(heads[0][0]) == "diverged" and "digest" in other.why and not other.synced


def test_dynamic_missions_exercise_every_kind_of_event():
    seen: set[str] = set()
    for seed in range(4):
        rng = random.Random(seed)
        inst = ScenarioGenerator("MA-AT", 9, 3, 16, 3).instance(seed, 0)
        m = Mission(scenario(inst, rng) if seed % 2 else inst, seed, rng=rng, check=False)
        m.run()
        seen |= m.kinds
    assert {"start", "choice", "arrival", "advance", "add_task", "cancel_task", "add_agent", "drop_agent"} <= seen


@pytest.mark.parametrize("which", ["early", "late", "many"])
def test_a_lost_message_is_a_gap_recovered_from_a_keyframe_and_the_mission_equals_offline(which):
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    drop = {"early": {3}, "late": {38}, "many": {8, 15, 22, 29}}[which]
    m = Mission(inst, 3, drop=drop)
    b = m.run()
    sol = b.result()
    ref = json.loads(json.dumps(solve(inst, "greedy", 3).to_dict()))
    got = json.loads(json.dumps(sol.to_dict()))
    for k in ("success", "routes", "tasks", "makespan"):
        assert got[k] == ref[k], k
    print(f"{which}: dropped {sorted(drop)}; replica {m.rep.counts}; keyframes {dict(b.keyframes)}")
    assert m.dropped == len(drop) and not m.drop
    # the versions after a lost one wait for a keyframe; a lost latest version is streamed again
    if which == "many":
        assert m.rep.counts["loaded"] >= 2 and b.keyframes.get("requested", 0) >= 1
    same_state(m.rep, b)


def test_a_gap_is_reported_with_its_reason_and_asked_for_again_until_a_keyframe_comes():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    now = FakeTime()
    b = MissionBoard(inst, seed=3, rules=RULES, wait_for_robots=False, now=now)
    rep = Replica(now=now, retry=1.0)
    views = []
    while len(views) < 4:
        v = b.poll()
        if v is not None:
            views.append(v)
        if len(views) < 4 and b.phase == "decide":
            b.choice(Choice(b.names[b.state.agent], b.session, b.version, int(decider("greedy", 3)[0](b.state))))
    assert views[0].keyframe and not any(v.keyframe for v in views[1:])
    assert rep.request() is None  # nothing heard yet: nobody to ask
    f, kf = wire(views[0])
    rep.receive(f, kf, mission_instance(b))
    assert rep.current and rep.request() is None
    assert rep.receive(wire(views[2])[0]) == "ahead" and not rep.current  # version 2 was lost
    assert rep.request() == (1, "missed version(s) 2..2 (got 3 after 1)")
    assert rep.request() is None  # not again at once ...
    now.t += 1.0
    assert rep.request() == (1, "missed version(s) 2..2 (got 3 after 1)")  # ... but every retry seconds
    assert rep.receive(wire(views[3])[0]) == "ahead"
    b.request(1, "missed")
    v = b.poll()  # no new version: a keyframe of the current one, not streamed again
    assert v.keyframe and not v.stream and v.version == views[3].version and v.reason == "requested"
    f, kf = wire(v)
    assert rep.receive(f, kf, mission_instance(b)) == "loaded"
    assert rep.current and rep.version == b.version and rep.request() is None
    same_state(rep, b)


def test_a_diverged_replica_drops_its_state_and_resynchronises():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    m = Mission(inst, 3)
    m.run(until=5)
    m.rep.state.arrive[0] += 0.5  # corrupt the replica (as a platform with other floats would)
    m.check = False
    m.run(until=6)
    assert m.rep.counts.get("diverged", 0) == 1 and m.rep.state is None and "state digest" in m.rep.why
    assert not m.rep.current and m.rep.asking_since is not None and m.b._asked  # it asked
    m.check = True
    b = m.run()
    same_state(m.rep, b)
    assert b.keyframes.get("requested", 0) >= 1 and m.rep.counts["loaded"] >= 2


def test_a_keyframe_that_may_be_old_is_confirmed_by_the_board_before_the_replica_acts():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    for until in (1, 12):  # the latest keyframe is the current version, or an old one
        m = Mission(inst, 3, check=False)
        b = m.run(until=until)
        kf = m.last_keyframe
        late = Replica(now=m.now)
        f, load = wire(kf)
        assert late.receive(f, load, mission_instance(b), latched=True) == "loaded"
        assert late.synced and not late.current
        version, why = late.request()
        assert version == kf.version and why.startswith("confirming version")
        b.request(version, why)
        m.now.t += KEYFRAME_REPEAT
        v = b.poll()
        if kf.version == b.version:  # it was the latest: the board repeats the header
            assert not v.keyframe and v.stream and v.version == kf.version
            assert late.receive(*wire(v)) == "confirmed"
        else:  # it was old: a keyframe of the current version
            assert v.keyframe and not v.stream and v.version == b.version > kf.version
            f, load = wire(v)
            assert late.receive(f, load, mission_instance(b)) == "loaded"
        assert late.current and late.version == b.version
        same_state(late, b)


def test_a_confirmation_with_the_current_version_repeats_the_header_only():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    now = FakeTime()
    b = MissionBoard(inst, seed=3, rules=RULES, wait_for_robots=False, now=now)
    v1 = b.poll()
    assert v1.keyframe and v1.reason == "first" and b.poll() is None
    b.request(v1.version)
    v = b.poll()
    assert v is not None and not v.keyframe and v.stream and v.version == v1.version == b.version
    assert b.poll() is None


def test_another_session_resets_the_replica():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    rep = Replica()
    for session in ("run-1", "run-2"):
        b = MissionBoard(inst, seed=3, rules=RULES, wait_for_robots=False, session=session)
        f, kf = wire(b.poll())
        assert rep.receive(f, kf, inst) == "loaded" and rep.session == session and rep.version == 1


def test_periodic_keyframes_every_n_versions_or_by_size():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    for period in (0, 5):
        m = Mission(inst, 3, check=False)
        m.b.keyframe_period = period
        b = m.run()
        kfs = b.keyframes
        print(f"period {period}: {b.version} versions, keyframes {dict(kfs)}, stream {b.stream_bytes} B")
        if period:
            assert kfs["period"] == pytest.approx(b.version / period, abs=2)
        else:  # keyframes cost at most about as much as the stream
            assert 1 <= kfs["period"] and kfs["period"] * len(b._state_json) <= 1.5 * b.stream_bytes
        assert kfs["first"] == 1 and kfs["done"] == 1


def test_a_board_state_clone_branches_like_an_offline_state():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    st = BoardState(inst, seed=3, rules=RULES)
    st.advance_to(0.0)
    twin = st.clone()
    assert type(twin) is MissionState and twin.until == math.inf and not hasattr(twin, "leg_log")
    ref = MissionState(inst, seed=3, rules=RULES)
    assert json.dumps(twin.snapshot()) == json.dumps(ref.snapshot())
    decide = decider("greedy", 3)[0]
    while not twin.done:  # a lookahead branch runs to the end, never held at the board's clock
        twin.step(int(decide(twin)))
        ref.step(int(decide(ref)))
    assert twin.done and json.dumps(twin.snapshot()) == json.dumps(ref.snapshot())
    assert not st.done and st.leg_log is not None


DIGEST_OF_THE_TEST_STATE = "cd28c4cba08b1473"


def test_the_digest_sees_a_change_of_any_robot_or_task():
    inst = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
    st = BoardState(inst, seed=3, rules=RULES)
    d = state_digest(st)
    assert len(d) == 16 and d == state_digest(st)
    for change in (lambda s: s.status.__setitem__(3, 4), lambda s: s.arrive.__setitem__(2, 1.0),
                   lambda s: s.rem.__setitem__((1, 0), 0.5), lambda s: s.log_leg(1, 1),
                   lambda s: s.mode.__setitem__(0, LOST), lambda s: setattr(s, "clock", 1e-9),
                   lambda s: s.queue.reverse(), lambda s: s.depart.__setitem__(5, -0.0),
                   lambda s: s.log_leg(5, 1) or s.log_leg(4, 1)):
        other = BoardState(inst, seed=3, rules=RULES)
        change(other)
        assert state_digest(other) != d
    assert np.array_equal(st.status, BoardState(inst, seed=3, rules=RULES).status)
    # integer arithmetic on a fixed weight stream: the same digest on every machine and in every
    # process, however long the weights have grown (the value below was computed once and kept)
    big = ScenarioGenerator("MA-AT", 60, 10, 300, 5).instance(1, 0)  # arrays longer than any before
    assert state_digest(BoardState(big, seed=0, rules=RULES)) == state_digest(BoardState(big, seed=0, rules=RULES))
    assert state_digest(BoardState(inst, seed=3, rules=RULES)) == d == DIGEST_OF_THE_TEST_STATE
