"""hmrta_msgs_py codecs: pure *_to_msg / *_from_msg pairs, tested without a ROS graph. Every
encoded message validates against its published JSON Schema (docs/schemas/)."""
from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
import jsonschema  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from referencing import Registry, Resource  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from hmrta.baselines import GREEDY_RULES, Greedy  # noqa: E402
from hmrta.core import MissionState, Rules  # noqa: E402
from hmrta.generators import ScenarioGenerator  # noqa: E402
from hmrta.methods import solve  # noqa: E402
from hmrta_msgs_py import codec as C  # noqa: E402
from hmrta_msgs_py import topics  # noqa: E402

INST = ScenarioGenerator("MA-AT", 6, 3, 8, 3).instance(5, 0)
RULES = Rules(max_open="team", backdate=False).to_dict()  # the rules object of a mission message
SCHEMAS = Path(__file__).resolve().parents[2] / "docs" / "schemas"
_ALL = [json.loads(p.read_text()) for p in sorted(SCHEMAS.glob("*.schema.json"))]
REGISTRY = Registry().with_resources((s["$id"], Resource.from_contents(s)) for s in _ALL)


def schema_errors(fmt: str, doc) -> list[str]:
    """Errors of doc against the published schema of fmt (``hmrta-board/2#/$defs/legs`` for a part)."""
    v = jsonschema.Draft202012Validator({"$ref": fmt}, registry=REGISTRY)
    return [f"{list(e.absolute_path)}: {e.message[:200]}" for e in v.iter_errors(doc)]


def assert_valid(fmt: str, doc) -> None:
    errs = schema_errors(fmt, doc)
    assert not errs, f"{fmt}: " + "; ".join(errs[:5])


def _mission(**kw) -> C.Mission:
    d = {"session": "abc", "instance": INST, "robots": tuple(f"r{a}" for a in range(INST.n_agents)), "seed": 4,
         "method": "greedy", "frame_id": "odom", "scale": 2.5, "rules": Rules.from_dict(RULES)}
    d.update(kw)
    return C.Mission(**d)


def _msg(text: str) -> String:
    m = String()
    m.data = text
    return m


def _mid_state() -> MissionState:
    state = MissionState(INST, seed=2, rules=GREEDY_RULES)
    for _ in range(5):
        state.step(Greedy()(state))
    return state


EVENTS = ({"type": "choice", "t": 1.5, "until": 1.5, "robot": 2, "node": 3, "version": 6, "latency_ms": 0.4,
           "compute_ms": 0.2}, {"type": "arrival", "t": 1.5, "robot": 0, "ptr": 1})


def _board(state: MissionState, **kw) -> C.Board:
    """A keyframe of ``state`` (``keyframe=False``: the stream header of the same version)."""
    legs = tuple((2, ((1, 0.25, 0.5, 0.0), (0, 0.1, 0.2, 3.5))) if a % 2 else None for a in range(state.A))
    d = dict(session="s1", version=7, rev=3, phase="decide", decider=state.agent, clock=float(state.clock),
             horizon=float(state.clock), n_done=int(state.n_done), n_cancelled=0, n_tasks=state.M, lost=(1, 3),
             legs=legs, state=state.snapshot(), events=EVENTS, digest="0123456789abcdef", until=float(state.clock),
             keyframe=True)
    d.update(kw)
    if not d["keyframe"]:
        d.update(legs=None, state=None, until=None)
    return C.Board(**d)


# ---------------------------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------------------------
def test_mission_round_trip():
    m = _mission()
    back = C.mission_from_msg(C.mission_to_msg(m))
    assert back.instance.to_dict() == INST.to_dict()
    assert (back.session, back.robots, back.seed, back.method, back.frame_id, back.scale, back.rules) == \
        (m.session, m.robots, m.seed, m.method, m.frame_id, m.scale, m.rules)
    assert back.rules == Rules(max_open="team", backdate=False)
    assert json.loads(C.mission_to_msg(m).data)["rules"] == {"max_open": "team", "safety": True, "backdate": False,
                                                              "t_max": None}
    # a Rules.to_dict() mapping is accepted in place of a Rules
    assert C.mission_to_msg(_mission(rules=RULES)).data == C.mission_to_msg(m).data
    assert back.index("r3") == 3 and back.index("nobody") is None


