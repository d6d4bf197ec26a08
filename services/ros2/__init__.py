"""ROS 2 on the wire: the live source (its frame assembler in :mod:`services.ros2.live`), the
markers-and-queries bridge, the bag player."""

from shared.registry import SERVICES, ServiceEntry

SERVICES.register(
    "ros2",
    ServiceEntry("the scene graph as ROS 2 markers, queries from ROS 2", node="services.ros2.node:build"),
)
