"""hmrta.board without ROS: the board's protocol driven by plain values (decoded choices, poses,
clock values, a fake wall clock). A whole mission run through it equals the offline rollout;
every rejection reason; the arrival gate; robot loss by timeout; the journal (replay after a crash
equals the uninterrupted mission, a torn last line is dropped, a foreign journal is refused)."""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

import pytest

from hmrta import keys as K
from hmrta.baselines import Greedy
from hmrta.board import (JOURNAL_FORMAT, KEYFRAME_REPEAT, RESEND, JournalError, MissionBoard, board_header,
                         read_journal, state_digest)
from hmrta.core import DONE, EMPTY, OPEN, MissionState
from hmrta.generators import ScenarioGenerator
from hmrta.instance import instance_from_dict
from hmrta.methods import decider, rules, solve
from hmrta.replica import Frame, Replica

INST = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(4, 0)
SEED = 3
RULES = rules("greedy")


@pytest.fixture(autouse=True)
def check_gate(monkeypatch):
    """Every incremental arrival gate of these tests is compared with the full scan."""
    monkeypatch.setattr("hmrta.board.CHECK_GATE", True)


@dataclass
class Choice:  # what hmrta_msgs_py.codec.choice_from_msg gives the board
    robot: str
    session: str
    version: int
    node: int
    compute_ms: float = 0.0
    payload: Any = field(default=None, compare=False)


class FakeTime:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def position(inst, legs, t: float) -> tuple[float, float]:
    """Where a robot driving ``legs`` (node, x, y, depart) from its depot is at time t (sim_robot's
    kinematics)."""
    pos = (float(legs[0][1]), float(legs[0][2]))
    for node, x, y, dep in legs[1:]:
        if node == RESEND:
            continue  # a goal re-sent: the leg it repeats is listed already
        if dep > t:
            break
        start = pos
        arrive = dep + math.hypot(x - start[0], y - start[1]) / inst.velocity
        if t >= arrive or arrive <= dep:
            pos = (x, y)
        else:
            f = (t - dep) / (arrive - dep)
            pos = (start[0] + (x - start[0]) * f, start[1] + (y - start[1]) * f)
    return pos


def greedy_turn(b: MissionBoard) -> None:
    """One turn of a mission on board ``b`` with robots that arrive at once: the decider's greedy
    choice, or else the clock to the board's horizon."""
    if b.phase == "decide":
        assert b.choice(Choice(b.names[b.state.agent], b.session, b.version, Greedy()(b.state))) is None
    else:
        b.set_clock(b._key[3])


def replica_of(b: MissionBoard) -> Replica:
    """The agents' replica of board ``b`` (one per board, fed by :func:`pump`)."""
    if not hasattr(b, "test_replica"):
        b.test_replica = Replica(now=b.now)
    return b.test_replica


def pump(b: MissionBoard):
    """Poll the board and hand what it publishes to the agents' replica, through the wire's JSON;
    the replica's keyframe requests go back to the board."""
    v = b.poll()
    rep = replica_of(b)
    if v is not None:
        f = Frame.from_header(json.loads(json.dumps(board_header(v))))
        rep.receive(f, (lambda: (json.loads(json.dumps(v.legs)), json.loads(v.state_json))) if v.keyframe else None,
                    mission_instance(b) if v.keyframe else None)
    ask = rep.request()
    if ask is not None:
        b.request(*ask)
    return v


def drive(b: MissionBoard, steps: int | None = None, report: bool = True, max_iter: int = 20000,
          clock: float = math.inf, where=None, tick: float = 0.0, changes_only: bool = False) -> int:
    """Play agents (greedy on their replica of the board's state) and robots that arrive at once,
    until the mission is over, ``steps`` choices were applied or the clock reached ``clock``;
    returns the choices applied. ``where(a, xy)``: where robot a reports itself when the sim puts
    it at xy; ``tick``: wall seconds of the fake clock (``b.now``) per round, with the watchdog
    run; ``changes_only``: a robot reports its pose only when it moved (a driver that publishes on
    updates)."""
    decide = decider("greedy", SEED)[0]
    reported: dict[int, tuple[float, float]] = {}
    inst, names = b.inst, b.names
    rep = replica_of(b)
    n = 0
    for _ in range(max_iter):
        pump(b)
        if b.finished or (steps is not None and n >= steps) or b.clock >= clock:
            return n
        st = b.state
        if b.phase == "decide":
            for _ in range(10):  # an agent that missed versions asks for a keyframe and waits for it
                if rep.current and rep.version == b.version:
                    break
                b.now.t += KEYFRAME_REPEAT
                pump(b)
            assert rep.current and rep.version == b.version and rep.digest == state_digest(st)
            c = Choice(names[st.agent], b.session, b.version, int(decide(rep.state)))
            assert b.choice(c) is None
            n += 1
            continue
        if tick:
            b.now.t += tick
            b.tick()
            pump(b)
            if b.finished:
                return n
            st = b.state
        horizon = b._key[3]
        b.set_clock(min(horizon, clock))
        added = {r["id"]: r["position"] for r in st.log if r["type"] == "add_agent" and "position" in r}
        if report:
            for a in range(st.A):
                if a not in b.lost:
                    # robots added during the mission start where they were added (default: depot)
                    x, y = added.get(a, st.inst.depots[a])
                    base = [(0, float(x), float(y), 0.0)]
                    xy = position(inst, base + st.leg_log[a], b.clock)
                    xy = where(a, xy) if where else xy
                    if not changes_only or reported.get(a) != xy:
                        b.pose(a, *xy)
                        reported[a] = xy
    raise AssertionError(f"stuck: {b.waiting_for()}")


def mission_instance(b: MissionBoard):
    """The instance of the mission the node (re)publishes, through its wire round trip: the
    robots added, not the tasks."""
    grown = dataclasses.replace(b.state.inst, tasks=b.inst.tasks, _cache={})
    return instance_from_dict(json.loads(json.dumps(grown.to_dict())))


def started_board(**kw) -> MissionBoard:
    return MissionBoard(INST, seed=SEED, rules=RULES, wait_for_robots=False, now=kw.pop("now", FakeTime()), **kw)


def same(sol, ref) -> None:
    a, r = json.loads(json.dumps(sol.to_dict())), json.loads(json.dumps(ref.to_dict()))
    for k in ("success", "routes", "tasks", "agents", "makespan", "awt", "redundancy"):
        assert a[k] == r[k], k


# ---------------------------------------------------------------------------------------------
def test_a_mission_through_the_board_equals_the_offline_rollout():
    b = started_board()
    n = drive(b)
    sol = b.result()
    same(sol, solve(INST, "greedy", SEED))
    assert n == sol.extra["decision_latency_ms"]["n"] > 0
    assert b.phase == "done" and sol.extra["lost_robots"] == [] and sol.extra["undone_tasks"] == []
    assert sol.extra["board_versions"] == b.version > n and sol.extra["live_events"] == {}
    assert "final_instance" not in sol.extra


def test_board_waits_for_every_robot_then_starts():
    now = FakeTime()
    b = MissionBoard(INST, seed=SEED, rules=RULES, now=now)
    v = b.poll()
    assert v.phase == "starting" and v.version == 1 and b.poll() is None
    names = b.names
    assert b.heartbeat("another-run", names) is None and not b.started  # another mission run: ignored
    b.heartbeat(b.session, names)
    for a in range(INST.n_agents - 1):
        b.pose(a, *INST.depots[a])
    assert not b.started and b.waiting() == [names[-1]]
    b.pose(INST.n_agents - 1, *INST.depots[-1])
    assert b.started and b.poll().phase == "decide"