def test_mission_rules_are_required_and_checked():
    with pytest.raises(ValueError, match="Mission.rules is required"):
        C.mission_to_msg(_mission(rules=None))
    with pytest.raises(ValueError, match=r"Mission\.rules\.max_open: expected a positive integer"):
        C.mission_to_msg(_mission(rules={**RULES, "max_open": 0}))
    good = json.loads(C.mission_to_msg(_mission()).data)
    w = "hmrta-mission/1"
    for rules, reason in [(KeyError, f"{w}: missing field 'rules'"),
                          ("team", f"{w}.rules: expected dict"),
                          ({**RULES, "max_open": "teams"}, f"{w}.rules.max_open: expected a positive integer"),
                          ({**RULES, "safety": "yes"}, f"{w}.rules.safety: expected true or false"),
                          ({**RULES, "horizon": 5}, f"{w}.rules.horizon: unknown rule"),
                          ({k: v for k, v in RULES.items() if k != "t_max"}, f"{w}.rules: missing rule 't_max'")]:
        d = {k: v for k, v in good.items() if k != "rules"} if rules is KeyError else {**good, "rules": rules}
        with pytest.raises(C.DecodeError) as e:
            C.mission_from_msg(_msg(json.dumps(d)))
        assert str(e.value).startswith(reason), str(e.value)
        assert schema_errors("hmrta-mission/1", d)  # the published schema refuses it too


def test_board_round_trip_rebuilds_the_exact_state():
    state = _mid_state()
    b = _board(state)
    msg = C.board_to_msg(b)
    back = C.board_from_msg(msg)
    assert back.keyframe and back.header() == b.header() and back.prev == 6 and back.events == EVENTS
    assert back.until == b.until and back.digest == b.digest
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


def test_a_stream_header_is_one_line_with_the_versions_events():
    state = _mid_state()
    head = C.board_to_msg(_board(state, keyframe=False))
    assert "\n" not in head.data and "until" not in json.loads(head.data)
    back = C.board_from_msg(head)
    assert not back.keyframe and back.legs is None and back.state is None and back.until is None
    assert back.events == EVENTS and back.prev == 6 and back.digest == "0123456789abcdef"
    assert back.header() == {k: v for k, v in C.board_from_msg(C.board_to_msg(_board(state))).header().items()
                             if k != "until"}
    with pytest.raises(ValueError, match="a keyframe needs legs and state"):
        C.board_to_msg(dataclasses.replace(_board(state), legs=None))


def test_keyframe_requests_round_trip_and_validate():
    r = C.KeyframeRequest("s1", 41, "missed version(s) 42..42", "host:12")
    d = json.loads(C.keyframe_request_to_msg(r).data)
    assert_valid("hmrta-keyframe-request/1", d)
    assert C.keyframe_request_from_msg(C.keyframe_request_to_msg(r)) == r
    assert C.keyframe_request_from_msg(C.keyframe_request_to_msg(C.KeyframeRequest("s1", -1))).version == -1
    for bad in ({**d, "version": -2}, {**d, "version": "1"}, {k: v for k, v in d.items() if k != "session"}):
        with pytest.raises(C.DecodeError):
            C.keyframe_request_from_msg(_msg(json.dumps(bad)))
        assert schema_errors("hmrta-keyframe-request/1", bad)


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
    head = C.board_to_msg(_board(state, version=9, keyframe=False))
    assert dec.decode(head).version == 9 and dec.state(head) is None


def test_small_payload_round_trips():
    c = C.Choice("robot_1", "s1", 12, 3, seq=4, compute_ms=1.25)
    assert C.choice_from_msg(C.choice_to_msg(c)) == c
    s = C.Status(("robot_1", "robot_2"), "s1", 9, "host:1")
    assert C.status_from_msg(C.status_to_msg(s)) == s
    r = C.Rejection("masked", "node 3 is not admissible", "robot_1", 12)
    assert C.rejection_from_msg(C.rejection_to_msg(r)) == r
    sol = solve(INST, "greedy", 1).to_dict()
    assert C.result_from_msg(C.result_to_msg(sol)) == json.loads(json.dumps(sol))


