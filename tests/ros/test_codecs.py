"""hmrta_msgs_py codecs: pure *_to_msg / *_from_msg pairs, tested without a ROS graph."""
from __future__ import annotations

import json
import math

import pytest

pytest.importorskip("rclpy")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from hmrta.baselines import GREEDY_RULES, Greedy  # noqa: E402
from hmrta.core import MissionState  # noqa: E402
from hmrta.generators import ScenarioGenerator  # noqa: E402
from hmrta.methods import solve  # noqa: E402
from hmrta_msgs_py import codec as C  # noqa: E402
from hmrta_msgs_py import topics  # noqa: E402

INST = ScenarioGenerator("MA-AT", 6, 3, 8, 3).instance(5, 0)


def _msg(text: str) -> String:
    m = String()
    m.data = text
    return m


def _mid_state() -> MissionState:
    state = MissionState(INST, seed=2, rules=GREEDY_RULES)
    for _ in range(5):
        state.step(Greedy()(state))
    return state


def _board(state: MissionState, **kw) -> C.Board:
    legs = tuple((2, ((1, 0.25, 0.5, 0.0), (0, 0.1, 0.2, 3.5))) if a % 2 else None for a in range(state.A))
    d = dict(session="s1", version=7, rev=3, phase="decide", decider=state.agent, clock=float(state.clock),
             horizon=float(state.clock), n_done=int(state.n_done), n_cancelled=0, n_tasks=state.M, lost=(1, 3),
             legs=legs, state=state.snapshot())
    d.update(kw)
    return C.Board(**d)


# ---------------------------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------------------------
def test_mission_round_trip():
    m = C.Mission("abc", INST, tuple(f"r{a}" for a in range(INST.n_agents)), 4, "greedy", "odom", 2.5)
    back = C.mission_from_msg(C.mission_to_msg(m))
    assert back.instance.to_dict() == INST.to_dict()
    assert (back.session, back.robots, back.seed, back.policy, back.frame_id, back.scale) == \
        (m.session, m.robots, m.seed, m.policy, m.frame_id, m.scale)
    assert back.index("r3") == 3 and back.index("nobody") is None


def test_board_round_trip_rebuilds_the_exact_state():
    state = _mid_state()
    b = _board(state)
    msg = C.board_to_msg(b)
    back = C.board_from_msg(msg)
    assert back.header() == b.header()
    assert back.legs == b.legs
    restored = MissionState.from_snapshot(INST, back.state)
    assert json.dumps(restored.snapshot()) == json.dumps(state.snapshot())  # NaN-safe comparison
    # the restored state decides exactly like the original
    assert Greedy()(restored) == Greedy()(state)
    # header-only decoding skips legs and state
    h = C.board_from_msg(msg, legs=False, state=False)
    assert h.legs is None and h.state is None and h.header() == b.header()
    # the state line may be serialised once by the caller
    assert C.board_to_msg(b, C.state_to_json(b.state)).data == msg.data


def test_board_decoder_shares_one_decoded_copy():
    state = _mid_state()
    msg = C.board_to_msg(_board(state))
    dec = C.BoardDecoder()
    b1 = dec.decode(msg)
    b2 = dec.decode(_msg(msg.data))  # another subscription's copy of the same board
    assert b1 is b2 and b1.state is None
    s1 = dec.state(msg)
    assert s1 is dec.state(msg)
    assert json.dumps(s1) == json.dumps(state.snapshot())
    b3 = dec.decode(C.board_to_msg(_board(state, version=8)))
    assert b3 is not b1 and b3.version == 8


def test_small_payload_round_trips():
    c = C.Choice("robot_1", "s1", 12, 3, seq=4, compute_ms=1.25)
    assert C.choice_from_msg(C.choice_to_msg(c)) == c
    s = C.Status(("robot_1", "robot_2"), "s1", 9, "host:1")
    assert C.status_from_msg(C.status_to_msg(s)) == s
    r = C.Rejection("masked", "node 3 is not admissible", "robot_1", 12)
    assert C.rejection_from_msg(C.rejection_to_msg(r)) == r
    sol = solve(INST, "greedy", 1).to_dict()
    assert C.result_from_msg(C.result_to_msg(sol)) == json.loads(json.dumps(sol))


@pytest.mark.parametrize("t", [0.0, 1e-9, 0.5, 12.345678901, 1234567.123456789])
def test_clock_and_stamps_round_to_the_nanosecond(t):
    assert abs(C.clock_from_msg(C.clock_to_msg(t)) - t) <= 1e-9 * max(1.0, t) * 1.01
    with pytest.raises(ValueError):
        C.time_to_stamp(-1.0)


def test_pose_round_trip_with_frame_and_scale():
    msg = C.pose_to_msg((0.25, 0.75), 3.5, "map", scale=20.0)
    assert msg.header.frame_id == "map" and msg.pose.position.x == 5.0 and msg.pose.position.y == 15.0
    assert msg.pose.orientation.w == 1.0
    assert C.pose_from_msg(msg, 20.0) == (0.25, 0.75, 3.5)
    msg.pose.position.x = math.nan
    with pytest.raises(C.DecodeError):
        C.pose_from_msg(msg)