def test_every_rejection_reason_and_nothing_changes():
    keys = {n: bytes([i]) * 32 for i, n in enumerate(f"robot_{a}" for a in range(INST.n_agents))}
    b = started_board(verifier=K.Verifier(keys))
    v = b.poll()
    assert v.phase == "decide"
    d, names = v.decider, b.names
    me, other = names[d], names[(d + 1) % len(names)]
    mask = b.state.mask()
    good = int(next(n for n in range(1, len(mask)) if mask[n]))
    bad = [n for n in range(len(mask)) if not mask[n]]
    sign = lambda robot, **kw: K.Signer({robot: keys[robot]}).sign(  # noqa: E731
        {"format": "hmrta-choice/1", "robot": robot, "session": b.session, "version": kw.get("version", v.version),
         "node": kw.get("node", good)})

    def send(robot, version=v.version, node=good, session=None, payload="sign"):
        p = sign(robot, version=version, node=node) if payload == "sign" else payload
        return b.choice(Choice(robot, session or b.session, version, node, payload=p))

    cases = [(send(me, session="x"), "foreign_session"), (send(me, payload=None), "unsigned"),
             (send(me, payload={**sign(me), "node": good + 1}), "forged"),
             (send("intruder", payload=sign(me) | {"robot": "intruder"}), "unknown_robot"),
             (send(other), "not_your_turn"), (send(me, version=v.version - 1), "stale"),
             (send(me, version=v.version + 2), "stale"), (send(me, node=len(mask) + 3), "masked"),
             (send(me, node=-1), "masked")]
    if bad:
        cases.append((send(me, node=bad[0]), "masked"))
    for r, reason in cases:
        assert r is not None and r.reason == reason, (r, reason)
    assert b.poll() is None and b.version == v.version and b.rev == 0  # nothing changed
    assert send(me) is None
    assert send(me).reason == "duplicate"
    assert b.poll().version == v.version + 1
    b.lose((d + 2) % len(names), "test")
    assert send(names[(d + 2) % len(names)], version=b.version).reason == "lost"
    assert sum(b.rejected.values()) == len(cases) + 2
    assert b.auth_rejected["choice"] == {"unsigned": 1, "forged": 1, "unknown_robot": 1}


def test_the_clock_is_held_until_members_report_at_their_task():
    b = started_board()
    drive(b, steps=3, report=False)  # nobody reports: the clock may reach the first start, not more
    b.poll()
    st = b.state
    starts = [float(st.start[m]) for a in range(st.A) for m in st.routes[a][:1] if st.start[m] == st.start[m]]
    if starts:
        assert b._key[3] <= min(starts) + 1e-9 and "arrivals not confirmed" in b.waiting_for()


def test_a_repeated_pose_keeps_the_robot_alive_and_changes_nothing_to_publish():
    """A driver's periodic pose from where the robot already was: the board notes that the robot
    is alive, and has nothing to recompute (the node then skips its publish step)."""
    now = FakeTime()
    b = started_board(now=now)
    for a in range(INST.n_agents):
        assert b.pose(a, *INST.depots[a]) is True  # the first report of each
    drive(b, steps=3)
    while b.poll() is not None:  # what the drive left to publish
        pass
    v = b.version
    now.t += 0.1  # (within HEADER_REPEAT: an idle board would repeat its latest header after it)
    for a in range(INST.n_agents):
        assert b.pose(a, *b.last_pose[a]) is False and b.seen_pose[a] == now.t
    assert not b._gate_dirty and b.poll() is None and b.version == v
    x, y = b.last_pose[2]
    assert b.pose(2, x + 0.01, y) is True and b._gate_dirty == {2}


def test_robots_that_never_report_fail_the_mission_naming_the_start_up_timeout():
    """No process of the mission's robots came up: at the start-up timeout every robot is dropped
    as never reported, and the failure says so (not only that the tasks became unsatisfiable)."""
    now = FakeTime()
    b = MissionBoard(INST, seed=SEED, rules=RULES, now=now, startup_timeout=3.0)
    b.poll()
    for _ in range(40):  # 4 s of ticks every 0.1 s
        now.t += 0.1
        b.tick()
        b.poll()
    assert b.started and set(b.lost.values()) == {"never reported"} and len(b.lost) == INST.n_agents
    sol = b.result()
    assert not sol.success
    assert f"{INST.n_agents} of {INST.n_agents} robot(s) never reported within the start-up timeout (3 s)" \
        in sol.extra["failure"], sol.extra["failure"]
    assert "on this ROS domain?" in sol.extra["failure"]


@dataclass
class Refusal:  # what hmrta_msgs_py.codec.status_from_msg gives the board in a status's refused
    robot: str
    why: str


def test_agents_that_refuse_are_said_at_once_and_the_board_stops_waiting_when_all_have():
    """An agent that refuses the mission says so in a last heartbeat: the board logs the reason
    once, keeps waiting while some robot may still take part, and starts without them (the
    mission failing, with their reasons) once every robot's agent has refused, long before the
    start-up timeout."""
    now, said = FakeTime(), []
    b = MissionBoard(INST, seed=SEED, rules=RULES, now=now, startup_timeout=120.0,
                     log=lambda level, text: said.append((level, text)))
    b.poll()
    why = "robot_0: method random but mission x runs greedy: not taking part"
    b.heartbeat(b.session, [], refused=[Refusal("robot_0", why)])
    b.heartbeat(b.session, [], refused=[Refusal("robot_0", why + " again"), Refusal("nobody", "spoofed")])
    warned = [t for level, t in said if level == "warning" and "refuses the mission" in t]
    assert warned == [f"robot 'robot_0': its agent refuses the mission: {why} (waiting for an agent of it that "
                      f"takes part until the start-up timeout, 120 s)"], said  # once per robot; a stranger: nothing
    assert not b.started
    b.heartbeat("another-run", [], refused=[Refusal(n, "x") for n in b.names])  # another mission run: ignored
    assert not b.started
    for n in b.names[1:-1]:
        b.heartbeat(b.session, [], refused=[Refusal(n, "multi-line\nreason " + "z" * 1000)])
    assert not b.started and len(b.refusals) == INST.n_agents - 1
    assert all(len(w) <= 300 and "\n" not in w for w in b.refusals.values())  # one line, bounded
    b.heartbeat(b.session, [], refused=[Refusal(b.names[0], why), Refusal(b.names[-1], "last")])
    assert b.started and now.t == 100.0  # every robot refused: no start-up timeout waited out
    assert len(b.lost) == INST.n_agents and b.lost[0] == f"its agent refused the mission: {why}"
    drive(b, steps=2)
    sol = b.result()
    assert not sol.success
    assert (f"{INST.n_agents} of {INST.n_agents} robot(s) refused by their agents (robot_0, robot_1, robot_2, "
            f"robot_3, robot_4, ...), robot_0's saying: {why}") in sol.extra["failure"], sol.extra["failure"]


def test_a_refusal_never_drops_a_robot_whose_agent_is_heard():
    """Whoever sends it, a refusal counts only for a robot that no agent reported: a message that
    names every robot as refused (also alongside their heartbeats) neither drops robots that are
    heard nor starts the mission; it is logged once per robot, however often it comes."""
    now, said = FakeTime(), []
    b = MissionBoard(INST, seed=SEED, rules=RULES, now=now, startup_timeout=0.0,
                     log=lambda level, text: said.append((level, text)))
    b.poll()
    b.heartbeat(b.session, b.names[:-1])  # every robot but the last is heard
    for _ in range(50):
        b.heartbeat(b.session, b.names[:-1], refused=[Refusal(n, "spoofed") for n in b.names])
    assert not b.started and b.lost == {} and b.refusals == {INST.n_agents - 1: "spoofed"}
    warned = [t for _, t in said if "refuses the mission" in t]
    assert warned == [f"robot '{b.names[-1]}': its agent refuses the mission: spoofed (waiting for an agent of "
                      f"it that takes part (no start-up timeout))"]
    b.heartbeat(b.session, [b.names[-1]])  # an agent that takes part after all
    assert b.refusals == {}
    for a in range(INST.n_agents):
        b.pose(a, *INST.depots[a])
    assert b.started and b.lost == {}
    b.heartbeat(b.session, [], refused=[Refusal(n, "spoofed") for n in b.names])  # running: all heard
    assert b.lost == {} and len([t for _, t in said if "refuses the mission" in t]) == 1