# ---------------------------------------------------------------------------------------------
# every encoded message validates against its published schema
# ---------------------------------------------------------------------------------------------
def test_encoded_messages_validate_against_their_schemas():
    assert_valid("hmrta-mission/1", json.loads(C.mission_to_msg(_mission()).data))
    assert_valid("hmrta-mission/1", json.loads(C.mission_to_msg(_mission(rules=Rules(t_max=90.0))).data))
    for c in (C.Choice("robot_1", "s1", 12, 3, seq=4, compute_ms=1.25), C.Choice("r", "s", 0, 0)):
        assert_valid("hmrta-choice/1", json.loads(C.choice_to_msg(c).data))
    for s in (C.Status(("robot_1", "robot_2"), "s1", 9, "host:1"), C.Status((), "", 0)):
        assert_valid("hmrta-status/1", json.loads(C.status_to_msg(s).data))
    for r in (C.Rejection("masked", "node 3 is not admissible", "robot_1", 12), C.Rejection("malformed", "bad JSON")):
        assert_valid("hmrta-rejection/1", json.loads(C.rejection_to_msg(r).data))
    for reason in C.REJECTION_REASONS:
        assert reason in json.loads((SCHEMAS / "hmrta-rejection-1.schema.json").read_text())[
            "properties"]["reason"]["examples"]
    for method in ("greedy", "greedy-coalition"):
        assert_valid("hmrta-solution/1", json.loads(C.result_to_msg(solve(INST, method, 1).to_dict()).data))
    # every format the codec writes has its schema file
    assert {s["$id"] for s in _ALL} >= set(C.FORMATS)


@pytest.mark.parametrize("steps", [0, 5, 12, None])
def test_boards_validate_against_their_schemas(steps):
    """Header, legs and a real snapshot (start, mid-mission, finished) each validate."""
    state = MissionState(INST, seed=2, rules=GREEDY_RULES)
    n = 0
    while not state.done and (steps is None or n < steps):
        state.step(Greedy()(state))
        n += 1
    board = _board(state, phase="done" if state.done else "decide", lost=() if state.done else (1, 3))
    head, legs, snap = C.board_to_msg(board).data.split("\n")
    assert_valid("hmrta-board/2", json.loads(head))
    assert_valid("hmrta-board/2#/$defs/legs", json.loads(legs))
    assert_valid("hmrta-state/1", json.loads(snap))
    assert_valid("hmrta-board/2#/$defs/state", json.loads(snap))
    assert_valid("hmrta-board/2", json.loads(C.board_to_msg(dataclasses.replace(board, keyframe=False)).data))
    assert json.loads(snap)["done"] == (steps is None)


def test_signed_choices_and_statuses_validate():
    keys = pytest.importorskip("hmrta.keys")
    signer = keys.Signer({"robot_1": bytes(32), "robot_2": bytes(range(32))})
    choice = signer.sign(json.loads(C.choice_to_msg(C.Choice("robot_1", "s1", 12, 3)).data))
    status = signer.sign(json.loads(C.status_to_msg(C.Status(("robot_1", "robot_2"), "s1", 9)).data))
    assert "mac" in choice and "counter" in status
    assert_valid("hmrta-choice/1", choice)
    assert_valid("hmrta-status/1", status)
    assert C.choice_from_msg(_msg(json.dumps(choice))).node == 3  # readers ignore the signature fields


