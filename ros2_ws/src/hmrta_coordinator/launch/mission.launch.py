"""Launch a whole HMRTA mission on a ROS 2 install: the task board, the simulated robots and one
agent node per simulated robot (own process, namespace <mission_namespace>/<robot>). The launch
ends when the board does.

    ros2 launch hmrta_coordinator mission.launch.py instance:=/path/mission.yaml seed:=1 \\
        output:=/tmp/mission.json method:=greedy time_scale:=5.0

Every parameter of ``task_board`` and ``sim_robot`` is a launch argument of the same name
(``ros2 launch hmrta_coordinator mission.launch.py --show-args``); ``seed``, ``method`` and its
options, ``keystore`` and ``exit_on_done`` also go to the agents. ``instance`` defaults to the
built-in example mission.

Real robots: list them in ``external`` (comma-separated) or in a fleet file (``fleet:=FILE.yaml``,
whose robots are external and whose pose topics the board reads); they get no simulation and no
agent here: start their agents with ``fleet.launch.py`` (or ``hmrta_agent agent.launch.py``) next
to them. ``remaps`` adds board remappings (``/robot_1/pose:=/tb3_1/pose``; in a mission namespace
``<mission_namespace>/robot_1/pose:=...``). ``mission_namespace:=/fleet1`` runs the whole mission
there (every node; agents in ``/fleet1/<robot>``). See docs/ros.md.
"""
from launch import LaunchDescription
from launch.actions import OpaqueFunction
from launch_ros.actions import Node

from hmrta_coordinator import launching as L

ARGS = {**L.args_of("task_board", "sim_robot"), **L.EXTRA_ARGS}
AGENT_PARAMS = ("seed", "exit_on_done", "keystore", "clock_topic", "mission_namespace", "method",
                *(p.name for p in L.P.method_parameters()))


def _nodes(context):
    from hmrta.formats import load_instance

    arg = L.values(context, ARGS)
    arg["instance"] = L.instance_path(arg["instance"])
    inst = load_instance(arg["instance"])
    robots = L.P.by_name(L.P.TASK_BOARD)["robot_names"].parse(arg["robot_names"]) or \
        [f"robot_{a}" for a in range(inst.n_agents)]
    ns = L.check_namespace(arg["mission_namespace"])
    fleet = L.load_fleet(arg["fleet"], ns) if arg["fleet"] else []
    external = L.P.by_name(L.P.SIM_ROBOT)["external"].parse(arg["external"]) + [r.name for r in fleet]
    unknown = sorted(set(external) - set(robots))
    if unknown:
        raise ValueError(f"external: {', '.join(unknown)} not among the mission's robots ({', '.join(robots[:5])}...)")
    board = L.board_node(arg, robots, L.board_remaps(fleet, ns) + L.parse_remaps(arg["remaps"]), fleet)
    sim_params = L.node_values("sim_robot", {**arg, "external": ",".join(dict.fromkeys(external))})
    sim = Node(package="hmrta_coordinator", executable="sim_robot", name="sim_robot", output="screen",
               parameters=[sim_params])
    common = L.node_values("agent_node", arg, only=AGENT_PARAMS)
    homes = {r: L.robot_namespace(r, ns) for r in robots if r not in external}  # <ns>/<robot>
    agents = [L.agent_node(L.FleetRobot(r, home, home + "/pose"), common, output="log") for r, home in homes.items()]
    return [board, sim, *agents]


def generate_launch_description():
    return LaunchDescription(L.declare(ARGS) + [OpaqueFunction(function=_nodes)])
