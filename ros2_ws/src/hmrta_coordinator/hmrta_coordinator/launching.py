"""Building blocks of the launch files (``mission.launch.py``, ``fleet.launch.py``).

Launch arguments come from the nodes' parameter tables (:mod:`hmrta_msgs_py.params`): one
argument per parameter, same name, same default, same meaning; a parameter several nodes declare
with one meaning (``seed``, ``method``, ``keystore``, ``exit_on_done``) is one argument feeding
them all. ``launch`` and ``launch_ros`` are imported only by the functions that build actions.

Fleet file (``fleet:=FILE.yaml``): the real robots and their topics::

    robots:
      - name: robot_1              # robot name in the mission (required)
        species: 0                 # checked against the mission (default: no check)
        namespace: /tb3_1          # the agent's namespace (default: <mission_namespace>/<name>)
        pose_topic: /tb3_1/pose    # where its pose is published (default: <mission_namespace>/<name>/pose)
        pose_type: PoseStamped     # its message type: PoseStamped, PoseWithCovarianceStamped, Odometry
        goal_topic: /tb3_1/goal_pose   # where its goals go (default: goal_pose in the namespace)
        key_file: keys/robots/robot_1.key.json   # sign with this key (default: none / keystore)
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hmrta_msgs_py import params as P
from hmrta_msgs_py.topics import check_mission_namespace as check_namespace  # noqa: F401 (for the launch files)
from hmrta_msgs_py.topics import robot_namespace

POSE_TYPES = ("PoseStamped", "PoseWithCovarianceStamped", "Odometry")
FLEET_FIELDS = ("name", "species", "namespace", "pose_topic", "pose_type", "goal_topic", "key_file")


@dataclass(frozen=True)
class FleetRobot:
    name: str
    namespace: str
    pose_topic: str
    pose_type: str = "PoseStamped"
    goal_topic: str = "goal_pose"
    species: int = -1
    key_file: str = ""


def load_fleet(path: str | Path, mission_namespace: str = "/") -> list[FleetRobot]:
    """The robots of a fleet file (defaults in ``mission_namespace``, the mission's topics
    ``<ns>/<robot>/...``); ValueError naming the file and the field for anything wrong."""
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ValueError(f"{path}: cannot read the fleet file: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("robots"), list) or not doc["robots"]:
        raise ValueError(f"{path}: robots: expected a non-empty list of robots")
    out: list[FleetRobot] = []
    for i, r in enumerate(doc["robots"]):
        where = f"{path}: robots[{i}]"
        if not isinstance(r, dict):
            raise ValueError(f"{where}: expected a mapping with name, namespace, pose_topic, ...")
        unknown = sorted(set(r) - set(FLEET_FIELDS))
        if unknown:
            raise ValueError(f"{where}: unknown field {unknown[0]!r} (expected {', '.join(FLEET_FIELDS)})")
        name = r.get("name")
        if not isinstance(name, str) or not name.strip("/") or "/" in name.strip("/"):
            raise ValueError(f"{where}.name: expected a robot name such as robot_1, got {name!r}")
        name = name.strip("/")
        for k in ("namespace", "pose_topic", "goal_topic", "key_file", "pose_type"):
            if k in r and (not isinstance(r[k], str) or not r[k]):
                raise ValueError(f"{where}.{k}: expected a non-empty string, got {r[k]!r}")
        species = r.get("species", -1)
        if isinstance(species, bool) or not isinstance(species, int) or species < -1:
            raise ValueError(f"{where}.species: expected a species index >= 0, got {species!r}")
        pose_type = r.get("pose_type", "PoseStamped")
        if pose_type not in POSE_TYPES:
            raise ValueError(f"{where}.pose_type: expected one of {', '.join(POSE_TYPES)}, got {pose_type!r}")
        own = robot_namespace(name, mission_namespace)  # where the board and sim_robot expect its topics
        ns = "/" + r["namespace"].strip("/") if "namespace" in r else own
        out.append(FleetRobot(name, ns, r.get("pose_topic", f"{own}/pose"), pose_type,
                              r.get("goal_topic", "goal_pose"), species, r.get("key_file", "")))
    names = [r.name for r in out]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: robots: a robot is listed twice")
    return out


# ---- launch arguments ------------------------------------------------------------------------
LAUNCH_DEFAULTS = {"output": "mission.json"}  # where the launch differs from the node default

EXTRA_ARGS = {
    "fleet": ("", "fleet file (YAML) listing the real robots and their topics (see docs/ros.md)"),
    "remaps": ("", "extra remappings of the task board, comma-separated FROM:=TO "
                   "(e.g. /robot_1/pose:=/tb3_1/pose)"),
}


def args_of(*nodes: str, skip: tuple[str, ...] = ()) -> dict[str, tuple[str, str]]:
    """name -> (default text, description): one launch argument per parameter of ``nodes``."""
    out: dict[str, tuple[str, str]] = {}
    for node in nodes:
        for p in P.node_parameters(node):
            if p.name not in out and p.name not in skip:
                out[p.name] = (LAUNCH_DEFAULTS.get(p.name, p.text()), f"[{node}] {p.help}")
    return out


def declare(args: dict[str, tuple[str, str]]) -> list:
    from launch.actions import DeclareLaunchArgument

    return [DeclareLaunchArgument(k, default_value=v, description=d) for k, (v, d) in args.items()]


def values(context, names) -> dict[str, str]:
    from launch.substitutions import LaunchConfiguration

    return {k: LaunchConfiguration(k).perform(context) for k in names}


def node_values(node: str, given: dict[str, str], only: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The typed parameters of ``node`` from the launch arguments (unset method options and
    empty string arrays omitted: ROS cannot type an empty list; the node's default is empty)."""
    options = {p.name for p in P.method_parameters()} - {"method"}
    out: dict[str, Any] = {}
    for p in P.node_parameters(node):
        if p.name not in given or (only is not None and p.name not in only):
            continue
        v = p.parse(given[p.name])
        if (p.type == P.STRING_ARRAY and not v) or (p.name in options and given[p.name] == ""):
            continue
        out[p.name] = v
    return out