def test_a_robot_whose_agent_refused_is_dropped_with_its_reason_at_the_start_up_timeout_or_at_once_when_running():
    now = FakeTime()
    b = MissionBoard(INST, seed=SEED, rules=RULES, now=now, startup_timeout=3.0)
    b.poll()
    for a in range(1, INST.n_agents):
        b.heartbeat(b.session, [b.names[a]])
        b.pose(a, *INST.depots[a])
    b.heartbeat(b.session, [], refused=[Refusal("robot_0", "robot_0: wrong species")])
    assert not b.started
    for _ in range(40):
        now.t += 0.1
        b.tick()
        b.poll()
    assert b.started and b.lost == {0: "its agent refused the mission: robot_0: wrong species"}
    running = started_board(now=FakeTime())  # wait_for_robots false: started before any agent is heard
    running.heartbeat(running.session, [running.names[1]])
    running.heartbeat(running.session, [], refused=[Refusal(n, "wrong method") for n in running.names[:2]])
    assert running.lost == {0: "its agent refused the mission: wrong method"}  # robot_1 is heard: kept


def test_a_robot_whose_every_pose_was_rejected_is_dropped_saying_why_not_as_never_reported():
    """Poses in another frame (Nav2's odom instead of map) are rejected: at the start-up timeout
    such a robot is dropped with the rejection's reason, and the failure says it, where it would
    otherwise read as a robot whose driver never came up."""
    now = FakeTime()
    b = MissionBoard(INST, seed=SEED, rules=RULES, now=now, startup_timeout=3.0)
    b.poll()
    b.heartbeat(b.session, b.names)
    why = "pose of robot_0 in frame 'odom', expected 'map' (frame_id)"
    b.pose_rejected(0, why)
    b.pose_rejected(99, "no such robot")  # (ignored)
    for a in range(1, INST.n_agents):
        b.pose(a, *INST.depots[a])
    for _ in range(40):
        now.t += 0.1
        b.tick()
        b.poll()
    assert b.started and b.lost == {0: f"no pose accepted: {why}"}
    for a in range(1, INST.n_agents):  # the others lost too: the mission fails
        b.lose(a, "x")
    drive(b)
    sol = b.result()
    assert not sol.success
    assert f"1 of {INST.n_agents} robot(s) had every pose rejected (robot_0), robot_0's: {why}" \
        in sol.extra["failure"], sol.extra["failure"]


def test_silent_robot_is_lost_and_the_others_finish():
    now = FakeTime()
    b = started_board(now=now, heartbeat_timeout=5.0)
    for a in range(INST.n_agents):
        b.heartbeat(b.session, [b.names[a]])
        b.pose(a, *INST.depots[a])
    drive(b, steps=4)
    for k in range(60):  # 6 s of a board ticking every 0.1 s, heartbeats every second
        now.t += 0.1
        if k % 10 == 9:
            b.heartbeat(b.session, b.names[1:])  # robot_0's agent fell silent
            for a in range(INST.n_agents):
                b.pose(a, *b.last_pose[a])
        b.tick()
    assert list(b.lost) == [0] and "agent heartbeat" in b.lost[0]
    b.heartbeat_timeout = 0.0  # the fake robots below do not beat any more
    drive(b)
    sol = b.result()
    assert sol.extra["lost_robots"] == ["robot_0"] and b.state.mode[0] == 4
    assert all(0 not in t["members"] for t in sol.tasks if t["start"] != t["start"] or t["start"] >= b.clock)


def test_a_board_that_did_not_run_reads_its_queues_before_it_drops_anyone():
    """A board process stopped (SIGSTOP) or starved for longer than every timeout: at its first
    tick the heartbeats, choices and poses sent meanwhile are still unread in its queues, so every
    timeout counts afresh from the resumption; silence after it still counts."""
    now, logs = FakeTime(), []
    b = started_board(now=now, heartbeat_timeout=5.0, decision_timeout=8.0,
                      log=lambda level, text: logs.append(text))
    for a in range(INST.n_agents):
        b.heartbeat(b.session, [b.names[a]])
    v = b.poll()
    assert v.phase == "decide"
    b.tick()
    now.t += 15.0  # stopped for 15 s
    b.tick()  # the watchdog runs before the queued messages are read
    assert b.lost == {} and any("did not run for 15.0 s" in t for t in logs)
    for k in range(52):
        if k % 10 == 0:
            b.heartbeat(b.session, b.names[1:])  # ... which come next: robot_0's agent is silent
        now.t += 0.1
        b.tick()
    assert list(b.lost) == [0] and "agent heartbeat" in b.lost[0]  # 5 s of silence after the resumption
    assert v.decider == 0 or v.decider not in b.lost  # the decider's 8 s count from the resumption too


def test_two_agent_processes_for_one_robot_are_warned_once_and_a_restart_is_not():
    now = FakeTime()
    b = started_board(now=now)
    r = b.names[1]
    assert b.heartbeat(b.session, [r], host="pc:100") is None
    now.t += 0.5
    assert b.heartbeat(b.session, [r], host="pc:200") is None  # a restarted agent: the old one is gone
    for _ in range(3):
        now.t += 0.5
        assert b.heartbeat(b.session, [r], host="pc:200") is None
    now.t += 0.5
    warn = b.heartbeat(b.session, [r], host="pc:100")  # ... and the first one is back: both run
    assert warn is not None and "two agent processes (pc:100 and pc:200)" in warn and repr(r) in warn
    now.t += 0.5
    assert b.heartbeat(b.session, [r], host="pc:200") is None  # warned once
    assert b.heartbeat(b.session, [b.names[2]], host="pc:100") is None  # other robots: their own


def test_decision_timeout_drops_the_decider():
    now = FakeTime()
    b = started_board(now=now, heartbeat_timeout=0.0, decision_timeout=2.0)
    v = b.poll()
    now.t += 2.5
    b.tick()
    assert list(b.lost) == [v.decider] and "no decision within" in b.lost[v.decider]


# ---------------------------------------------------------------------------------------------
# journal
# ---------------------------------------------------------------------------------------------
def test_a_board_replayed_from_its_journal_continues_like_the_uninterrupted_mission(tmp_path, monkeypatch):
    j = tmp_path / "journal.jsonl"
    epoch = [1.0e9]
    monkeypatch.setattr("hmrta.board.time.time", lambda: epoch[0])
    b = started_board(journal=j)
    drive(b, steps=7)
    b.poll()
    version, session, rev = b.version, b.session, b.rev
    legs, snap = b._legs_now(), b.state.snapshot()
    # crash: the object is dropped without closing; a new board on the same journal
    epoch[0] += 40.0  # ... 40 s of wall time after the mission started
    b2 = started_board(journal=j)
    assert (b2.session, b2.version, b2.rev) == (session, version, rev)
    assert b2._legs_now() == legs and b2.state.snapshot() == snap and b2.ptr == b.ptr
    assert b2.accepted == b.accepted and b2.started and b2.restarts == 1
    drive(b2)
    sol = b2.result()
    same(sol, solve(INST, "greedy", SEED))
    assert sol.extra["board_restarts"] == 1 and b2.version > version
    assert sol.extra["mission_wall_seconds"] >= 40.0  # counted from the mission's start, not the restart
    header, recs, _, dropped = read_journal(j)
    assert header["format"] == JOURNAL_FORMAT and dropped is None
    assert [r["v"] for r in recs] == list(range(1, b2.version + 1))  # one line per version, none twice
    kinds = {e["type"] for r in recs for e in r.get("ev", ())}
    assert {"start", "choice", "arrival", "resume"} <= kinds
    assert recs[-1]["phase"] == "done" and recs[-1]["wall_seconds"] == pytest.approx(sol.extra["mission_wall_seconds"],
                                                                                      abs=1e-3)
    # a board that replays the finished mission ends at once with the same result, ten minutes on:
    # the mission's own wall time, not the time since it started
    epoch[0] += 600.0
    b3 = started_board(journal=j)
    assert b3.finished and b3.state.done
    again = b3.result()
    same(again, sol)
    assert again.extra["mission_wall_seconds"] == sol.extra["mission_wall_seconds"]
    assert again.compute_seconds == sol.compute_seconds and again.extra["lost_robots"] == []


