"""Launch the agent of one real robot (its own decision maker), e.g. on the robot's computer.

    ros2 launch hmrta_agent agent.launch.py robot:=robot_3 goal_topic:=/tb3_3/goal_pose method:=rl
    ros2 launch hmrta_agent agent.launch.py robot:=robot_3 goal_topic:=/tb3_3/goal_pose \
        pose_topic:=/tb3_3/amcl_pose pose_type:=PoseWithCovarianceStamped

The agent joins the mission it hears on <mission_namespace>/hmrta/mission (its name must be one of
the mission's robots; its node runs in <mission_namespace>/<robot>), decides when the board gives it the turn, and sends its robot's goals as
geometry_msgs/PoseStamped on ``goal_topic`` (a Nav2 bt_navigator's ``goal_pose`` takes them as is).
It reads the robot's pose on ``pose_topic`` (of ``pose_type``, as the board reads it) to stop the
robot where it is if the board drops it.
Every parameter of ``agent_node`` is a launch argument of the same name. For several robots, use
``hmrta_coordinator fleet.launch.py`` with a fleet file.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from hmrta_msgs_py import params as P

PARAMS = P.node_parameters("agent_node")
ARGS = {
    "robot": ("robot_0", "robot name in the mission (the node's namespace is <mission_namespace>/<robot>)"),
    "goal_topic": ("goal_pose", "where to send the robot's goals (relative: in the robot's namespace)"),
    "pose_topic": ("pose", "where the robot's pose is published (relative: in the robot's namespace)"),
    **{p.name: (p.text(), p.help) for p in PARAMS if p.name != "robot"},
}
OPTIONS = {p.name for p in P.method_parameters()} - {"method"}


def _agent(context):
    arg = {k: LaunchConfiguration(k).perform(context) for k in ARGS}
    params = {p.name: p.parse(arg[p.name]) for p in PARAMS if not (p.name in OPTIONS and arg[p.name] == "")}
    from hmrta_msgs_py.topics import check_mission_namespace, robot_namespace

    ns = robot_namespace(arg["robot"], check_mission_namespace(params.get("mission_namespace", "/")))
    remaps = [("goal_pose", arg["goal_topic"])] + ([("pose", arg["pose_topic"])] if arg["pose_topic"] != "pose" else [])
    return [Node(package="hmrta_agent", executable="agent_node", name="agent", namespace=ns,
                 output="screen", parameters=[params], remappings=remaps)]


def generate_launch_description():
    return LaunchDescription([DeclareLaunchArgument(k, default_value=v, description=d) for k, (v, d) in ARGS.items()]
                             + [OpaqueFunction(function=_agent)])
