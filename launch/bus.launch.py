"""Several drives on one link (RS-485 line, Modbus TCP card) from one bus file.

    ros2 launch vfd_ros2 bus.launch.py config_file:=/path/to/bus.yaml \
        [managed:=true [autostart:=false]]
    ros2 launch vfd_ros2 bus.launch.py config_file:=/path/to/bus.yaml \
        joint_commands_topic:=/robot_joint_commands joint_states_topic:=/robot_joint_states

Example bus file: share/vfd_ros2/config/sim_agv_bus.yaml. managed:=true: the bus node is
a lifecycle node (all its drives move through the transitions together). The joint topics
are topic_based_ros2_control's contract (README: ros2_control); '' = off.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from vfd_ros2.apps.bringup import NodeSpec


def _node(context):
    def value(name):
        return LaunchConfiguration(name).perform(context)
    spec = NodeSpec('bus_node', value('name'), value('namespace'),
                    {'config_file': value('config_file'),
                     'joint_commands_topic': value('joint_commands_topic'),
                     'joint_states_topic': value('joint_states_topic')}).managed(
        value('managed'), value('autostart'))
    return [Node(**spec.launch_kwargs())]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('config_file', description='bus YAML: the link and its drives'),
        DeclareLaunchArgument('name', default_value='bus'),
        DeclareLaunchArgument('namespace', default_value='/'),
        DeclareLaunchArgument('joint_commands_topic', default_value='',
                              description='sensor_msgs/JointState velocity commands in'),
        DeclareLaunchArgument('joint_states_topic', default_value='',
                              description="the drives' joint states out, together"),
        DeclareLaunchArgument('managed', default_value='false',
                              description='a lifecycle (managed) node'),
        DeclareLaunchArgument('autostart', default_value='true',
                              description='the managed node configures and activates at start'),
        OpaqueFunction(function=_node),
    ])
