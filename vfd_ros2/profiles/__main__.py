"""``python -m vfd_ros2.profiles [name|path ...]``: check profile files."""

from .loader import main

raise SystemExit(main())
