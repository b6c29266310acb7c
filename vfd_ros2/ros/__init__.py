"""The only rclpy code: drive_node, bus_node, diff_drive_node, messages, the spin idiom."""
