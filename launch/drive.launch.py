"""One drive node from a YAML parameter file.

    ros2 launch vfd_ros2 drive.launch.py params_file:=/path/to/drive.yaml \
        namespace:=/agv/left_wheel

The parameter file's top key must match the node, e.g. /agv/left_wheel/drive
(or use /** to match any). Examples: share/vfd_ros2/config/*.yaml.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('params_file', description='drive_node parameter YAML'),
        DeclareLaunchArgument('namespace', default_value='/drive0',
                              description='one namespace per drive, e.g. /agv/left_wheel'),
        DeclareLaunchArgument('name', default_value='drive'),
        Node(package='vfd_ros2', executable='drive_node',
             name=LaunchConfiguration('name'), namespace=LaunchConfiguration('namespace'),
             parameters=[LaunchConfiguration('params_file')], output='screen',
             emulate_tty=True),
    ])
