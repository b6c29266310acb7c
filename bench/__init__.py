"""The vfd_ros2 benchmark (``scripts/bench``; see bench/run.py)."""
