"""tracker: source-track propagation between keyframes and keyframe correction (paper III-B)."""

from shared.registry import SERVICES, ServiceEntry

SERVICES.register(
    "tracker",
    ServiceEntry("source tracks between keyframes", node="services.tracker.node:build"),
)
