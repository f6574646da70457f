"""Launch a whole HMRTA mission on a ROS 2 install: the task board, the simulated robots and one
agent node per robot (own process, namespace /robot_<i>). The launch ends when the board does.

    ros2 launch hmrta_coordinator mission.launch.py instance:=/path/mission.yaml seed:=1 \\
        output:=/tmp/mission.json method:=greedy time_scale:=5.0

``instance`` defaults to the built-in example mission. For a real fleet, list the robots that
are not simulated in ``external`` (comma-separated) and remap their topics (see docs/ros.md).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from hmrta import methods

ARGS = {
    "instance": ("", "mission file (hmrta-instance/1 YAML or CTAS-D config.json); empty: the example"),
    "seed": ("0", "episode seed (decision order)"),
    "method": ("greedy", methods.help_text(methods.live_methods())),
    **{o.name: ("" if o.default is None else str(o.default), o.help) for o in methods.live_options().values()},
    "output": ("mission.json", "where the task board writes the hmrta-solution/1 JSON"),
    "time_scale": ("0.0", "sim seconds per wall second (0: as fast as possible)"),
    "external": ("", "comma-separated robots driven outside (not simulated)"),
    "heartbeat_timeout": ("5.0", "wall seconds before a silent robot is declared lost"),
}


def _nodes(context):
    from pathlib import Path

    import hmrta
    from hmrta.formats import load_instance

    arg = {k: LaunchConfiguration(k).perform(context) for k in ARGS}
    instance = arg["instance"] or str(Path(hmrta.__file__).resolve().parent / "data" / "example.yaml")
    inst = load_instance(instance)
    robots = [f"robot_{a}" for a in range(inst.n_agents)]
    external = [r.strip() for r in arg["external"].split(",") if r.strip()]
    common = {"seed": int(arg["seed"]), "method": arg["method"],
              **{k: o.type(arg[k]) for k, o in methods.live_options().items() if arg[k] != ""}}
    board = Node(package="hmrta_coordinator", executable="task_board", name="task_board", output="screen",
                 parameters=[{"instance": instance, "output": arg["output"], "robot_names": robots,
                              "heartbeat_timeout": float(arg["heartbeat_timeout"]), **common}],
                 on_exit=Shutdown(reason="mission finished"))
    sim_params = {"time_scale": float(arg["time_scale"])}
    if external:
        sim_params["external"] = external
    sim = Node(package="hmrta_coordinator", executable="sim_robot", name="sim_robot", output="screen",
               parameters=[sim_params])
    agents = [Node(package="hmrta_agent", executable="agent_node", name="agent", namespace=r, output="log",
                   parameters=[{"robot": r, **common}]) for r in robots]
    return [board, sim, *agents]


def generate_launch_description():
    return LaunchDescription([DeclareLaunchArgument(k, default_value=v, description=d) for k, (v, d) in ARGS.items()]
                             + [OpaqueFunction(function=_nodes)])
