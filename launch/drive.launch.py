"""One drive node from a YAML parameter file.

    ros2 launch vfd_ros2 drive.launch.py params_file:=/path/to/drive.yaml \
        namespace:=/agv/left_wheel [managed:=true [autostart:=false]]

The parameter file's top key must match the node, e.g. /agv/left_wheel/drive
(or use /** to match any). Examples: share/vfd_ros2/config/*.yaml.
managed:=true: a lifecycle node, configured and activated at start unless
autostart:=false (then a lifecycle manager or `ros2 lifecycle set` does it).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from vfd_ros2.apps.bringup import NodeSpec


def _node(context):
    def value(name):
        return LaunchConfiguration(name).perform(context)
    spec = NodeSpec('drive_node', value('name'), value('namespace')).managed(
        value('managed'), value('autostart'))
    kwargs = spec.launch_kwargs()
    kwargs['parameters'] = [value('params_file')]
    return [Node(**kwargs)]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('params_file', description='drive_node parameter YAML'),
        DeclareLaunchArgument('namespace', default_value='/drive0',
                              description='one namespace per drive, e.g. /agv/left_wheel'),
        DeclareLaunchArgument('name', default_value='drive'),
        DeclareLaunchArgument('managed', default_value='false',
                              description='a lifecycle (managed) node'),
        DeclareLaunchArgument('autostart', default_value='true',
                              description='the managed node configures and activates at start'),
        OpaqueFunction(function=_node),
    ])
