"""Launch the simulated AGV: two drives on ONE simulated RS-485 line and diff_drive.

One bus_node serves a drive node per wheel; diff_drive turns cmd_vel into wheel
commands and the measured wheel speeds into odom.

    ros2 launch vfd_ros2 sim_agv.launch.py [directory:=/tmp/vfd_ros2/sim_agv] \
        [managed:=true [autostart:=false]]
    ros2 topic pub -r 20 /agv/cmd_vel geometry_msgs/msg/TwistStamped "{twist: {linear: {x: 0.3}}}"
    ros2 param set /agv/sim_drive silent_unit_ids "[2]"     # pull the right drive off the line
    ros2 lifecycle set /agv/bus deactivate                  # managed:=true: stop and hold

Ctrl-C: the simulator keeps the line open until the bus has written every stop.
The node list and the bus file come from vfd_ros2.apps.bringup (unit-tested); this
file only turns them into launch actions.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from vfd_ros2.apps.bringup import DEFAULT_SIM_DIR, sim_agv, sim_agv_bus, write_bus_file


def _nodes(context):
    def value(name):
        return LaunchConfiguration(name).perform(context)
    directory = value('directory')
    write_bus_file(sim_agv_bus(directory), directory)
    return [Node(**spec.managed(value('managed'), value('autostart')).launch_kwargs())
            for spec in sim_agv(directory=directory)]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('directory', default_value=DEFAULT_SIM_DIR,
                              description='where the emulated serial line and bus file go'),
        DeclareLaunchArgument('managed', default_value='false',
                              description='bus_node as a lifecycle (managed) node'),
        DeclareLaunchArgument('autostart', default_value='true',
                              description='the managed node configures and activates at start'),
        OpaqueFunction(function=_nodes),
    ])
