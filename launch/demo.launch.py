"""Launch the demo: per wheel a simulated drive on its own line and a drive_node.

The demo's velocity profile runs too (run_demo:=true).

    ros2 launch vfd_ros2 demo.launch.py [run_demo:=false] [directory:=/tmp/vfd_ros2/sim_agv]

The node list comes from vfd_ros2.apps.bringup.sim_wheels (unit-tested); this file only
turns it into launch actions.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from vfd_ros2.apps.bringup import DEFAULT_SIM_DIR, sim_wheels


def _nodes(context):
    directory = LaunchConfiguration('directory').perform(context)
    return [Node(package='vfd_ros2', executable=spec.executable, name=spec.name,
                 namespace=spec.namespace, parameters=[spec.parameters], output='screen')
            for spec in sim_wheels(directory=directory)]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('directory', default_value=DEFAULT_SIM_DIR,
                              description='where the emulated serial ports are created'),
        DeclareLaunchArgument('run_demo', default_value='true',
                              description='also run the demo velocity profile'),
        OpaqueFunction(function=_nodes),
        Node(package='vfd_ros2', executable='demo', arguments=['--attach'], output='screen',
             condition=IfCondition(LaunchConfiguration('run_demo'))),
    ])