# ---------------------------------------------------------------------------------------------
# unknown formats and versions: DecodeError with the reason, per decoder
# ---------------------------------------------------------------------------------------------
def _encoded() -> dict[str, tuple[str, object]]:
    """format -> (encoded text, decoder)."""
    state = MissionState(INST, seed=2, rules=GREEDY_RULES)
    return {
        "hmrta-mission/1": (C.mission_to_msg(_mission()).data, C.mission_from_msg),
        "hmrta-choice/1": (C.choice_to_msg(C.Choice("robot_1", "s1", 12, 3)).data, C.choice_from_msg),
        "hmrta-status/1": (C.status_to_msg(C.Status(("robot_1",), "s1", 9)).data, C.status_from_msg),
        "hmrta-rejection/1": (C.rejection_to_msg(C.Rejection("stale", "old")).data, C.rejection_from_msg),
        "hmrta-solution/1": (C.result_to_msg(solve(INST, "greedy", 1).to_dict()).data, C.result_from_msg),
        "hmrta-board/2": (C.board_to_msg(_board(state)).data, C.board_from_msg),
        "hmrta-keyframe-request/1": (C.keyframe_request_to_msg(C.KeyframeRequest("s1", 3)).data,
                                     C.keyframe_request_from_msg),
    }


@pytest.mark.parametrize("fmt", ["hmrta-mission/1", "hmrta-choice/1", "hmrta-status/1", "hmrta-rejection/1",
                                 "hmrta-solution/1", "hmrta-board/2", "hmrta-keyframe-request/1"])
def test_decoders_reject_unknown_formats_and_versions_with_the_reason(fmt):
    text, decode = _encoded()[fmt]
    decode(_msg(text))  # the encoded message decodes
    name = fmt.rpartition("/")[0]
    first, sep, rest = text.partition("\n")  # a board's header is its first line
    d = json.loads(first)
    other = f"{name}/{int(fmt.rpartition('/')[2]) + 1}"
    cases = [({**d, "format": other}, f"{fmt}: unsupported version '{other}' (this build reads '{fmt}')"),
             ({**d, "format": f"{name}/0"}, f"{fmt}: unsupported version '{name}/0'"),
             ({**d, "format": "hmrta-other/1"}, f"expected format '{fmt}', got 'hmrta-other/1'"),
             ({**d, "format": 1}, f"expected format '{fmt}', got 1"),
             ({k: v for k, v in d.items() if k != "format"}, f"{fmt}: missing field 'format' (expected '{fmt}')"),
             ({**{k: v for k, v in d.items() if k != "format"}, "schema": fmt}, f"{fmt}: missing field 'format'")]
    for bad, reason in cases:
        with pytest.raises(C.DecodeError) as e:
            decode(_msg(json.dumps(bad) + sep + rest))
        assert str(e.value) == reason or str(e.value).startswith(reason), (str(e.value), reason)
        assert schema_errors(fmt, bad)  # and the published schema refuses it


def test_board_state_of_an_unknown_version_is_rejected():
    state = MissionState(INST, seed=2, rules=GREEDY_RULES)
    head, legs, snap = C.board_to_msg(_board(state)).data.split("\n")
    for fmt, reason in [("hmrta-state/2", "hmrta-board/2.state: hmrta-state/1: unsupported version 'hmrta-state/2'"),
                        ("hmrta-board/2", "hmrta-board/2.state: expected format 'hmrta-state/1', got 'hmrta-board/2'")]:
        msg = _msg("\n".join((head, legs, json.dumps({**json.loads(snap), "format": fmt}))))
        with pytest.raises(C.DecodeError, match="^" + reason.replace(".", r"\.").replace("(", r"\(")):
            C.board_from_msg(msg)
        dec = C.BoardDecoder()
        assert dec.decode(msg).version == 7  # the header alone still decodes
        with pytest.raises(C.DecodeError, match="unsupported version|expected format"):
            dec.state(msg)
    msg = _msg("\n".join((head, legs, json.dumps({k: v for k, v in json.loads(snap).items() if k != "format"}))))
    with pytest.raises(C.DecodeError, match="missing field 'format'"):
        C.board_from_msg(msg)


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

    assert topics.KEYFRAME_QOS.durability == DurabilityPolicy.TRANSIENT_LOCAL and topics.KEYFRAME_QOS.depth == 1
    assert topics.KEYFRAME_QOS.reliability == ReliabilityPolicy.RELIABLE
    # the stream: deep (a reader behind for a while loses nothing), volatile (no stale history)
    assert topics.BOARD_QOS.reliability == ReliabilityPolicy.RELIABLE and topics.BOARD_QOS.depth >= 1000
    assert topics.BOARD_QOS.durability == DurabilityPolicy.VOLATILE
    assert topics.CHOICE_QOS.reliability == ReliabilityPolicy.RELIABLE and topics.CHOICE_QOS.depth >= 50
    assert topics.robot_topic("robot_3", topics.POSE) == "/robot_3/pose"
    assert topics.robot_topic("/fleet/tb3/", topics.GOAL) == "/fleet/tb3/goal_pose"


