"""Recording missions to MCAP: ``hmrta-mission --record`` and the ``recorder`` executable, read
back with ``hmrta.replay`` (same routes as the result and the offline rollout) and drawn with
``hmrta render --from``."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("mcap_ros2")
rclpy = pytest.importorskip("rclpy")
from mcap.reader import make_reader  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from hmrta.cli import main as cli_main  # noqa: E402
from hmrta.formats import load_instance  # noqa: E402
from hmrta.methods import solve  # noqa: E402
from hmrta.replay import read_recording  # noqa: E402
from hmrta_coordinator.mission import default_instance  # noqa: E402
from hmrta_coordinator.recorder import HEARD  # noqa: E402
from hmrta_msgs_py import topics  # noqa: E402

BIN = Path(sys.executable).parent


def _env(domain: int, tmp_path: Path) -> dict[str, str]:
    return dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain),
                ROS_LOG_DIR=str(tmp_path / "ros_logs"))


def test_recorded_sim_mission_reads_back_with_the_same_routes(tmp_path, domain):
    out, rec_file, seed = tmp_path / "mission.json", tmp_path / "mission.mcap", 1
    r = subprocess.run([str(BIN / "hmrta-mission"), "--method", "greedy", "--seed", str(seed), "--out", str(out),
                        "--no-plot", "--quiet", "--agents-per-process", "15", "--timeout", "150",
                        # paced: volatile messages (choices, goals) sent before the recorder has
                        # discovered their publishers are not recorded, and an unpaced mission can
                        # be over within the 1-2 s that discovery takes on a loaded machine
                        "--time-scale", "5",
                        "--domain-id", str(domain), "--record", str(rec_file)],
                       capture_output=True, text=True, timeout=200, env=_env(domain, tmp_path), cwd=tmp_path)
    assert r.returncode == 0, f"mission exited {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    assert f"wrote {rec_file}" in r.stdout and not Path(str(rec_file) + ".part").exists()
    result = json.loads(out.read_text())
    inst = load_instance(default_instance())
    rec = read_recording(rec_file)
    assert rec.instance.to_dict() == inst.to_dict() and rec.plan_source == "result"
    assert rec.routes == result["routes"] == solve(inst, "greedy", seed).routes
    assert rec.plan.makespan == result["makespan"]
    # every mission topic and every robot's goals and poses, with messages
    robots = [f"robot_{a}" for a in range(inst.n_agents)]
    expected = {topics.MISSION, topics.BOARD, topics.KEYFRAME, topics.CHOICE, topics.RESULT, topics.CLOCK}
    expected |= {topics.robot_topic(r, leaf) for r in robots for leaf in (topics.GOAL, topics.POSE)}
    missing = sorted(expected - {t for t, n in rec.counts.items() if n > 0})
    assert not missing, f"not recorded: {missing}; recorded {rec.counts}"
    assert rec.counts[topics.MISSION] == 1 and rec.counts[topics.RESULT] == 1
    # volatile topics (choices, goals, poses) published before the recorder matched their
    # publishers can be missed on a loaded machine: only presence is guaranteed
    assert rec.counts[topics.CHOICE] <= sum(map(len, result["routes"])) + 10 * inst.n_agents
    # the executed mission: every planned visit seen in the poses, in the planned order
    visits = rec.visits()
    assert [[v["task"] for v in rows] for rows in visits] == result["routes"]
    arrivals = [v for rows in visits for v in rows]
    # every visit seen in the poses (how close actual times come to planned ones depends on how
    # the replay maps receive times onto the paced mission clock, which varies with the load)
    assert all(v["actual_arrival"] is not None for v in arrivals), arrivals
    # a standard ROS 2 MCAP: ros2 profile, CDR messages, ros2msg schemas
    with open(rec_file, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {s.name for s in summary.schemas.values()} >= {"std_msgs/msg/String", "geometry_msgs/msg/PoseStamped",
                                                             "rosgraph_msgs/msg/Clock"}
    png = tmp_path / "replay.png"
    assert cli_main(["render", "--from", str(rec_file), "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000


def test_recorder_executable_gets_latched_topics_and_finishes_on_sigterm(tmp_path, graph):
    """Started after the mission was published (latched: it still gets it), follows the robots
    the mission names, and on SIGTERM finishes and renames its file.

    The pose (recorded best effort) is lost if sent before the recorder's reader has matched
    its publisher: the publishers come before the mission's, so that the recorder, once it has
    heard the mission (its line), has discovered them too (a node's endpoints are announced in
    order), and its pose reader, made as it reads the mission, matches at once. The choices are
    reliable: acknowledged, they are in the recorder's reader before the SIGTERM, and a stopped
    recorder records what its readers hold before it closes the file (``spin_nodes(drain=...)``)."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.duration import Duration

    node = graph.node("publisher")
    pose_pub = node.create_publisher(PoseStamped, "/bot_a/pose", topics.POSE_PUB_QOS)
    choice_pub = node.create_publisher(String, topics.CHOICE, topics.CHOICE_QOS)
    mission_pub = node.create_publisher(String, topics.MISSION, topics.MISSION_QOS)
    mission_pub.publish(String(data=json.dumps({"format": "hmrta-mission/1", "robots": ["bot_a"]})))
    out, log = tmp_path / "rec" / "run.mcap", tmp_path / "recorder.log"
    with open(log, "w") as fh:
        proc = subprocess.Popen([str(BIN / "recorder"), "--ros-args", "-p", f"output:={out}",
                                 "-p", "discovery_period:=0.2"],
                                stdout=fh, stderr=subprocess.STDOUT, env=_env(graph.domain, tmp_path),
                                start_new_session=True)
    try:
        graph.spin_until(lambda: HEARD in log.read_text() or proc.poll() is not None, 60,
                         "the recorder to hear the mission")
        assert proc.poll() is None, log.read_text()
        graph.spin_until(lambda: pose_pub.get_subscription_count() > 0 and choice_pub.get_subscription_count() > 0,
                         60, "the recorder to subscribe to the mission's robot and the choices")
        for i in range(5):
            choice_pub.publish(String(data=f"c{i}"))
            msg = PoseStamped()
            msg.pose.position.x = float(i)
            pose_pub.publish(msg)
            graph.executor.spin_once(timeout_sec=0.05)
        assert choice_pub.wait_for_all_acked(Duration(seconds=30)), "the recorder did not acknowledge the choices"
        assert Path(str(out) + ".part").exists() and not out.exists()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    text = log.read_text()
    assert proc.returncode in (0, -signal.SIGTERM), text
    assert out.exists() and not Path(str(out) + ".part").exists(), text
    with open(out, "rb") as f:
        s = make_reader(f).get_summary()
    counts = {c.topic: s.statistics.channel_message_counts.get(i, 0) for i, c in s.channels.items()}
    assert counts == {topics.MISSION: 1, topics.CHOICE: 5, "/bot_a/pose": 5}, counts
    # beside it, the recorded topics' QoS as rosbag2's overrides: a playback offers the latched
    # mission transient local, as the board does (else the nodes' latched subscribers never match)
    import yaml

    qos = yaml.safe_load((tmp_path / "rec" / "run.qos.yaml").read_text())
    assert set(qos) == set(counts)
    assert qos[topics.MISSION] == {"history": "keep_last", "depth": 1, "reliability": "reliable",
                                   "durability": "transient_local"}
    assert qos[topics.CHOICE]["durability"] == "volatile" and qos[topics.CHOICE]["reliability"] == "reliable"
    assert qos["/bot_a/pose"]["reliability"] == "best_effort"
    assert "run.qos.yaml" in text and not list((tmp_path / "rec").glob("*.part"))


