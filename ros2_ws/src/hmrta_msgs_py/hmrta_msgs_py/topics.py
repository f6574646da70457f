"""Topic names and QoS profiles, declared once for every HMRTA node.

A mission lives in a *mission namespace* (every node's ``mission_namespace`` parameter, default
``/``): its mission-wide topics are ``<ns>/hmrta/...`` (:class:`MissionTopics`), absolute so that
nodes in robot namespaces share them, and its robots' topics are ``<ns>/<robot>/goal_pose`` and
``<ns>/<robot>/pose`` (:func:`robot_topic`); an agent publishes its goals on the relative name
``goal_pose``, resolved in the robot's namespace, so a real robot is integrated by namespace or by
remapping. Two missions on one ROS domain run in two mission namespaces (docs/ros.md).
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

ROOT = "/"  # the default mission namespace: /hmrta/..., /<robot>/pose

# ---- mission-wide topics: <mission namespace>/hmrta/<leaf> (MissionTopics) ---------------------
LEAVES = {  # MissionTopics attribute: leaf
    "mission": "mission",  # std_msgs/String hmrta-mission/1                 board -> all (latched)
    "board": "board",  # std_msgs/String hmrta-board/2 header per version (events)  board -> all
    "keyframe": "board_keyframe",  # std_msgs/String hmrta-board/2 keyframe: header, legs, state (latched)
    "keyframe_requests": "keyframe_requests",  # std_msgs/String hmrta-keyframe-request/1  replicas -> board
    "choice": "choice",  # std_msgs/String hmrta-choice/1                      agents -> board
    "status": "agent_status",  # std_msgs/String hmrta-status/1                agents -> board (heartbeat)
    "rejections": "rejections",  # std_msgs/String hmrta-rejection/1           board -> anyone
    "result": "result",  # std_msgs/String hmrta-solution/1                    board -> all (latched)
    "markers": "markers",  # visualization_msgs/MarkerArray                    board -> RViz
    "task_requests": "task_requests",  # std_msgs/String hmrta-task-request/1  operators -> board
    "task_events": "task_events",  # std_msgs/String hmrta-task-event/1        board -> operators
    # the mission clock (sim_robot -> all; the default of the nodes' ``clock_topic``): inside the
    # mission's hmrta namespace, so another node's /clock (a simulator such as Gazebo) never moves a
    # mission (check_clock_topic: what may name it)
    "clock": "clock",  # rosgraph_msgs/Clock
}

# ---- per-robot topics (relative: resolved in the robot's namespace) -----------------------------
GOAL = "goal_pose"  # geometry_msgs/PoseStamped  agent -> robot driver (Nav2's goal topic)
POSE = "pose"  # robot driver -> board (position): geometry_msgs/PoseStamped (default),
# geometry_msgs/PoseWithCovarianceStamped (amcl_pose) or nav_msgs/Odometry (the board's pose_type)


def robot_namespace(robot: str, namespace: str = ROOT) -> str:
    """A robot's namespace in a mission namespace: robot_namespace('robot_3', '/fleet1') ->
    '/fleet1/robot_3' (where its agent runs and the board and sim_robot expect its topics)."""
    return f"{namespace.rstrip('/')}/{robot.strip('/')}"


def robot_topic(robot: str, leaf: str, namespace: str = ROOT) -> str:
    """Absolute per-robot topic in a mission namespace, e.g. robot_topic('robot_3', POSE) ->
    '/robot_3/pose', robot_topic('robot_3', POSE, '/fleet1') -> '/fleet1/robot_3/pose'."""
    return f"{robot_namespace(robot, namespace)}/{leaf}"


def check_mission_namespace(ns: object, what: str = "mission_namespace") -> str:
    """``ns`` as a mission namespace ('/' or '/a/b', no trailing slash), or a ValueError naming
    ``what`` (the nodes' parameter, a command's option) that says what was expected."""
    want = "an absolute ROS namespace such as / or /fleet1"
    if not isinstance(ns, str) or not ns.startswith("/"):
        raise ValueError(f"{what}: expected {want}, got {ns!r}")
    if "//" in ns:
        raise ValueError(f"{what}: expected {want}, got {ns!r} (a namespace has no empty token: no '//')")
    norm = "/" + ns.strip("/")
    if norm != "/":
        from rclpy.validate_namespace import validate_namespace

        try:
            validate_namespace(norm)
        except Exception as e:  # noqa: BLE001 - rclpy's InvalidNamespaceException: its first line says why
            raise ValueError(f"{what}: expected {want}, got {ns!r} ({str(e).splitlines()[0].rstrip(':')})") from None
    return norm


class MissionTopics:
    """The mission-wide topic names of one mission namespace, one attribute per entry of
    :data:`LEAVES` (``MissionTopics('/fleet1').board`` is '/fleet1/hmrta/board'); the module's
    constants (``BOARD``, ...) are those of the root namespace."""

    mission: str
    board: str
    keyframe: str
    keyframe_requests: str
    choice: str
    status: str
    rejections: str
    result: str
    markers: str
    task_requests: str
    task_events: str
    clock: str

    def __init__(self, namespace: str = ROOT):
        self.namespace = namespace
        for attr, leaf in LEAVES.items():
            setattr(self, attr, f"{namespace.rstrip('/')}/hmrta/{leaf}")

    def __repr__(self) -> str:
        return f"MissionTopics({self.namespace!r})"

    def robot(self, robot: str, leaf: str) -> str:
        """A robot's topic in this mission namespace (:func:`robot_topic`)."""
        return robot_topic(robot, leaf, self.namespace)

    def clock_topic(self, given: str, what: str = "clock_topic") -> str:
        """The mission clock topic: ``given`` (checked by :func:`check_clock_topic`) or, when
        empty, this namespace's ``<ns>/hmrta/clock``."""
        return check_clock_topic(given, what) if given else self.clock


