"""The topics table of docs/ros.md is kept true: every topic hmrta_msgs_py.topics names has a row
with its QoS as the code sets it, and the table names no other topic."""
from __future__ import annotations

import re
from pathlib import Path

from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

from hmrta_msgs_py import topics

DOC = Path(__file__).resolve().parents[2] / "docs" / "ros.md"


def _rows() -> dict[str, list[str]]:
    text = DOC.read_text()
    table = text[text.index("## Topics"):].split("\n## ", 1)[0]
    rows = {}
    for line in table.splitlines():
        m = re.match(r"\| `([^`]+)`", line)
        if m:
            rows[m.group(1)] = [c.strip() for c in line.strip().strip("|").split("|")]
    return rows


def _qos_text(q) -> str:
    rel = "reliable" if q.reliability == ReliabilityPolicy.RELIABLE else "best effort"
    dur = ", transient local" if q.durability == DurabilityPolicy.TRANSIENT_LOCAL else ""
    return f"{rel}{dur}, depth {q.depth}"


def test_every_topic_has_a_row_with_its_qos_and_no_other_rows():
    rows = _rows()
    named = {
        topics.MISSION: topics.MISSION_QOS, topics.BOARD: topics.BOARD_QOS, topics.KEYFRAME: topics.KEYFRAME_QOS,
        topics.KEYFRAME_REQUESTS: topics.KEYFRAME_REQUEST_QOS, topics.CHOICE: topics.CHOICE_QOS,
        topics.STATUS: topics.STATUS_QOS, topics.REJECTIONS: topics.REJECTION_QOS, topics.RESULT: topics.RESULT_QOS,
        topics.MARKERS: topics.MARKER_QOS, topics.CLOCK: topics.CLOCK_QOS,
        topics.TASK_REQUESTS: topics.TASK_REQUEST_QOS, topics.TASK_EVENTS: topics.TASK_EVENT_QOS,
        topics.robot_topic("<robot>", topics.GOAL): topics.GOAL_QOS,
    }
    seen = {name: next((k for k in rows if k == name or k.startswith(name + " ")), None) for name in named}
    missing = [n for n, k in seen.items() if k is None]
    assert not missing, f"docs/ros.md topics table lacks {missing}"
    for name, q in named.items():
        assert rows[seen[name]][2] == _qos_text(q), f"{name}: the table says {rows[seen[name]][2]!r}"
    pose = topics.robot_topic("<robot>", topics.POSE)
    assert pose in rows and all(t in rows[pose][1] for t in topics.POSE_SUB_QOS_BY_TYPE)
    extra = set(rows) - set(seen.values()) - {pose}
    assert not extra, f"docs/ros.md topics table names topics the code does not: {sorted(extra)}"
