"""The ROS parameters of every HMRTA node, in one table per node: name, type, default, meaning.

``--help`` of each executable prints its table, the launch files expose one launch argument per
entry, and the tests check each table against the parameters its node really declares. The
method parameters (``method`` and every option of a method a node runs) come from the method table
:data:`hmrta.methods.METHODS`. Importing this module needs neither rclpy nor launch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# ROS parameter types as ``ros2 param describe`` names them
STRING, INTEGER, DOUBLE, BOOL, STRING_ARRAY = "string", "integer", "double", "bool", "string_array"


@dataclass(frozen=True)
class Param:
    name: str
    type: str  # one of STRING, INTEGER, DOUBLE, BOOL, STRING_ARRAY
    default: Any
    help: str

    def parse(self, text: str) -> Any:
        """A launch argument's text as this parameter's value; ValueError naming the parameter."""
        t = text.strip()
        try:
            if self.type == BOOL:
                if t.lower() in ("true", "1", "yes", "on"):
                    return True
                if t.lower() in ("false", "0", "no", "off"):
                    return False
                raise ValueError
            if self.type == INTEGER:
                return int(t)
            if self.type == DOUBLE:
                return float(t)
            if self.type == STRING_ARRAY:
                items = (s.strip().strip("'\"") for s in t.strip("[]").split(","))
                return [s for s in items if s]
            return text
        except ValueError:
            raise ValueError(f"{self.name}: expected {self.type}, got {text!r}") from None

    def text(self) -> str:
        """The default as launch-argument text."""
        if self.type == BOOL:
            return "true" if self.default else "false"
        if self.type == STRING_ARRAY:
            return ",".join(self.default)
        return str(self.default)


TASK_BOARD: tuple[Param, ...] = (
    Param("instance", STRING, "", "mission file (hmrta-instance/1 YAML or CTAS-D config.json); required"),
    Param("seed", INTEGER, 0, "episode seed (decision order)"),
    Param("output", STRING, "", "where to write the hmrta-solution/1 JSON (empty: only <mission_namespace>/hmrta/result)"),
    Param("robot_names", STRING_ARRAY, [], "robot names in the mission's agent order (empty: robot_<i>)"),
    Param("frame_id", STRING, "map", "frame of goals, poses and markers; a pose in another frame is rejected"),
    Param("pose_type", STRING, "PoseStamped",
          "message type of every robot's pose topic: PoseStamped, PoseWithCovarianceStamped (amcl_pose) or Odometry"),
    Param("pose_types", STRING_ARRAY, [], "per-robot pose types overriding pose_type, ROBOT:TYPE (robot_1:Odometry)"),
    Param("mission_namespace", STRING, "/",
          "the mission's namespace: its topics are <ns>/hmrta/... and <ns>/<robot>/pose, goal_pose (two missions "
          "on one ROS domain: two namespaces; the same on every node of a mission)"),
    Param("clock_topic", STRING, "", "mission clock topic (rosgraph_msgs/Clock, published by sim_robot; empty: "
          "<mission_namespace>/hmrta/clock); never /clock"),
    Param("scale", DOUBLE, 1.0, "metres per mission unit (positions on the wire = mission coordinates x scale)"),
    Param("wait_for_robots", BOOL, True, "start the mission only once every robot's agent and pose are up"),
    Param("startup_timeout", DOUBLE, 120.0, "wall seconds to wait for the robots at start (0: forever)"),
    Param("heartbeat_timeout", DOUBLE, 5.0,
          "wall seconds without its agent's heartbeat before a robot is dropped (a silent pose drops nobody; "
          "0: never)"),
    Param("decision_timeout", DOUBLE, 30.0, "wall seconds an agent has to answer its turn before it is dropped "
          "(0: never)"),
    Param("arrival_tolerance", DOUBLE, 0.25,
          "metres from its goal within which a robot counts as arrived (Nav2's default xy_goal_tolerance; with "
          "real robots take a little more than your controller's goal tolerance plus the localisation's noise, "
          "or a robot the controller calls arrived may be held and then dropped as stuck)"),
    Param("leg_timeout_factor", DOUBLE, 3.0,
          "a leg times out after this x its planned travel time + leg_timeout_floor: the goal is re-sent once, "
          "then the robot is dropped as stuck (factor and floor 0: never)"),
    Param("leg_timeout_floor", DOUBLE, 10.0, "seconds added to every leg's timeout (see leg_timeout_factor)"),
    Param("exit_on_done", BOOL, True, "exit when the mission is finished"),
    Param("marker_period", DOUBLE, 0.5, "wall seconds between <mission_namespace>/hmrta/markers updates (0: no markers)"),
    Param("progress_period", DOUBLE, 5.0, "wall seconds between progress log lines (0: none)"),
    Param("real_time_departures", BOOL, False, "no back-dated departures (real robots cannot leave in the past)"),
    Param("keystore", STRING, "", "mission keystore folder (or its keys.json); empty: no authentication"),
    Param("journal", STRING, "", "JSON-lines journal of the board, replayed when it exists (empty: none)"),
    Param("rejection_rate", DOUBLE, 200.0, "logged and published rejections per second, at most (0: none one by one; "
          "a count by reason every 5 s)"),
    Param("queue_depth", INTEGER, 2000, "receive queue depth (messages) of choices and heartbeats"),
    Param("keyframe_period", INTEGER, 0,
          "board versions between keyframes (0: whenever the stream has carried as many bytes as a keyframe)"),
)

SIM_ROBOT: tuple[Param, ...] = (
    Param("robots", STRING_ARRAY, [], "robots to simulate (empty: every mission robot not in external)"),
    Param("external", STRING_ARRAY, [], "robots driven outside (real robots): not simulated"),
    Param("time_scale", DOUBLE, 0.0, "sim seconds per wall second (0: as fast as possible)"),
    Param("rate", DOUBLE, 20.0, "pose and clock updates per wall second while paced (time_scale > 0)"),
    Param("heartbeat_period", DOUBLE, 1.0, "wall seconds between pose and clock heartbeats"),
    Param("mission_namespace", STRING, "/",
          "the mission's namespace: its topics are <ns>/hmrta/... and <ns>/<robot>/pose, goal_pose (two missions "
          "on one ROS domain: two namespaces; the same on every node of a mission)"),
    Param("clock_topic", STRING, "", "mission clock topic to publish (rosgraph_msgs/Clock; empty: "
          "<mission_namespace>/hmrta/clock); never /clock"),
    Param("exit_on_done", BOOL, True, "exit when the mission is finished"),
    Param("board_silence_warning", DOUBLE, 10.0,
          "wall seconds without hearing the task board before a warning (repeated every 3 x as long; 0: never)"),
)

AGENT_NODE: tuple[Param, ...] = (
    Param("robot", STRING, "", "robot name in the mission (empty: the last part of the node's namespace)"),
    Param("index", INTEGER, -1, "the robot's agent index in the mission (-1: from its name)"),
    Param("species", INTEGER, -1, "the robot's species, checked against the mission (-1: no check)"),
    Param("seed", INTEGER, 0, "seed of sampled decisions"),
    Param("exit_on_done", BOOL, True, "exit when the mission is finished"),
    Param("keystore", STRING, "", "mission keystore folder: sign with the hosted robots' keys (empty: unsigned)"),
    Param("key_file", STRING, "", "one robot's key file (robots/<robot>.key.json) to sign with"),
    Param("mission_namespace", STRING, "/",
          "the mission's namespace: its topics are <ns>/hmrta/... and <ns>/<robot>/pose, goal_pose (two missions "
          "on one ROS domain: two namespaces; the same on every node of a mission)"),
    Param("clock_topic", STRING, "", "mission clock topic (goals are sent when it passes their departure; empty: "
          "<mission_namespace>/hmrta/clock)"),
    Param("board_silence_warning", DOUBLE, 10.0,
          "wall seconds without hearing the task board before a warning (repeated every 3 x as long; 0: never)"),
    Param("pose_type", STRING, "PoseStamped",
          "message type of the robot's pose topic (pose in the node's namespace: remap it to the driver's), read "
          "to stop a robot the board drops and to place a robot that joins: PoseStamped, PoseWithCovarianceStamped "
          "(amcl_pose) or Odometry (the board's pose_type for this robot)"),
)

RECORDER: tuple[Param, ...] = (
    Param("output", STRING, "", "MCAP file to write (empty: hmrta_<date>_<time>.mcap in the working folder)"),
    Param("robots", STRING_ARRAY, [], "robots whose goal_pose and pose topics to record (empty: the mission's robots)"),
    Param("topics", STRING_ARRAY, [], "further topics to record (any message type installed here)"),
    Param("markers", BOOL, False, "also record <mission_namespace>/hmrta/markers (RViz markers; large)"),
    Param("discovery_period", DOUBLE, 1.0,
          "wall seconds between looks for new topics to record (> 0; at least 0.05 is used)"),
    Param("compression", STRING, "zstd", "chunk compression: zstd, lz4 or none"),
    Param("mission_namespace", STRING, "/",
          "the mission's namespace: its topics are <ns>/hmrta/... and <ns>/<robot>/pose, goal_pose (two missions "
          "on one ROS domain: two namespaces; the same on every node of a mission)"),
    Param("clock_topic", STRING, "", "mission clock topic to record (empty: <mission_namespace>/hmrta/clock)"),
)

NODES: dict[str, tuple[Param, ...]] = {"task_board": TASK_BOARD, "sim_robot": SIM_ROBOT, "agent_node": AGENT_NODE,
                                       "recorder": RECORDER}
METHOD_NODES = ("task_board", "agent_node")  # nodes that also declare the method parameters

_TYPES = {str: STRING, int: INTEGER, float: DOUBLE, bool: BOOL}


def method_parameters() -> tuple[Param, ...]:
    """``method`` and every live method option, as declared by
    :func:`hmrta_msgs_py.runtime.declare_method_parameters` (ROS has no None: '' / 0)."""
    from hmrta.methods import help_text, live_options, mission_methods, node_options

    out = [Param("method", STRING, "portfolio", "the method that decides (rl-sN = rl-sample with N samples); "
                 "on a node, portfolio (the default): the task board chooses at the start and publishes the one "
                 "chosen as the mission's method; an agent started with portfolio runs the mission's method, "
                 "whatever it is | " + help_text(mission_methods()))]
    live = live_options()
    for o in node_options().values():
        default = o.default if o.default is not None else {str: "", int: 0, float: 0.0}[o.type]
        note = "" if o.name in live else " (task_board only: an agent runs the method its board chose)"
        out.append(Param(o.name, _TYPES[o.type], default, o.help + note))
    return tuple(out)


def node_parameters(node: str) -> tuple[Param, ...]:
    """Every parameter ``node`` (task_board, sim_robot, agent_node, recorder) declares."""
    table = NODES[node]
    return table + method_parameters() if node in METHOD_NODES else table


def by_name(params: tuple[Param, ...]) -> dict[str, Param]:
    return {p.name: p for p in params}