# ---------------------------------------------------------------------------------------------
# malformed payloads: always DecodeError, never anything else
# ---------------------------------------------------------------------------------------------
GOOD_CHOICE = {"format": "hmrta-choice/1", "robot": "robot_1", "session": "s", "version": 3, "node": 1}
BAD_CHOICES = [
    "", "not json", "[1, 2]", "null", '"text"', "{}", '{"format": "hmrta-choice/2"}',
    json.dumps({**GOOD_CHOICE, "version": True}),
    json.dumps({**GOOD_CHOICE, "version": "3"}),
    json.dumps({**GOOD_CHOICE, "version": 3.0}),
    json.dumps({**GOOD_CHOICE, "node": None}),
    json.dumps({**GOOD_CHOICE, "robot": ""}),
    json.dumps({**GOOD_CHOICE, "robot": 7}),
    json.dumps({**GOOD_CHOICE, "compute_ms": "fast"}),
    json.dumps({k: v for k, v in GOOD_CHOICE.items() if k != "session"}),
    '{"format": "hmrta-choice/1", "robot": "r", "session": "s", "version": 1, "node": 1, "compute_ms": NaN}',
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
    for text in ["", "x", head + "\n" + legs, f"{head}\n[[1]]\n{snap}", f"{head}\n{legs}\n[1]",
                 f"{head}\n{legs}\n{{", good.replace('"phase":"decide"', '"phase":"dancing"'),
                 good.replace('"version":7', '"version":"7"'), f'{head}\n[[0,[[1,0,0]]]]\n{snap}',
                 f'{head}\n[[0,[[1,0.1,0.2,0.0]]]]\n{snap}', head.replace('"ev":[', '"ev":[1,'),
                 head.replace('"prev":6', '"prev":null'), good.replace(',"until":', ',"untill":'),
                 head.replace('"digest":"0123456789abcdef"', '"digest":7')]:
        with pytest.raises(C.DecodeError):
            C.board_from_msg(_msg(text))
    inst = INST.to_dict()
    bad_missions = [{"format": "hmrta-mission/1"},
                    {"format": "hmrta-mission/1", "session": "s", "instance": {**inst, "velocity": -1}, "robots": [],
                     "seed": 0, "method": "greedy", "frame_id": "map", "scale": 1.0},
                    {"format": "hmrta-mission/1", "session": "s", "instance": inst, "robots": ["a"] * INST.n_agents,
                     "seed": 0, "method": "greedy", "frame_id": "map", "scale": 1.0},
                    {"format": "hmrta-mission/1", "session": "s", "instance": inst,
                     "robots": [f"r{i}" for i in range(INST.n_agents)], "seed": 0, "method": "greedy",
                     "frame_id": "map", "scale": 0}]
    for d in bad_missions:
        with pytest.raises(C.DecodeError):
            C.mission_from_msg(_msg(json.dumps(d)))
    for d in [{"format": "hmrta-status/1", "robots": "robot_1", "session": "s", "seq": 1},
              {"format": "hmrta-status/1", "robots": [None], "session": "s", "seq": 1}]:
        with pytest.raises(C.DecodeError):
            C.status_from_msg(_msg(json.dumps(d)))
    with pytest.raises(C.DecodeError):
        C.result_from_msg(_msg('{"format": "hmrta-solution/0"}'))


JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
                    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=5),
                    max_leaves=12)