def mission_topics(namespace: object, what: str = "mission_namespace") -> MissionTopics:
    """The topics of the mission in ``namespace`` (a node's ``mission_namespace`` parameter),
    checked by :func:`check_mission_namespace` (ValueError naming ``what``)."""
    return MissionTopics(check_mission_namespace(namespace, what))


_ROOT_TOPICS = MissionTopics()  # the root namespace's names, as constants
MISSION, BOARD, KEYFRAME = _ROOT_TOPICS.mission, _ROOT_TOPICS.board, _ROOT_TOPICS.keyframe
KEYFRAME_REQUESTS, CHOICE, STATUS = _ROOT_TOPICS.keyframe_requests, _ROOT_TOPICS.choice, _ROOT_TOPICS.status
REJECTIONS, RESULT, MARKERS = _ROOT_TOPICS.rejections, _ROOT_TOPICS.result, _ROOT_TOPICS.markers
TASK_REQUESTS, TASK_EVENTS, CLOCK = _ROOT_TOPICS.task_requests, _ROOT_TOPICS.task_events, _ROOT_TOPICS.clock


def qos(depth: int, reliable: bool = True, latched: bool = False) -> QoSProfile:
    """KEEP_LAST ``depth``; reliable or best effort; transient local (``latched``) or volatile."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


# keyframe, mission and result: reliable + transient local, depth 1 (late joiners get the latest)
LATCHED_QOS = qos(1, latched=True)
KEYFRAME_QOS = MISSION_QOS = RESULT_QOS = LATCHED_QOS
# a mission reader keeps every mission message that arrives before it runs: two boards' latched
# missions in one mission namespace (the later-created one gives way: both must be heard), or
# another board's and its own, which reach a board that matched the other's publisher while it
# was still starting (a portfolio's simulation) at the same moment; depth 1 kept only the last
MISSION_SUB_QOS = qos(10, latched=True)
# the board stream: every version in order, reliable with a deep history, so that a reader that
# falls behind for a while loses nothing (a version it still misses is a gap: it asks for a
# keyframe). Volatile: a late reader gets no history it could mistake for the present; it starts
# from the latched keyframe, and an idle board streams its latest header again every 0.25 s
BOARD_QOS = qos(1000)
# sim_robot reads the stream for the latest horizon only (it moves the clock there; once in step
# it applies no events): best effort spares the board a reliable reader on the path of every
# decision. A version it misses is made up by the next one, or by the repeat 0.25 s later
BOARD_SIM_QOS = qos(1000, reliable=False)
KEYFRAME_REQUEST_QOS = qos(100)
# choices: reliable, deeper queue (a burst of agents must not lose any)
CHOICE_QOS = qos(100)
STATUS_QOS = qos(50)
REJECTION_QOS = qos(100)
MARKER_QOS = qos(1, latched=True)
TASK_REQUEST_QOS = qos(100)
TASK_EVENT_QOS = qos(100, latched=True)  # a late operator gets the latest answers
CLOCK_QOS = qos(1, latched=True)  # a late subscriber gets the current time at once
GOAL_QOS = qos(10)
# poses are published reliably; the board subscribes best effort so that any robot driver
# (sensor-data QoS included) can feed it; poses repeat as heartbeats, so a lost sample only delays
POSE_PUB_QOS = qos(10)
POSE_SUB_QOS = qos(10, reliable=False)
# amcl_pose (PoseWithCovarianceStamped) is published reliable + transient local and only on filter
# updates: subscribed the same way, a robot standing still is seen at once from its latest pose
AMCL_POSE_SUB_QOS = qos(1, latched=True)
POSE_SUB_QOS_BY_TYPE = {"PoseStamped": POSE_SUB_QOS, "PoseWithCovarianceStamped": AMCL_POSE_SUB_QOS,
                        "Odometry": POSE_SUB_QOS}


def check_root_namespace(node, what: str) -> None:
    """A ValueError unless ``node`` (the task board, sim_robot) runs in the root namespace: the
    mission's topics are absolute names in its *mission* namespace, so a node namespace
    (``-r __ns:=/fleet1``) would not move them; ``-p mission_namespace:=/fleet1`` does."""
    ns = node.get_namespace()
    if ns != "/":
        raise ValueError(f"namespace {ns}: {what} takes no node namespace (the mission's topics are absolute names "
                         f"in its mission namespace: <ns>/hmrta/..., <ns>/<robot>/pose): to keep this mission apart "
                         f"from another on the same ROS domain, leave -r __ns:= out and give every node of the mission "
                         f"-p mission_namespace:={ns} (docs/ros.md, Several missions on one ROS domain)")


def check_robot_name(name: str, what: str = "robot") -> str:
    """``name`` if it can name a robot's topics (``<ns>/<name>/pose``, ``goal_pose``); else a
    ValueError naming ``what`` (the node's parameter)."""
    from rclpy.validate_topic_name import validate_topic_name

    try:
        validate_topic_name(f"/{name}/pose")
    except Exception:  # noqa: BLE001 - rclpy's InvalidTopicNameException
        raise ValueError(f"{what}: {name!r} is not a robot name (a ROS name: letters, digits and '_', not "
                         f"starting with a digit)") from None
    return name


def _valid_topic(name: str, what: str) -> str:
    """``name`` if rclpy takes it as a topic name; else a ValueError naming ``what`` with rclpy's reason."""
    from rclpy.validate_topic_name import validate_topic_name

    try:
        validate_topic_name(name)
    except Exception as e:  # noqa: BLE001 - rclpy's InvalidTopicNameException: its first line says why
        raise ValueError(f"{what}: {name!r} is not a topic name ({str(e).splitlines()[0]})") from None
    return name


def check_absolute_topic(name: str, what: str) -> str:
    """``name`` if it is an absolute topic name as the ROS graph lists topics (``/ns/name``); else
    a ValueError naming ``what`` (a node's parameter)."""
    if not isinstance(name, str) or not name.startswith("/") or "//" in name or name.endswith("/"):
        raise ValueError(f"{what}: expected absolute topic names such as /scan, got {name!r}")
    return _valid_topic(name, what)


def check_clock_topic(name: str, what: str = "clock_topic") -> str:
    """``name`` if it can name the mission clock (an absolute, valid topic other than /clock, a
    simulator's); else a ValueError naming ``what`` (the nodes' parameter, ``hmrta-task``'s option)."""
    if not isinstance(name, str) or not name.startswith("/") or name.rstrip("/") == "/clock":
        raise ValueError(f"{what}: expected an absolute topic other than /clock, got {name!r}")
    return _valid_topic(name, what)