def test_a_restarted_board_gives_robots_it_has_not_heard_yet_the_start_up_timeout(tmp_path):
    """A board restarted on its journal is found by the agents' publishers only after discovery
    (heartbeats sent before are lost): a robot it has not heard yet is dropped only after the
    start-up timeout, as at the first start; one it heard and then not is dropped after the
    heartbeat timeout."""
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    for a in range(INST.n_agents):
        b.heartbeat(b.session, [b.names[a]])
    drive(b, steps=5)
    assert b.join("newbie", species=0) is None and "newbie" in b.names  # joined at run time
    b.poll()
    now = FakeTime()
    b2 = started_board(journal=j, now=now, heartbeat_timeout=5.0, startup_timeout=30.0)
    assert b2.restarts == 1 and b2.started and not b2.lost and b2.names[-1] == "newbie"
    late = {1, 2, len(b2.names) - 1}  # their agents' processes are discovered late (the joined robot's too)
    for k in range(200):  # 20 s of ticks every 0.1 s, heartbeats every second
        now.t += 0.1
        if k % 10 == 9:
            b2.heartbeat(b2.session, [n for a, n in enumerate(b2.names) if a not in late and (a != 3 or k < 20)])
        b2.tick()
    assert set(b2.lost) == {3} and b2.lost[3] == "no agent heartbeat for 5 s"  # heard, then silent
    for _ in range(110):  # past the start-up timeout of the restart
        now.t += 0.1
        b2.heartbeat(b2.session, [n for a, n in enumerate(b2.names) if a not in late | {3}])
        b2.tick()
    assert set(b2.lost) == late | {3} and b2.lost[1] == "no agent heartbeat since the board restarted (30 s)"


def test_losses_are_journaled_and_replayed(tmp_path):
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j, heartbeat_timeout=0.0)
    drive(b, steps=3)
    b.lose(2, "test loss")
    drive(b, steps=2)
    b.poll()
    b2 = started_board(journal=j, heartbeat_timeout=0.0)
    assert b2.lost == {2: "test loss"} and b2.state.snapshot() == b.state.snapshot()
    drive(b2)
    drive(b)
    assert b2.result().routes == b.result().routes


