"""Launch the agents of a fleet of real robots, one per robot in the fleet file, each in its
namespace with its goals remapped to the robot's goal topic; with ``board:=true`` also the task
board, reading each robot's pose from its pose topic.

    ros2 launch hmrta_coordinator fleet.launch.py fleet:=fleet.yaml method:=greedy
    ros2 launch hmrta_coordinator fleet.launch.py fleet:=fleet.yaml board:=true instance:=mission.yaml \\
        scale:=1.0 real_time_departures:=true

Fleet file (YAML)::

    robots:
      - {name: robot_0, namespace: /tb3_0, pose_topic: /tb3_0/pose, goal_topic: /tb3_0/goal_pose}
      - {name: robot_1, species: 1, namespace: /tb3_1, pose_topic: /tb3_1/pose, goal_topic: /tb3_1/goal_pose}

Every parameter of ``agent_node`` that is not per robot (``seed``, ``method`` and its options,
``keystore``, ``exit_on_done``) and, for ``board:=true``, every parameter of ``task_board`` is a
launch argument of the same name; ``mission_namespace`` (the mission's, default ``/``) also sets
the defaults of a fleet robot's namespace and pose topic (``<mission_namespace>/<name>``). With the
board here, the mission's other robots are simulated only if a ``sim_robot`` runs
(``mission.launch.py fleet:=...`` starts both). See docs/ros.md.
"""
from launch import LaunchDescription
from launch.actions import OpaqueFunction

from hmrta_coordinator import launching as L

PER_ROBOT = ("robot", "index", "species", "key_file")  # from the fleet file
ARGS = {
    "fleet": ("", "fleet file (YAML) listing the robots: name, species, namespace, pose_topic, pose_type, "
                  "goal_topic, key_file (required)"),
    "board": ("false", "also start the task board (true/false)"),
    **L.args_of("agent_node", skip=PER_ROBOT),
    **L.args_of("task_board"),
    "remaps": L.EXTRA_ARGS["remaps"],
}


def _nodes(context):
    arg = L.values(context, ARGS)
    if not arg["fleet"]:
        raise ValueError("fleet: set the fleet file: fleet:=FILE.yaml")
    ns = L.check_namespace(arg["mission_namespace"])
    fleet = L.load_fleet(arg["fleet"], ns)
    common = L.node_values("agent_node", arg, only=tuple(a for a in ARGS if a not in PER_ROBOT))
    nodes = [L.agent_node(r, common) for r in fleet]
    if L.P.Param("board", L.P.BOOL, False, "").parse(arg["board"]):
        arg["instance"] = L.instance_path(arg["instance"])
        nodes.insert(0, L.board_node(arg, [], L.board_remaps(fleet, ns) + L.parse_remaps(arg["remaps"]), fleet))
    return nodes


def generate_launch_description():
    return LaunchDescription(L.declare(ARGS) + [OpaqueFunction(function=_nodes)])
