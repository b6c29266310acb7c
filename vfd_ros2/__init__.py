"""vfd_ros2: ROS 2 driver for industrial motor drives."""