FIELDS = st.fixed_dictionaries({}, optional={"format": st.sampled_from(["hmrta-choice/1", "hmrta-status/1",
                                                                          "hmrta-board/2", "x"]),
                                             "robot": JSON, "robots": JSON, "session": JSON, "version": JSON,
                                             "node": JSON, "seq": JSON, "compute_ms": JSON, "phase": JSON})


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=40), JSON.map(json.dumps), FIELDS.map(json.dumps)))
def test_fuzzed_payloads_decode_or_raise_decode_error(text):
    for decode in (C.choice_from_msg, C.status_from_msg, C.board_from_msg, C.mission_from_msg,
                   C.rejection_from_msg, C.result_from_msg, C.keyframe_request_from_msg):
        try:
            decode(_msg(text))
        except C.DecodeError:
            pass


def test_goal_headings_round_trip():
    for yaw in (0.0, 1.0, -2.5, math.pi / 2, 3.1):
        msg = C.pose_to_msg((0.5, 0.25), 3.0, "map", 10.0, yaw)
        assert abs(math.remainder(C.yaw_from_msg(msg) - yaw, math.tau)) < 1e-12
        assert math.isclose(msg.pose.orientation.z ** 2 + msg.pose.orientation.w ** 2, 1.0)
    assert C.pose_to_msg((0.5, 0.25), 3.0).pose.orientation.w == 1.0 and C.yaw_from_msg(C.pose_to_msg((0, 0), 0)) == 0
    zero = C.pose_to_msg((0.5, 0.25), 3.0)
    zero.pose.orientation.w = 0.0  # an unset quaternion (all zeros): no heading
    assert C.yaw_from_msg(zero) is None


def test_statuses_carry_the_refusals_of_agents_that_stop():
    s = C.Status((), "s1", 4, "h:1", refused=(C.Refusal("robot_2", "robot_2: method random but ..."),))
    d = json.loads(C.status_to_msg(s).data)
    assert_valid("hmrta-status/1", d)
    assert C.status_from_msg(C.status_to_msg(s)) == s
    assert "refused" not in json.loads(C.status_to_msg(C.Status(("r",), "s", 1)).data)  # written only when some
    long = C.Status((), "s1", 5, refused=(C.Refusal("robot_2", "x" * 5000),))  # an agent's reason is cut, not refused
    assert C.status_from_msg(C.status_to_msg(long)).refused[0].why == "x" * C.REFUSAL_WHY_MAX
    signed = pytest.importorskip("hmrta.keys").Signer({"robot_2": bytes(32)}).sign(d)
    assert_valid("hmrta-status/1", signed)
    for bad, reason in [([{"robot": "x"}], "refused[0]: missing field 'why'"),
                        ([{"robot": "", "why": "w"}], "refused[0].robot: expected a non-empty robot name"),
                        ([{"robot": "x", "why": 3}], "refused[0].why: expected str"),
                        ([{"robot": "x", "why": "w" * 1001}], "refused[0].why: expected at most 1000 characters"),
                        (["x"], "refused[0]: expected an object"), ("x", "refused: expected list")]:
        with pytest.raises(C.DecodeError, match=re.escape(reason)):
            C.status_from_msg(_msg(json.dumps({**d, "refused": bad})))
        assert schema_errors("hmrta-status/1", {**d, "refused": bad})  # and the published schema refuses it


# ---------------------------------------------------------------------------------------------
# robots joining (status.joining, a grown mission) and operator requests matched by request_id
# ---------------------------------------------------------------------------------------------
def test_statuses_carry_robots_asking_to_join():
    s = C.Status(("robot_1",), "s1", 3, "h:1", joining=(C.Join("robot_new", 2), C.Join("scout", None, (1.0, 0.0, 2.0),
                                                                                        (0.25, 0.75))))
    d = json.loads(C.status_to_msg(s).data)
    assert_valid("hmrta-status/1", d)
    assert C.status_from_msg(C.status_to_msg(s)) == s
    assert "joining" not in json.loads(C.status_to_msg(C.Status(("r",), "s", 1)).data)  # written only when asked
    for bad, reason in [([{"robot": "x"}], "joining[0]: expected exactly one of species and traits"),
                        ([{"robot": "x", "species": -1}], "joining[0].species: expected a species index >= 0"),
                        ([{"robot": "", "species": 1}], "joining[0].robot: expected a non-empty robot name"),
                        ([{"robot": "x", "species": 1, "position": [0.5]}], "joining[0].position: expected [x, y]"),
                        (["x"], "joining[0]: expected an object")]:
        with pytest.raises(C.DecodeError, match=re.escape(reason)):
            C.status_from_msg(_msg(json.dumps({**d, "joining": bad})))
        assert schema_errors("hmrta-status/1", {**d, "joining": bad})


