"""Launch the demo: per wheel a simulated drive on its own line and a drive_node.

The demo's velocity profile runs too (run_demo:=true); its end ends the launch (a failed
demo leaves the drives up).

    ros2 launch vfd_ros2 demo.launch.py [run_demo:=false] [directory:=/tmp/vfd_ros2/demo]
        [managed:=true [autostart:=false]]

managed:=true starts the drive nodes as lifecycle nodes (configured and activated at
start unless autostart:=false; then a lifecycle manager or `ros2 lifecycle set` does it,
and run_demo:=false: the profile gives up after 20 s of unconfigured drives).
The demo's processes keep DDS on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
set here as scripts/demo does: the demo refuses to run without it).
Ctrl-C: each simulator keeps its line open until its driver has written the stop.
The node list comes from vfd_ros2.apps.bringup.sim_wheels (unit-tested); this file only
turns it into launch actions.
"""

from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    LogInfo,
    OpaqueFunction,
    SetEnvironmentVariable,
    Shutdown,
)
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from vfd_ros2.apps.bringup import DEFAULT_DEMO_DIR, sim_wheels


def _nodes(context):
    def value(name):
        return LaunchConfiguration(name).perform(context)
    return [Node(**spec.managed(value('managed'), value('autostart')).launch_kwargs())
            for spec in sim_wheels(directory=value('directory'))]


def _after_demo(event, _context):
    # The profile's end ends the launch (its drives stopped first), as scripts/demo does;
    # a failed demo leaves the drives up for a look (managed:=true autostart:=false
    # without run_demo:=false gives up after 20 s).
    if event.returncode == 0:
        return [Shutdown(reason='the demo profile ended')]
    return [LogInfo(msg=f'the demo failed (exit code {event.returncode}): the simulated '
                        'drives and drive nodes stay up for a look; Ctrl-C ends the launch')]


def generate_launch_description():
    return LaunchDescription([
        SetEnvironmentVariable('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST'),
        DeclareLaunchArgument('directory', default_value=DEFAULT_DEMO_DIR,
                              description='where the emulated serial ports are created'),
        DeclareLaunchArgument('run_demo', default_value='true',
                              description='also run the demo velocity profile'),
        DeclareLaunchArgument('managed', default_value='false',
                              description='drive nodes as lifecycle (managed) nodes'),
        DeclareLaunchArgument('autostart', default_value='true',
                              description='managed nodes configure and activate at start'),
        OpaqueFunction(function=_nodes),
        Node(package='vfd_ros2', executable='demo', arguments=['--attach'], output='screen',
             emulate_tty=False, condition=IfCondition(LaunchConfiguration('run_demo')),
             on_exit=_after_demo),
    ])