def test_recorder_help_and_bad_compression(tmp_path, domain):
    r = subprocess.run([str(BIN / "recorder"), "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "output (string" in r.stdout
    r = subprocess.run([str(BIN / "recorder"), "--ros-args", "-p", f"output:={tmp_path / 'x.mcap'}",
                        "-p", "compression:=gzip"], capture_output=True, text=True, timeout=60,
                       env=_env(domain, tmp_path))
    assert r.returncode == 2 and "compression: expected one of zstd, lz4, none" in r.stderr
    assert not list(tmp_path.glob("x.mcap*"))


def test_the_recorder_takes_its_own_missions_topics_by_name_not_by_prefix():
    """A recorder of the root mission does not take the topics of a mission whose namespace is
    /hmrta (/hmrta/hmrta/board, /hmrta/robot_0/pose): the recording would hold two missions."""
    from types import SimpleNamespace

    from hmrta_coordinator.recorder import Recorder, known_topics

    rec = SimpleNamespace(extra=["/tf"], known=set(known_topics(False)), robot_names=["robot_0"],
                          topics=topics.MissionTopics())
    wanted = {n for n in ("/hmrta/board", "/hmrta/clock", "/robot_0/pose", "/tf", "/hmrta/hmrta/board",
                          "/hmrta/markers", "/hmrta/robot_0/pose", "/hmrta/other") if Recorder._wanted(rec, n)}
    assert wanted == {"/hmrta/board", "/hmrta/clock", "/robot_0/pose", "/tf"}
