"""keyframe_vl: class-agnostic masks and CLIP features at keyframes, and the embedding API."""

from shared.registry import SERVICES, ServiceEntry

SERVICES.register(
    "keyframe_vl",
    ServiceEntry("FastSAM masks and CLIP features at keyframes, the vl/embed queryable", node="services.keyframe_vl.node:build"),
)
