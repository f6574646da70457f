"""Topic names and QoS profiles, declared once for every HMRTA node.

Mission-wide topics are absolute (``/hmrta/...``) so that nodes in robot namespaces share them;
per-robot topics are relative names resolved in the robot's namespace (``/<robot>/goal_pose``,
``/<robot>/pose``), so a real robot is integrated by namespace or by remapping.
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# ---- mission-wide topics ------------------------------------------------------------------------
MISSION = "/hmrta/mission"  # std_msgs/String hmrta-mission/1       board -> all (latched)
BOARD = "/hmrta/board"  # std_msgs/String hmrta-board/2 header per version (events)  board -> all
KEYFRAME = "/hmrta/board_keyframe"  # std_msgs/String hmrta-board/2 keyframe: header, legs, state  (latched)
KEYFRAME_REQUESTS = "/hmrta/keyframe_requests"  # std_msgs/String hmrta-keyframe-request/1  replicas -> board
CHOICE = "/hmrta/choice"  # std_msgs/String hmrta-choice/1          agents -> board
STATUS = "/hmrta/agent_status"  # std_msgs/String hmrta-status/1    agents -> board (heartbeat)
REJECTIONS = "/hmrta/rejections"  # std_msgs/String hmrta-rejection/1  board -> anyone
RESULT = "/hmrta/result"  # std_msgs/String hmrta-solution/1        board -> all (latched)
MARKERS = "/hmrta/markers"  # visualization_msgs/MarkerArray        board -> RViz
TASK_REQUESTS = "/hmrta/task_requests"  # std_msgs/String hmrta-task-request/1  operators -> board
TASK_EVENTS = "/hmrta/task_events"  # std_msgs/String hmrta-task-event/1  board -> operators
# the mission clock (sim_robot -> all; ``clock_topic`` parameter): inside the /hmrta namespace, so
# another node's /clock (a simulator such as Gazebo) never moves a mission
CLOCK = "/hmrta/clock"  # rosgraph_msgs/Clock (check_clock_topic: what may name it)

# ---- per-robot topics (relative: resolved in the robot's namespace) -----------------------------
GOAL = "goal_pose"  # geometry_msgs/PoseStamped  agent -> robot driver (Nav2's goal topic)
POSE = "pose"  # robot driver -> board (position): geometry_msgs/PoseStamped (default),
# geometry_msgs/PoseWithCovarianceStamped (amcl_pose) or nav_msgs/Odometry (the board's pose_type)


def robot_topic(robot: str, leaf: str) -> str:
    """Absolute per-robot topic, e.g. robot_topic('robot_3', POSE) -> '/robot_3/pose'."""
    return f"/{robot.strip('/')}/{leaf}"


def _qos(depth: int, reliable: bool = True, latched: bool = False) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


# keyframe, mission and result: reliable + transient local, depth 1 (late joiners get the latest)
LATCHED_QOS = _qos(1, latched=True)
KEYFRAME_QOS = MISSION_QOS = RESULT_QOS = LATCHED_QOS
# the board stream: every version in order, reliable with a deep history, so that a reader that
# falls behind for a while loses nothing (a version it still misses is a gap: it asks for a
# keyframe). Volatile: a late reader gets no history it could mistake for the present; it starts
# from the latched keyframe, and an idle board streams its latest header again every 0.25 s
BOARD_QOS = _qos(1000)
# sim_robot reads the stream for the latest horizon only (it moves the clock there; once in step
# it applies no events): best effort spares the board a reliable reader on the path of every
# decision. A version it misses is made up by the next one, or by the repeat 0.25 s later
BOARD_SIM_QOS = _qos(1000, reliable=False)
KEYFRAME_REQUEST_QOS = _qos(100)
# choices: reliable, deeper queue (a burst of agents must not lose any)
CHOICE_QOS = _qos(100)
STATUS_QOS = _qos(50)
REJECTION_QOS = _qos(100)
MARKER_QOS = _qos(1, latched=True)
TASK_REQUEST_QOS = _qos(100)
TASK_EVENT_QOS = _qos(100, latched=True)  # a late operator gets the latest answers
CLOCK_QOS = _qos(1, latched=True)  # a late subscriber gets the current time at once
GOAL_QOS = _qos(10)
# poses are published reliably; the board subscribes best effort so that any robot driver
# (sensor-data QoS included) can feed it; poses repeat as heartbeats, so a lost sample only delays
POSE_PUB_QOS = _qos(10)
POSE_SUB_QOS = _qos(10, reliable=False)
# amcl_pose (PoseWithCovarianceStamped) is published reliable + transient local and only on filter
# updates: subscribed the same way, a robot standing still is seen at once from its latest pose
AMCL_POSE_SUB_QOS = _qos(1, latched=True)
POSE_SUB_QOS_BY_TYPE = {"PoseStamped": POSE_SUB_QOS, "PoseWithCovarianceStamped": AMCL_POSE_SUB_QOS,
                        "Odometry": POSE_SUB_QOS}


def check_root_namespace(node, what: str) -> None:
    """A ValueError unless ``node`` (the task board, sim_robot) runs in the root namespace: the
    mission's topics are absolute, so a namespace (``-r __ns:=/fleet1``) would not separate its
    mission from another on the same ROS domain; each mission needs its own ROS_DOMAIN_ID."""
    ns = node.get_namespace()
    if ns != "/":
        raise ValueError(f"namespace {ns}: {what} takes no namespace (the mission's topics are absolute: /hmrta/..., "
                         f"/<robot>/pose; a namespace would not keep this mission apart from another on the same "
                         f"ROS domain): run each mission on its own ROS_DOMAIN_ID (docs/ros.md, Several machines)")


def check_clock_topic(name: str, what: str = "clock_topic") -> str:
    """``name`` if it can name the mission clock (an absolute, valid topic other than /clock, a
    simulator's); else a ValueError naming ``what`` (the nodes' parameter, ``hmrta-task``'s option)."""
    if not isinstance(name, str) or not name.startswith("/") or name.rstrip("/") == "/clock":
        raise ValueError(f"{what}: expected an absolute topic other than /clock, got {name!r}")
    from rclpy.validate_topic_name import validate_topic_name

    try:
        validate_topic_name(name)
    except Exception as e:  # noqa: BLE001 - rclpy's InvalidTopicNameException: its first line says why
        raise ValueError(f"{what}: {name!r} is not a topic name ({str(e).splitlines()[0]})") from None
    return name
