"""The source service: replays a recorded sequence as ``frames`` over Zenoh."""

from shared.registry import SERVICES, ServiceEntry

SERVICES.register(
    "source",
    ServiceEntry("replays a recorded sequence (or a live ROS 2 robot) as frames; runs as `trackgraph source`"),
)