def parse_remaps(text: str) -> list[tuple[str, str]]:
    out = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        src, sep, dst = item.partition(":=")
        if not sep or not src.strip() or not dst.strip():
            raise ValueError(f"remaps: expected FROM:=TO, got {item!r}")
        out.append((src.strip(), dst.strip()))
    return out


def board_remaps(fleet: list[FleetRobot], mission_namespace: str = "/") -> list[tuple[str, str]]:
    """The board reads each robot's pose on <mission_namespace>/<robot>/pose: point it at the
    fleet's pose topics."""
    out = []
    for r in fleet:
        own = robot_namespace(r.name, mission_namespace) + "/pose"
        if r.pose_topic != own:
            out.append((own, r.pose_topic))
    return out


def board_pose_types(fleet: list[FleetRobot], given: list[str]) -> list[str]:
    """The board's ``pose_types`` (ROBOT:TYPE): those of the launch argument, then each fleet
    robot's ``pose_type`` where it is not PoseStamped (the fleet file wins for its robots)."""
    listed = {r.name: f"{r.name}:{r.pose_type}" for r in fleet if r.pose_type != "PoseStamped"}
    out = [g for g in given if g.rpartition(":")[0].strip().strip("/") not in {r.name for r in fleet}]
    return out + list(listed.values())


def agent_node(robot: FleetRobot, common: dict[str, Any], output: str = "screen"):
    """The agent of one robot, in its namespace, goals remapped to the robot's goal topic and its
    pose read as the board reads it (the fleet file's pose topic and type; the type of the
    ``pose_type`` argument where the fleet file has the default, as :func:`board_pose_types`)."""
    from launch_ros.actions import Node

    params = {"robot": robot.name, **common}
    if robot.species >= 0:
        params["species"] = robot.species
    if robot.key_file:
        params["key_file"] = robot.key_file
    if robot.pose_type != "PoseStamped":
        params["pose_type"] = robot.pose_type
    remaps = [("goal_pose", robot.goal_topic)] if robot.goal_topic != "goal_pose" else []
    if robot.pose_topic != robot.namespace.rstrip("/") + "/pose":
        remaps.append(("pose", robot.pose_topic))
    return Node(package="hmrta_agent", executable="agent_node", name="agent", namespace=robot.namespace,
                output=output, parameters=[params], remappings=remaps)


def board_node(given: dict[str, str], robots: list[str], remaps: list[tuple[str, str]],
               fleet: list[FleetRobot] = ()):
    from launch.actions import Shutdown
    from launch_ros.actions import Node

    params = node_values("task_board", given)
    pose_types = board_pose_types(list(fleet), params.get("pose_types", []))
    if pose_types:
        params["pose_types"] = pose_types
    if robots and "robot_names" not in params:
        params["robot_names"] = robots
    return Node(package="hmrta_coordinator", executable="task_board", name="task_board", output="screen",
                parameters=[params], remappings=remaps, on_exit=Shutdown(reason="mission finished"))


def instance_path(text: str) -> str:
    if text:
        return text
    import hmrta

    return str(Path(hmrta.__file__).resolve().parent / "data" / "example.yaml")

