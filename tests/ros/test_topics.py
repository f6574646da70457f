"""Topic names of a mission namespace (hmrta_msgs_py.topics): the root namespace gives the
documented names, a namespace prefixes every mission topic and every robot topic, and a value
that is no namespace is refused with the parameter's name."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy")
from hmrta_msgs_py import topics  # noqa: E402


def test_the_root_namespace_gives_the_documented_names():
    t = topics.MissionTopics()
    assert (t.mission, t.board, t.keyframe, t.choice, t.status, t.clock) == (
        topics.MISSION, topics.BOARD, topics.KEYFRAME, topics.CHOICE, topics.STATUS, topics.CLOCK)
    assert topics.BOARD == "/hmrta/board" and topics.STATUS == "/hmrta/agent_status"
    assert topics.robot_topic("robot_3", topics.POSE) == "/robot_3/pose" == t.robot("robot_3", topics.POSE)


def test_a_namespace_prefixes_every_mission_and_robot_topic():
    t = topics.mission_topics("/fleet1/")
    assert t.namespace == "/fleet1"
    names = [getattr(t, a) for a in topics.LEAVES]
    assert len(set(names)) == len(topics.LEAVES) and all(n.startswith("/fleet1/hmrta/") for n in names)
    assert t.robot("robot_3", topics.GOAL) == "/fleet1/robot_3/goal_pose"
    assert topics.mission_topics("/a/b").board == "/a/b/hmrta/board"
    assert t.clock_topic("") == "/fleet1/hmrta/clock" and t.clock_topic("/sim/clock") == "/sim/clock"
    with pytest.raises(ValueError, match="clock_topic: expected an absolute topic other than /clock"):
        t.clock_topic("/clock")


@pytest.mark.parametrize("bad", ["fleet1", "", "/fleet 1", "/1fleet", "/a//b", "//", 7])
def test_what_is_no_namespace_is_refused_naming_the_parameter(bad):
    with pytest.raises(ValueError, match=r"^mission_namespace: expected an absolute ROS namespace such as / or /fleet1, "):
        topics.mission_topics(bad)
    with pytest.raises(ValueError, match=r"^--mission-namespace: expected"):
        topics.check_mission_namespace(bad, "--mission-namespace")