def test_a_grown_mission_round_trips_with_its_added_robots_once():
    state = _mid_state()
    state.add_agent(1)
    grown = dataclasses.replace(state.inst, tasks=INST.tasks, _cache={})
    m = _mission(instance=grown, robots=tuple(f"r{a}" for a in range(INST.n_agents + 1)))
    d = json.loads(C.mission_to_msg(m).data)
    assert_valid("hmrta-mission/1", d)
    back = C.mission_from_msg(C.mission_to_msg(m))
    assert back.instance.added_agents == (1,) and back.instance.n_agents == INST.n_agents + 1
    snap = json.loads(json.dumps(state.snapshot()))
    assert MissionState.from_snapshot(back.instance, snap).snapshot() == snap  # not counted twice
    with pytest.raises(C.DecodeError, match="robots: expected"):  # the robot list must grow with it
        C.mission_from_msg(C.mission_to_msg(_mission(instance=grown)))


def test_task_requests_and_events_carry_the_request_id():
    r = C.TaskRequest("add", "inspect-7", {"location": [0.3, 0.7], "requirements": [1, 0, 0], "duration": 1.0}, "n-1")
    d = json.loads(C.task_request_to_msg(r).data)
    assert d["request_id"] == "n-1" and C.task_request_from_msg(C.task_request_to_msg(r)) == r
    assert_valid("hmrta-task-request/1", d)
    old = C.TaskRequest("cancel", "inspect-7")  # a client without request ids
    assert "request_id" not in json.loads(C.task_request_to_msg(old).data)
    assert C.task_request_from_msg(C.task_request_to_msg(old)).request_id == ""
    e = C.TaskEvent("inspect-7", "rejected", 1.5, None, "exists already", "add", "n-1")
    d = json.loads(C.task_event_to_msg(e).data)
    assert d["request_id"] == "n-1" and C.task_event_from_msg(C.task_event_to_msg(e)) == e
    assert_valid("hmrta-task-event/1", d)
    with pytest.raises(C.DecodeError, match="request_id: expected str"):
        C.task_request_from_msg(_msg(json.dumps({**json.loads(C.task_request_to_msg(r).data), "request_id": 5})))
    for bad in ("a\nb", "x\x1b[31m", "\x85"):  # ids are printed in logs and on consoles: one line
        msg = C.task_request_to_msg(C.TaskRequest("cancel", bad))
        with pytest.raises(C.DecodeError, match="id: expected an id on one line, got a control character"):
            C.task_request_from_msg(msg)
        assert any("id" in e for e in schema_errors("hmrta-task-request/1", json.loads(msg.data)))  # the schema too
    assert C.request_id_of('{"format": "hmrta-task-request/1", "op": "move", "request_id": "n-2"}') == "n-2"
    assert C.request_id_of("not json") == "" and C.request_id_of('{"request_id": 3}') == ""


def test_a_huge_received_value_is_quoted_on_one_short_line():
    """A hostile value (a 100,000-character robot name, host or phase) is refused with a reason
    of one short line: the board logs and publishes reasons."""
    huge = "x" * 100_000
    for d in ({"robots": [huge]}, {"robots": ["robot_0"], "host": huge}, {"robots": [["a" * 5000]]}):
        msg = String(data=json.dumps({"format": "hmrta-status/1", "session": "s", "seq": 1, **d}))
        with pytest.raises(C.DecodeError) as e:
            C.status_from_msg(msg)
        assert len(str(e.value)) < 300 and "\n" not in str(e.value), str(e.value)[:400]
