"""Launch the agent of one real robot (its own decision maker), e.g. on the robot's computer.

    ros2 launch hmrta_agent agent.launch.py robot:=robot_3 goal_topic:=/tb3_3/goal_pose method:=rl

The agent joins the mission it hears on /hmrta/mission (its name must be one of the mission's
robots), decides when the board gives it the turn, and sends its robot's goals as
geometry_msgs/PoseStamped on ``goal_topic`` (a Nav2 bt_navigator's ``goal_pose`` takes them as is).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from hmrta import methods

ARGS = {
    "robot": ("robot_0", "robot name in the mission (also the node's namespace)"),
    "goal_topic": ("goal_pose", "where to send the robot's goals (relative: in the robot's namespace)"),
    "method": ("greedy", methods.help_text(methods.live_methods())),
    **{o.name: ("" if o.default is None else str(o.default), o.help) for o in methods.live_options().values()},
    "seed": ("0", "seed (sampled decoding)"),
}
METHOD_PARAMS = ["method", *methods.live_options()]


def generate_launch_description():
    c = {k: LaunchConfiguration(k) for k in ARGS}
    agent = Node(package="hmrta_agent", executable="agent_node", name="agent", namespace=c["robot"], output="screen",
                 parameters=[{**{k: ParameterValue(c[k], value_type=str)
                                 for k in ("robot", *METHOD_PARAMS)},
                              "seed": ParameterValue(c["seed"], value_type=int)}],
                 remappings=[("goal_pose", c["goal_topic"])])
    return LaunchDescription([DeclareLaunchArgument(k, default_value=v, description=d) for k, (v, d) in ARGS.items()]
                             + [agent])
