"""Programs built on everything below: the demo and the bringup specs for launch files."""