def test_a_torn_last_line_is_dropped_never_applied_in_part(tmp_path):
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    drive(b, steps=5)
    b.poll()
    intact = j.read_bytes()
    header, recs, good, _ = read_journal(j)
    assert good == len(intact)
    last = json.dumps({"v": b.version + 1, "rev": b.rev + 1, "ev": [{"type": "choice", "robot": 0, "node": 1,
                                                                      "version": b.version}]}).encode()
    for torn in (last[: len(last) // 2], last[:-1] + b"\n"[:0], b"\x00\x00\x00\n"):
        j.write_bytes(intact + torn)
        h, r, keep, dropped = read_journal(j)
        assert dropped and "torn last line" in dropped and keep == len(intact) and r == recs
        logged = []
        b2 = started_board(journal=j, log=lambda lvl, text: logged.append(text))
        assert (b2.version, b2.rev) == (b.version, b.rev) and b2.state.snapshot() == b.state.snapshot()
        assert any("dropped a torn last line" in t for t in logged)
        b2.close()
        assert j.read_bytes().startswith(intact) and b"\x00" not in j.read_bytes()[len(intact):]
        assert read_journal(j)[3] is None  # the file was cut back before anything was appended
        j.write_bytes(intact)
    # a damaged line that is not the last is corruption, not a torn write
    lines = intact.split(b"\n")
    lines[2] = lines[2][:10]
    j.write_bytes(b"\n".join(lines))
    with pytest.raises(JournalError, match="line 3"):
        started_board(journal=j)


def test_a_file_that_is_not_a_journal_is_refused_and_left_untouched(tmp_path):
    j = tmp_path / "notes.txt"
    for text in (b"important notes\n", b"garbage", b"[1, 2]\n", b'{"v": 1}\n'):
        j.write_bytes(text)
        with pytest.raises(JournalError, match="not an hmrta journal|expected format"):
            started_board(journal=j)
        assert j.read_bytes() == text
    # a header cut short (the board died while writing it) is a torn journal, started afresh
    full = tmp_path / "full.jsonl"
    started_board(journal=full).poll()
    header_line = full.read_bytes().split(b"\n")[0]
    for cut in (5, len(header_line) // 2, len(header_line) - 1):
        j.write_bytes(header_line[:cut])
        b = started_board(journal=j)
        b.poll()
        b.close()
        assert read_journal(j)[0]["format"] == "hmrta-journal/1"


def test_a_journal_of_another_mission_is_refused(tmp_path):
    j = tmp_path / "journal.jsonl"
    started_board(journal=j).poll()
    with pytest.raises(JournalError, match="another mission"):
        MissionBoard(INST, seed=SEED + 1, rules=RULES, wait_for_robots=False, journal=j)
    other = ScenarioGenerator("MA-AT", 6, 3, 10, 3).instance(5, 0)
    with pytest.raises(JournalError, match="instance_sha256"):
        MissionBoard(other, seed=SEED, rules=RULES, wait_for_robots=False, journal=j)
    j.write_text('{"format": "hmrta-journal/9"}\n')
    with pytest.raises(JournalError, match="expected format"):
        started_board(journal=j)


def test_a_journal_resumed_under_another_method_says_how_to_resume_it(tmp_path):
    """The same mission restarted with another method: the journal is not another mission's (the
    old text said to remove it, losing the mission); the error says which method resumes it."""
    j = tmp_path / "journal.jsonl"
    started_board(journal=j, method="greedy").poll()
    with pytest.raises(JournalError) as e:
        MissionBoard(INST, seed=SEED, rules=RULES, method="greedy-coalition", wait_for_robots=False, journal=j)
    assert "-p method:=portfolio" in str(e.value) and "-p method:=greedy;" in str(e.value)
    assert "another mission" not in str(e.value) and "remove it" not in str(e.value)


def test_journal_lines_validate_against_the_schema(tmp_path):
    from test_schemas import assert_valid

    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    drive(b, steps=4)
    b.lose(1, "test")
    b.poll()
    header, recs, _, _ = read_journal(j)
    assert_valid("hmrta-journal/1", header)
    for r in recs:
        assert_valid("hmrta-journal/1#/$defs/version", r)


def test_operator_tasks_are_added_cancelled_answered_and_journaled(tmp_path):
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    early = b.task_request("add", "x", {"location": [0.5, 0.5], "requirements": [1, 0, 0], "duration": 1.0})
    assert early["event"] == "accepted"  # a started board takes requests at once
    drive(b, steps=3)
    new = {"location": [0.2, 0.8], "requirements": [1, 1, 0], "duration": 2.0}
    a = b.task_request("add", "inspect-7", new)
    assert a["event"] == "accepted" and a["task"] == INST.n_tasks + 1
    assert b.task_request("add", "inspect-7", new)["reason"] == "task 'inspect-7': a task with this id exists already"
    bad = b.task_request("add", "too-big", {**new, "requirements": [99, 0, 0]})
    assert bad["event"] == "rejected" and "skill 0" in bad["reason"]
    assert b.task_request("cancel", "nope")["reason"].startswith("task 'nope': no task with this id")
    assert b.task_request("cancel", str(INST.n_tasks + 7))["event"] == "rejected"  # no such index either
    assert b.task_request("cancel", "x")["event"] == "accepted"
    drive(b, steps=2)
    b.poll()
    snap = b.state.snapshot()
    b2 = started_board(journal=j)
    assert b2.state.snapshot() == snap and set(b2.requests) == {"x", "inspect-7"}
    assert b.live_events == b2.live_events == {"add_task": 2, "cancel_task": 1}  # the refused ones: none
    drive(b)
    events = [(e["id"], e["event"]) for e in b.task_events]
    assert ("inspect-7", "started") in events and ("inspect-7", "done") in events and ("x", "cancelled") in events
    assert events.index(("inspect-7", "started")) < events.index(("inspect-7", "done"))
    sol = b.result()
    assert sol.extra["undone_tasks"] == [INST.n_tasks] and len(sol.tasks) == INST.n_tasks + 2
    assert sol.extra["live_events"] == {"add_task": 2, "cancel_task": 1}
    assert len(sol.extra["final_instance"]["tasks"]) == INST.n_tasks + 2


@pytest.mark.parametrize("later", [None, 0.0, 0.6])
def test_an_operator_task_while_the_robots_drive_home_reopens_the_mission(tmp_path, later):
    """Every task done, the robots driving home: an operator's task is accepted at the mission
    clock (``later`` None: the board clock at the last completion itself) and done, and the
    mission equals the offline one that knew the task would come then; the journal rebuilds it.
    A robot lost on the way home closes the mission for good."""
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    while not b.state.done:
        st = b.state
        if later is None and st.agent is None and not ((st.status == EMPTY) | (st.status == OPEN)).any():
            drive(b, clock=max(float(e[0]) for e in st.events))  # the board clock stops at the last completion
        else:
            drive(b, steps=1, clock=b.clock + 0.05)
    pump(b)
    if later is None:
        assert b.clock == b.state.clock
        later = 0.0
    assert b.phase == "closing" and not b.finished
    home = max(float(x) for x in b.state.arrive)
    b.set_clock(b.state.clock + later * (home - b.state.clock))  # on the way home
    pump(b)
    task = {"location": [0.9, 0.1], "requirements": [1, 1, 0], "duration": 1.5}
    assert b.task_request("cancel", "3")["reason"].startswith("task '3': already done; nothing to cancel: every "
                                                                "task is done")
    assert b.task_request("cancel", "nosuch")["reason"].startswith("task 'nosuch': no task with this id")
    ans = b.task_request("add", "late", task)
    assert ans["event"] == "accepted" and ans["task"] == INST.n_tasks and ans["t"] == pytest.approx(b.clock)
    assert not b.state.done
    drive(b)
    assert b.finished and b.state.success and b.state.status[INST.n_tasks] == DONE
    ref = MissionState(INST, seed=SEED, rules=RULES)
    ref.schedule({"type": "add_task", "t": ans["t"], "task": task, "name": "late"})
    while not ref.done:
        ref.step(Greedy()(ref))
    assert b.state.routes == ref.routes and b.state.makespan == ref.makespan
    assert b.result().extra["live_events"] == {"add_task": 1}
    assert started_board(journal=j).state.snapshot() == b.state.snapshot()

    b = started_board()
    while not b.state.done:
        drive(b, steps=1, clock=b.clock + 0.05)
    b.lose(0, "silent")
    refused = b.task_request("add", "late", task)
    assert refused["event"] == "rejected" and "a robot was lost on the way" in refused["reason"]


def test_the_journal_of_a_changed_mission_checks_every_decision_against_the_method(tmp_path):
    """A mission with an operator's task, a cancellation, a task added while the robots drive home
    and a robot lost: replaying its journal, every recorded choice is greedy's on the same state;
    a journal whose choice was changed is caught at that choice; another method disagrees."""
    from hmrta.board import check_journal_decisions

    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    drive(b, steps=3)
    assert b.task_request("add", "x", {"location": [0.5, 0.5], "requirements": [1, 0, 0], "duration": 1.0})["event"] == "accepted"
    drive(b, steps=4)
    b.lose(1, "silent")
    drive(b, steps=2)
    assert b.task_request("cancel", "x")["event"] == "accepted"
    while not b.state.done:
        drive(b, steps=1, clock=b.clock + 0.05)
    assert b.task_request("add", "late", {"location": [0.9, 0.1], "requirements": [1, 1, 0],
                                          "duration": 1.5})["event"] == "accepted"
    drive(b)
    n = sum(1 for line in j.read_text().splitlines()[1:] for ev in json.loads(line).get("ev", ()) if ev["type"] == "choice")
    assert check_journal_decisions(INST, j, Greedy(), SEED, RULES) == (n, None) and n > 10
    agree, first = check_journal_decisions(INST, j, decider("greedy-coalition", SEED)[0], SEED, RULES)
    assert first is not None and agree < n
    lines = j.read_text().splitlines()
    for i, line in enumerate(lines[1:], 1):  # the fifth choice made otherwise
        rec = json.loads(line)
        choices = [ev for ev in rec.get("ev", ()) if ev["type"] == "choice"]
        if choices and sum(1 for x in lines[1:i] for ev in json.loads(x).get("ev", ()) if ev["type"] == "choice") == 4:
            choices[0]["node"] = 0 if choices[0]["node"] else 1
            lines[i] = json.dumps(rec)
            break
    j.write_text("\n".join(lines) + "\n")
    agree, first = check_journal_decisions(INST, j, Greedy(), SEED, RULES)
    assert agree == 4 and "chose node" in first


def test_an_added_task_is_accepted_exactly_when_a_mission_file_could_hold_it():
    """The board's check of an add request and a mission file's validation take the same bounds
    (duration and requirements in [0, MAX_VALUE], the location in the unit square), integers beyond
    the float range included: a refusal is an answer, never an exception."""
    from hmrta.instance import MAX_VALUE, InstanceError

    b = started_board()
    base = {"location": [0.2, 0.8], "requirements": [1, 0, 0], "duration": 2.0}
    changes = [{"duration": 0}, {"duration": MAX_VALUE}, {"duration": MAX_VALUE + 1}, {"duration": 10**400},
               {"duration": -1.0}, {"requirements": [10**400, 0, 0]}, {"requirements": [0, 0, 0]},
               {"location": [0.2, 1.5]}, {"location": [10**400, 0.5]}]
    in_file, live = [], []
    for i, change in enumerate(changes):
        task = {**base, **change}
        d = INST.to_dict()
        try:
            instance_from_dict({**d, "tasks": d["tasks"] + [task]})
            in_file.append(True)
        except InstanceError:
            in_file.append(False)
        ans = b.task_request("add", f"op-{i}", task)
        live.append(ans["event"] == "accepted")
        assert ans["event"] == "accepted" or ans["reason"].startswith("new task: "), ans
    assert in_file == [True, True] + [False] * 7
    assert live == in_file


def test_a_refused_request_changes_nothing_even_while_the_clock_runs_ahead_of_the_state(tmp_path):
    """An operator add the team cannot do, or a join of an unknown species, between two events
    (the mission clock ahead of the held state): the state, its revision and its journal stay as
    they were, so the replicas (which never hear of a refusal) stay equal to the board."""
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    n = drive(b, steps=4)
    while b.phase == "decide" and n < 40:  # to a moment with every robot on its way
        n += drive(b, steps=1)
    while b.poll() is not None:
        pass
    assert b.phase != "decide"
    b.set_clock(b.clock + 0.25 * (b._key[3] - b.clock))  # part way to the next event
    b.poll()
    assert b.state.clock < b.clock  # the state is held at its last event
    before = (state_digest(b.state), b.rev, float(b.state.clock), j.read_text())
    bad = {"location": [0.2, 0.8], "requirements": [99, 0, 0], "duration": 2.0}
    assert b.task_request("add", "too-big", bad)["event"] == "rejected"
    assert b.task_request("add", "nan", {**bad, "requirements": [1, 0, 0], "duration": math.nan})["event"] == "rejected"
    assert "cannot join" in b.join("stranger", species=INST.n_species + 3)
    assert b.poll() is None
    assert (state_digest(b.state), b.rev, float(b.state.clock), j.read_text()) == before
    drive(b)
    b2 = started_board(journal=j)  # the journal replays to the same state
    assert b2.state.snapshot() == b.state.snapshot()


def test_a_task_of_the_mission_is_cancelled_by_its_index(tmp_path):
    """``hmrta-task cancel 3``: a task of the mission file (no operator id) by the index that
    ``hmrta-task list`` prints; journaled, so a restarted board has it cancelled too."""
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    drive(b, steps=2)
    m = next(m for m in range(INST.n_tasks) if b.state.status[m] <= 1 and not b.state.members[m])  # nobody on it
    ans = b.task_request("cancel", str(m))
    assert ans["event"] == "accepted" and ans["task"] == m and b.state.status[m] == 4  # cancelled
    assert b.task_request("cancel", str(m))["event"] == "rejected"  # already cancelled
    digits = b.task_request("add", "3", {"location": [0.2, 0.8], "requirements": [1, 0, 0], "duration": 1.0})
    assert digits["event"] == "rejected" and "names a task of the mission by its index" in digits["reason"]
    assert b.task_request("add", "op-1", {"location": [0.2, 0.8], "requirements": [1, 0, 0], "duration": 1.0})["event"] == "accepted"
    assert b.task_request("cancel", "op-1")["task"] == INST.n_tasks  # which task a cancel cancelled
    b.poll()
    assert b.live_events == {"cancel_task": 2, "add_task": 1}  # counted as published
    drive(b)
    sol = b.result()
    assert m in sol.extra["undone_tasks"] and all(m not in r for r in sol.routes)
    b2 = started_board(journal=j)
    assert b2.state.snapshot() == b.state.snapshot()


def test_the_board_state_never_runs_ahead_of_the_mission_clock():
    """A task whose work outlasts every decision is still running (and cancellable) on the board
    while the clock has not reached its finish; the held state ends like the offline rollout."""
    b = started_board()
    long = {"location": [0.9, 0.1], "requirements": [0, 1, 0], "duration": 500.0}
    assert b.task_request("add", "spare", long)["event"] == "accepted"
    drive(b, clock=50.0)  # long after every other task is done
    b.poll()
    m = b.state.names.index("spare")
    assert not b.state.done and b.state.clock <= b.clock + 1e-6 < 500.0
    assert b.phase in ("wait", "decide") and b.state.status[m] != 3  # not done before its time
    ans = b.task_request("cancel", "spare")
    assert ans["event"] == "accepted", ans
    drive(b)
    assert b.finished and b.state.status[m] == 4 and b.result().makespan < 500.0


def test_a_stray_clock_past_the_horizon_is_followed_only_up_to_the_horizons_the_board_publishes(tmp_path):
    """Another publisher on the clock's topic (a second sim_robot, a recording played back) jumps
    the clock far ahead: the board follows it only up to the horizon it published, warns once,
    and the mission still equals the offline rollout (no task completes before its time)."""
    said: list[str] = []
    b = started_board(journal=tmp_path / "j.jsonl", log=lambda level, text: said.append(text))
    drive(b, steps=3)
    b.poll()
    allowed = b.allowed
    assert allowed == b._key[3] and allowed < 1000.0
    b.set_clock(100000.0)  # the stray clock
    assert b.clock == allowed and b.state.clock <= allowed + 1e-9
    b.set_clock(100000.5)  # it keeps publishing: one warning for it (at most one every 10 s)
    assert sum("past the board's horizon" in t for t in said) == 1
    # the simulated robots' own clock, paced (0.5 a step up to each horizon), takes over: the board
    # follows it and is never ahead of it again (the stray value is forgotten, not caught up with)
    paced = allowed
    for _ in range(5000):
        pump(b)
        if b.finished:
            break
        if b.phase == "decide":
            assert b.choice(Choice(b.names[b.state.agent], b.session, b.version, Greedy()(b.state))) is None
            continue
        paced = min(paced + 0.5, b._key[3])
        b.set_clock(paced)
        assert b.clock == pytest.approx(paced)
        for a in range(b.state.A):
            base = [(0, *map(float, b.state.inst.depots[a]), 0.0)]
            b.pose(a, *position(b.inst, base + b.state.leg_log[a], b.clock))
    assert b.finished
    same(b.result(), solve(INST, "greedy", SEED))
    # a board restarted on the journal knows the horizons its predecessor published
    b2 = started_board(journal=tmp_path / "j.jsonl")
    assert b2.allowed == pytest.approx(b.allowed)


def test_a_new_board_that_first_hears_a_clock_it_never_released_knows_it_for_another_missions(tmp_path):
    """A board restarted without its journal (a sim_robot still following its predecessor's
    mission at t=4) used to follow that clock up to its own horizons and then wait forever for
    arrivals nobody drove to. Its first clock past what it released is named another mission's;
    a board resumed on its journal takes the clock as its own."""
    j = tmp_path / "j.jsonl"
    b = MissionBoard(INST, seed=SEED, rules=RULES, journal=tmp_path / "other.jsonl")
    assert b.foreign_clock(0.0) is None  # its own sim_robot, before the start
    why = b.foreign_clock(4.081)
    assert why.startswith("the mission clock is at 4.081 s before this board released any time (horizon 0.000 s)")
    assert "-p journal:=FILE" in why and "restart sim_robot" in why and "mission_namespace" in why
    b = started_board(journal=j)
    drive(b, steps=5)
    b.poll()
    assert b.foreign_clock(b.allowed) is None and b.foreign_clock(b.allowed + 1.0) is not None
    b2 = started_board(journal=j)  # restarted on its journal: the clock runs on from where it was
    assert b2.replayed > 0 and b2.foreign_clock(b.allowed + 1000.0) is None


def test_a_clock_heard_past_the_horizon_is_followed_as_new_horizons_allow():
    """A clock that ran ahead of what this board process has published (it lost the line of its
    latest horizon) is not lost: the board catches up as its horizons grow, and finishes."""
    b = started_board()
    drive(b, steps=2)
    b.poll()
    target = b.allowed + 3.0
    b.set_clock(target)  # then silent: the simulated robots wait for a horizon past it
    assert b.clock == b.allowed < target
    for _ in range(200):  # decisions and arrivals only: nobody publishes the clock again
        pump(b)
        if b.clock >= target:
            break
        if b.phase == "decide":
            assert b.choice(Choice(b.names[b.state.agent], b.session, b.version, Greedy()(b.state))) is None
        for a in range(b.state.A):
            base = [(0, *map(float, b.state.inst.depots[a]), 0.0)]
            b.pose(a, *position(b.inst, base + b.state.leg_log[a], b.clock))
    assert b.clock == target  # reached by the board's own horizons
    drive(b)
    assert b.finished and b.result().success


def test_a_held_state_ends_exactly_like_one_never_held():
    ref = MissionState(INST, seed=SEED, rules=RULES)
    held = MissionState(INST, seed=SEED, rules=RULES)
    held.until = 0.0
    decide = decider("greedy", SEED)[0]
    held.advance_to(0.0)
    steps = 0
    while not held.done:
        if held.agent is None:
            nxt = min([held.events[0][0]] if held.events else [math.inf])
            held.advance_to(nxt / 2 if steps % 2 else nxt)  # halfway stops change nothing
            steps += 1
            continue
        node = int(decide(held))
        assert ref.agent == held.agent and ref.clock == held.clock
        ref.step(node)
        held.step(node)
    assert ref.done and held.snapshot() == ref.snapshot() and steps > 2


# ---------------------------------------------------------------------------------------------
# robots joining a running mission
# ---------------------------------------------------------------------------------------------
@dataclass
class Join:  # what hmrta_msgs_py.codec.status_from_msg gives the board in Status.joining
    robot: str
    species: int | None = None
    traits: Any = None
    position: Any = None


def test_a_robot_that_asks_to_join_is_added_journaled_and_works(tmp_path):
    waiting = MissionBoard(INST, seed=SEED, rules=RULES, now=FakeTime())
    assert waiting.heartbeat(waiting.session, [], joining=[Join("robot_new", 1)]) is None
    assert "robot_new" not in waiting.names  # not before the mission runs (the agent asks again)
    j = tmp_path / "journal.jsonl"
    b = started_board(journal=j)
    drive(b, steps=4)
    t = b._event_time()
    b.heartbeat(b.session, [], joining=[Join("robot_new", 1, position=(0.5, 0.25))])
    A = INST.n_agents
    assert b.names == [f"robot_{a}" for a in range(A)] + ["robot_new"] and b.robots_changed
    assert b.state.A == A + 1 and list(b.state.inst.agent_species[A:]) == [1]
    assert tuple(b.state.from_pos[A]) == (0.5, 0.25)
    b.heartbeat(b.session, [], joining=[Join("robot_new", 1)])  # repeated until it is in the mission: no-op
    assert b.state.A == A + 1
    refused = b.heartbeat(b.session, [], joining=[Join("robot_x", 7)])
    assert refused == "robot 'robot_x' cannot join: new robot: species 7: no such species (0..2)"
    assert b.heartbeat(b.session, [], joining=[Join("robot_x", 7)]) is None  # warned once
    drive(b)
    sol = b.result()
    assert sol.success and sol.routes[A] and sol.extra["robots"][A] == "robot_new"
    # the same mission offline: the robot added by a timed event at the same instant, same place
    ref = MissionState(INST, seed=SEED, rules=RULES)
    ref.schedule({"type": "add_agent", "t": t, "species": 1, "position": [0.5, 0.25]})
    decide = decider("greedy", SEED)[0]
    while not ref.done:
        ref.step(int(decide(ref)))
    assert [list(r) for r in ref.routes] == sol.routes and ref.makespan == sol.makespan
    # replayed from the journal: the same robots under the same names, the same state
    b2 = started_board(journal=j)
    assert b2.names == b.names and b2.state.snapshot() == b.state.snapshot()
    same(b2.result(), sol)


def test_robots_asking_to_join_are_taken_at_most_join_rate_a_second():
    """One heartbeat naming a hundred robots adds a burst of 2 x JOIN_RATE; the others join as
    their agents ask again, JOIN_RATE a second, with one warning."""
    said: list[str] = []
    b = started_board(log=lambda level, text: said.append(text))
    drive(b, steps=2)
    A, burst = b.state.A, int(2 * MissionBoard.JOIN_RATE)
    crowd = [Join(f"robot_j{i}", 0) for i in range(100)]
    b.heartbeat(b.session, [], joining=crowd)
    assert b.state.A == A + burst
    b.heartbeat(b.session, [], joining=crowd)  # asked again at once: nobody more
    assert b.state.A == A + burst
    b.now.t += 1.0
    b.heartbeat(b.session, [], joining=crowd)
    assert b.state.A == A + burst + int(MissionBoard.JOIN_RATE)
    assert b.names[A:A + 3] == ["robot_j0", "robot_j1", "robot_j2"]
    assert sum("faster than" in t for t in said) == 1


def test_a_grown_mission_instance_round_trips_and_never_counts_added_robots_twice():
    st = MissionState(INST, seed=SEED, rules=RULES)
    decide = decider("greedy", SEED)[0]
    for _ in range(3):
        st.step(int(decide(st)))
    st.add_agent(2)
    st.add_agent(traits=[1, 1, 0], position=[0.1, 0.9])
    snap = json.loads(json.dumps(st.snapshot()))
    grown = dataclasses.replace(st.inst, tasks=INST.tasks, _cache={})
    wire = instance_from_dict(json.loads(json.dumps(grown.to_dict())))
    assert wire.n_agents == INST.n_agents + 2 and wire.added_agents == (2, 3) and wire.species[3].count == 0
    assert instance_from_dict(json.loads(json.dumps(wire.to_dict()))).added_agents == (2, 3)
    for inst in (INST, wire):  # the instance as it started, or as republished: the same state
        again = MissionState.from_snapshot(inst, snap)
        assert again.A == INST.n_agents + 2 and again.snapshot() == snap
    d = wire.to_dict()
    d["species"][3]["count"] = 0
    d["added_agents"] = [2]  # a species nobody has
    with pytest.raises(ValueError, match=r"species\[3\]\.count"):
        instance_from_dict(d)


def test_scenario_robots_are_named_by_their_order_and_joined_robots_keep_their_names():
    inst = dataclasses.replace(INST, events=({"type": "add_agent", "t": 0.5, "species": 0},
                                             {"type": "add_agent", "t": 1.0, "species": 2}), _cache={})
    b = MissionBoard(inst, seed=SEED, rules=RULES, wait_for_robots=False, now=FakeTime())
    b.heartbeat(b.session, [], joining=[Join("scout", 1)])
    drive(b)
    A = INST.n_agents
    assert b.names[A:] == ["scout", f"robot_{A}", f"robot_{A + 1}"] and b.result().success


def test_robots_a_scenario_adds_at_time_0_are_on_the_board_from_its_first_version(tmp_path):
    """A scenario's add_robot at t=0 is applied as the state is built: the board's first version
    crashed (IndexError in state_digest: the leg counts of the robots at the start only), and so
    did every restart on its journal."""
    inst = dataclasses.replace(INST, events=({"type": "add_agent", "t": 0.0, "species": 0},
                                             {"type": "drop_agent", "t": 0.0, "agent": 1},
                                             {"type": "add_agent", "t": 1.0, "species": 2}), _cache={})
    A = INST.n_agents
    j = tmp_path / "journal.jsonl"
    b = MissionBoard(inst, seed=SEED, rules=RULES, wait_for_robots=False, now=FakeTime(), journal=j)
    assert b.names[A:] == [f"robot_{A}"] and len(b.state.leg_seqs) == A + 1 and b.poll() is not None
    assert b.robots_changed and b.lost == {1: "lost (scenario event)"}  # (the node republishes the mission)
    # (replicas built from version 0 alike: tests/policy/test_replica.py)
    drive(b, steps=3)
    b.close()
    again = MissionBoard(inst, seed=SEED, rules=RULES, wait_for_robots=False, now=FakeTime(), journal=j)
    assert again.names[:A + 1] == b.names[:A + 1] and again.restarts == 1
    drive(again)
    sol = again.result()
    assert sol.success and again.names[A:] == [f"robot_{A}", f"robot_{A + 1}"]
    same(sol, solve(inst, "greedy", SEED))


def test_task_answers_echo_the_request_id():
    b = started_board()
    task = {"location": [0.5, 0.5], "requirements": [1, 0, 0], "duration": 1.0}
    assert b.task_request("add", "a", task, request_id="n1")["request_id"] == "n1"
    again = b.task_request("add", "a", task, request_id="n2")
    assert again["event"] == "rejected" and again["request_id"] == "n2"
    assert "request_id" not in b.task_request("cancel", "a")


# ---------------------------------------------------------------------------------------------
# arrival tolerance and stuck robots
# ---------------------------------------------------------------------------------------------
def short(d: float, who=None):
    """``where`` of robots that stop ``d`` mission units short of every goal (``who``: only those)."""
    def where(a, xy):
        return (xy[0] - d / math.sqrt(2), xy[1] - d / math.sqrt(2)) if who is None or a in who else xy
    return where


def test_a_robot_within_tolerance_of_its_goal_has_arrived():
    # 10 m per mission unit: 0.25 m of tolerance; every robot stops 0.2 m short of its goals
    b = started_board(tolerance=0.025, scale=10.0, leg_timeout_factor=0.0, leg_timeout_floor=0.0)
    drive(b, where=short(0.02))
    sol = b.result()
    same(sol, solve(INST, "greedy", SEED))
    assert b.finished and sol.extra["lost_robots"] == []
    # with 0.1 m of tolerance the same robots never arrive: the clock is held, and says why, readably
    b = started_board(tolerance=0.01, scale=10.0, leg_timeout_factor=0.0, leg_timeout_floor=0.0)
    with pytest.raises(AssertionError, match="stuck") as e:
        drive(b, where=short(0.02), max_iter=300)
    text = str(e.value)
    assert "np.float64" not in text and "0.20 m from the task" in text and "tolerance 0.10 m" in text


def test_a_robot_near_its_next_task_before_setting_off_has_not_arrived():
    b = started_board(tolerance=0.5)  # half the mission area: every task is "near"
    drive(b, steps=3)
    for a in range(b.state.A):
        for i, m in enumerate(b.state.routes[a][:b.ptr[a]]):
            assert b._departed(a, 1 + int(m))


def test_a_robot_standing_near_its_task_arrives_when_its_leg_departs_without_a_new_pose():
    """Robots report only when they move: one that stands within tolerance of its next task (half
    the mission area) is confirmed there once its leg has departed, with no pose after that."""
    b = started_board(tolerance=0.5, leg_timeout_factor=0.0, leg_timeout_floor=0.0)
    drive(b, changes_only=True)
    same(b.result(), solve(INST, "greedy", SEED))


def stuck_board(**kw):
    logs: list[tuple[float, str, str]] = []
    now = FakeTime()
    b = started_board(now=now, leg_timeout_factor=1.0, leg_timeout_floor=2.0, heartbeat_timeout=0.0,
                      log=lambda level, text: logs.append((now.t, level, text)), **kw)
    return b, now, logs


def test_a_robot_that_never_arrives_gets_its_goal_again_then_is_dropped_and_the_rest_finish(tmp_path):
    j = tmp_path / "journal.jsonl"
    b, now, logs = stuck_board(journal=j)
    s = 0  # reports its depot whatever its goals
    drive(b, tick=0.1, where=lambda a, xy: tuple(INST.depots[a]) if a == s else xy)
    sol = b.result()
    assert b.finished and list(b.lost) == [s]
    reason = sol.extra["lost_reasons"][b.names[s]]
    assert reason.startswith("stuck: no arrival at task ") and "goal re-sent after" in reason
    assert "np.float64" not in reason
    resend = [t for t, level, text in logs if "re-sending its goal" in text]
    lost = [t for t, level, text in logs if "lost (stuck" in text]
    assert len(resend) == 1 and len(lost) == 1
    limit = float(reason.split("re-sent after ")[1].split(" s")[0])
    assert lost[0] - resend[0] == pytest.approx(limit, abs=0.25)  # the second timeout: one more limit
    log = b.state.leg_log[s]
    again = [i for i, g in enumerate(log) if g[0] == RESEND]
    assert len(again) == 1 and log[again[0]][1:] in [g[1:] for g in log[:again[0]] if g[0] > 0]  # a task's leg
    # the others finished every task they can do without it
    team = INST.traits[[a for a in range(INST.n_agents) if a != s]].sum(0)
    for m in sol.extra["undone_tasks"]:
        assert not (INST.requirements[m] <= team).all()
    assert all(r["return_time"] is not None for a, r in enumerate(sol.to_dict()["agents"]) if a != s)
    # the resend is journaled: a board replayed from the journal has the same legs and state
    b.close()
    r = MissionBoard(INST, seed=SEED, rules=RULES, journal=j, now=FakeTime())
    assert r.state.leg_log == b.state.leg_log and r.rev == b.rev and r.finished
    for st in (b.state, r.state):  # the resend counts as a leg in the counter the digest reads
        assert st.leg_seqs.tolist() == [n + len(log) for n, log in zip(st.leg_base, st.leg_log)]
    # the result says where the robot was, its depot (reported_at), not only where its plan had it
    # (at: its task); so does the board replayed from the journal, and the map's X stands there
    for board in (b, r):
        drop, = [e for e in board.result().extra["dynamic"]["events"] if e["type"] == "drop_agent"]
        assert drop["reported_at"] == pytest.approx(INST.depots[s].tolist()) and drop["at"] != drop["reported_at"]
    assert "reported_at" not in next(e for e in b.state.log if e["type"] == "drop_agent")  # the state's own log
    from hmrta.render import mission_changes

    got = mission_changes(INST, sol).reported_at
    assert list(got) == [s] and got[s] == pytest.approx(INST.depots[s].tolist())


def test_the_clock_held_by_a_robot_names_the_robots_due_not_those_on_their_way():
    """While one robot holds the clock at its task's start, the others on their way to later
    starts are on time: the diagnostics name only the robots due by the clock."""
    import re

    inst = ScenarioGenerator("MA-AT", 9, 3, 12, 3).instance(5, 0)
    b = MissionBoard(inst, seed=SEED, rules=RULES, wait_for_robots=False, now=FakeTime(), leg_timeout_factor=1.0,
                     leg_timeout_floor=2.0, heartbeat_timeout=0.0, log=lambda level, text: None)
    s, said = 6, []  # robot 6 stays at its depot; others are on their way to later starts meanwhile

    def where(a, xy):
        if a == s:
            said.append(b.waiting_for())
            return tuple(inst.depots[a])
        return xy

    drive(b, tick=0.1, where=where)
    held = 0
    for text in said:  # while robot s is due (its task's start reached), only robots due are named
        mine = re.search(rf"{b.names[s]} at task \d+ \(starts t=([0-9.]+) s", text)
        clock = float(re.search(r"clock ([0-9.]+) s", text).group(1))
        if mine and float(mine.group(1)) <= clock + 1e-3:
            held += 1
            assert all(float(x) <= clock + 1e-3 for x in re.findall(r"starts t=([0-9.]+) s", text)), text
    assert held


def test_a_late_robot_that_arrives_after_its_goal_was_re_sent_is_kept():
    b, now, logs = stuck_board()
    s, late = 1, {}

    def where(a, xy):
        if a != s:
            return xy
        if any("re-sending" in text for _, _, text in logs):
            late.setdefault("at", now.t)
            return xy
        return tuple(INST.depots[a]) if not late else xy

    drive(b, tick=0.1, where=where)
    sol = b.result()
    assert b.finished and b.lost == {} and "at" in late
    same(sol, solve(INST, "greedy", SEED))  # the clock waited: the plan is unchanged, only later


def test_no_leg_timeout_when_factor_and_floor_are_zero():
    b, now, logs = stuck_board()
    b.leg_timeout_factor = b.leg_timeout_floor = b.decision_timeout = 0.0
    drive(b, steps=2, report=False)  # nobody reports: the board waits for arrivals
    for _ in range(50):
        now.t += 100.0
        b.tick()
    assert b.lost == {} and not [text for _, _, text in logs[1:] if "did not run" not in text]


def test_a_wrong_gate_part_holds_the_mission_clock_at_most_gate_rescan_seconds(monkeypatch):
    """The arrival gate's safety net: a robot's part kept by mistake (here: forced below the
    clock) holds the clock only until the gate, still holding it, rescans every robot, at most
    GATE_RESCAN seconds of board time later."""
    from hmrta.board import GATE_RESCAN

    monkeypatch.setattr("hmrta.board.CHECK_GATE", False)  # the mistake must reach the safety net
    b = started_board()
    drive(b, steps=6)
    right = b.gate()
    assert right > b.clock  # nothing holds the clock here
    b._gate_part[0] = b.clock - 1.0  # a part kept by mistake
    assert b.gate() == b.clock - 1.0  # held...
    b.now.t += GATE_RESCAN / 2
    assert b.gate() == b.clock - 1.0  # ... for a while
    b.now.t += GATE_RESCAN / 2
    assert b.gate() == right  # then every robot is scanned afresh
    assert drive(b) > 0 and b.finished
