"""Several drives on one link (RS-485 line, Modbus TCP card) from one bus file.

    ros2 launch vfd_ros2 bus.launch.py config_file:=/path/to/bus.yaml
    ros2 launch vfd_ros2 bus.launch.py config_file:=/path/to/bus.yaml \
        joint_commands_topic:=/robot_joint_commands joint_states_topic:=/robot_joint_states

The joint topics are topic_based_ros2_control's contract (README: ros2_control); '' = off.

Example bus file: share/vfd_ros2/config/sim_agv_bus.yaml.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('config_file', description='bus YAML: the link and its drives'),
        DeclareLaunchArgument('name', default_value='bus'),
        DeclareLaunchArgument('namespace', default_value='/'),
        DeclareLaunchArgument('joint_commands_topic', default_value='',
                              description='sensor_msgs/JointState velocity commands in'),
        DeclareLaunchArgument('joint_states_topic', default_value='',
                              description="the drives' joint states out, together"),
        Node(package='vfd_ros2', executable='bus_node', name=LaunchConfiguration('name'),
             namespace=LaunchConfiguration('namespace'),
             parameters=[{'config_file': LaunchConfiguration('config_file'),
                          'joint_commands_topic': LaunchConfiguration('joint_commands_topic'),
                          'joint_states_topic': LaunchConfiguration('joint_states_topic')}],
             output='screen', emulate_tty=True),
    ])