def test_markers_round_trip():
    v = C.MarkerView(((0.1, 0.2, "open"), (0.3, 0.4, "done")), (("robot_0", 0.5, 0.5, False), ("robot_1", 0.0, 1.0, True)),
                     ((0.0, 0.0, 1.0, 1.0),))
    msg = C.markers_to_msg(v, 2.0, "map", 10.0)
    assert len(msg.markers) == 5
    back = C.markers_from_msg(msg, 10.0)
    assert back.tasks == v.tasks and back.robots == v.robots
    assert [pytest.approx(g) == b for g, b in zip(v.legs, back.legs)] == [True]


def test_topic_names_and_qos_are_declared_once():
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    assert topics.BOARD_QOS.durability == DurabilityPolicy.TRANSIENT_LOCAL and topics.BOARD_QOS.depth == 1
    assert topics.BOARD_QOS.reliability == ReliabilityPolicy.RELIABLE
    assert topics.CHOICE_QOS.reliability == ReliabilityPolicy.RELIABLE and topics.CHOICE_QOS.depth >= 50
    assert topics.robot_topic("robot_3", topics.POSE) == "/robot_3/pose"
    assert topics.robot_topic("/fleet/tb3/", topics.GOAL) == "/fleet/tb3/goal_pose"


# ---------------------------------------------------------------------------------------------
# malformed payloads: always DecodeError, never anything else
# ---------------------------------------------------------------------------------------------
GOOD_CHOICE = {"schema": "hmrta-choice/1", "robot": "robot_1", "session": "s", "version": 3, "node": 1}
BAD_CHOICES = [
    "", "not json", "[1, 2]", "null", '"text"', "{}", '{"schema": "hmrta-choice/2"}',
    json.dumps({**GOOD_CHOICE, "version": True}),
    json.dumps({**GOOD_CHOICE, "version": "3"}),
    json.dumps({**GOOD_CHOICE, "version": 3.0}),
    json.dumps({**GOOD_CHOICE, "node": None}),
    json.dumps({**GOOD_CHOICE, "robot": ""}),
    json.dumps({**GOOD_CHOICE, "robot": 7}),
    json.dumps({**GOOD_CHOICE, "compute_ms": "fast"}),
    json.dumps({k: v for k, v in GOOD_CHOICE.items() if k != "session"}),
    '{"schema": "hmrta-choice/1", "robot": "r", "session": "s", "version": 1, "node": 1, "compute_ms": NaN}',
    "[" * 100000,
]


@pytest.mark.parametrize("text", BAD_CHOICES, ids=range(len(BAD_CHOICES)))
def test_malformed_choices_raise_decode_error(text):
    with pytest.raises(C.DecodeError):
        C.choice_from_msg(_msg(text))


def test_malformed_boards_missions_and_statuses_raise_decode_error():
    state = _mid_state()
    good = C.board_to_msg(_board(state)).data
    head, legs, snap = good.split("\n", 2)
    for text in ["", "x", head, head + "\n" + legs, f"{head}\n[[1]]\n{snap}", f"{head}\n{legs}\n[1]",
                 f"{head}\n{legs}\n{{", good.replace('"phase":"decide"', '"phase":"dancing"'),
                 good.replace('"version":7', '"version":"7"'), f'{head}\n[[0,[[1,0,0]]]]\n{snap}',
                 f'{head}\n[[0,[[1,0.1,0.2,0.0]]]]\n{snap}']:
        with pytest.raises(C.DecodeError):
            C.board_from_msg(_msg(text))
    inst = INST.to_dict()
    bad_missions = [{"schema": "hmrta-mission/1"},
                    {"schema": "hmrta-mission/1", "session": "s", "instance": {**inst, "velocity": -1}, "robots": [],
                     "seed": 0, "policy": "greedy", "frame_id": "map", "scale": 1.0},
                    {"schema": "hmrta-mission/1", "session": "s", "instance": inst, "robots": ["a"] * INST.n_agents,
                     "seed": 0, "policy": "greedy", "frame_id": "map", "scale": 1.0},
                    {"schema": "hmrta-mission/1", "session": "s", "instance": inst,
                     "robots": [f"r{i}" for i in range(INST.n_agents)], "seed": 0, "policy": "greedy",
                     "frame_id": "map", "scale": 0}]
    for d in bad_missions:
        with pytest.raises(C.DecodeError):
            C.mission_from_msg(_msg(json.dumps(d)))
    for d in [{"schema": "hmrta-status/1", "robots": "robot_1", "session": "s", "seq": 1},
              {"schema": "hmrta-status/1", "robots": [None], "session": "s", "seq": 1}]:
        with pytest.raises(C.DecodeError):
            C.status_from_msg(_msg(json.dumps(d)))
    with pytest.raises(C.DecodeError):
        C.result_from_msg(_msg('{"format": "hmrta-solution/0"}'))


JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
                    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=5),
                    max_leaves=12)
FIELDS = st.fixed_dictionaries({}, optional={"schema": st.sampled_from(["hmrta-choice/1", "hmrta-status/1",
                                                                          "hmrta-board/1", "x"]),
                                             "robot": JSON, "robots": JSON, "session": JSON, "version": JSON,
                                             "node": JSON, "seq": JSON, "compute_ms": JSON, "phase": JSON})


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=40), JSON.map(json.dumps), FIELDS.map(json.dumps)))
def test_fuzzed_payloads_decode_or_raise_decode_error(text):
    for decode in (C.choice_from_msg, C.status_from_msg, C.board_from_msg, C.mission_from_msg,
                   C.rejection_from_msg, C.result_from_msg):
        try:
            decode(_msg(text))
        except C.DecodeError:
            pass
