"""Running drives: the control loop, the one motion-permit rule, service actions, buses.

``controller.DriveController`` runs one drive (``loop.CycleLoop``: its own thread,
or a ``bus.Bus`` serving several drives on one link); ``permit.decide`` is the
only rule for motion; ``actions`` holds the service steps; ``settings`` the
table of node parameters and ``factory`` the composition root that turns them
into profile + transport + drive + controller. No ROS here.
"""
