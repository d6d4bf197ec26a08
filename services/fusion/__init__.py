"""fusion: TSDF with source-track hypotheses, persistent 3D segments, re-identification and the
hierarchical scene graph (paper sections III-A, III-C, III-D, III-E)."""

from shared.registry import SERVICES, ServiceEntry

SERVICES.register(
    "fusion",
    ServiceEntry(
        "TSDF, segments, places, rooms and the scene graph",
        node="services.fusion.node:build",
        out="dir",
        out_help="fusion needs --out MAP_DIR for its snapshots and the final map",
    ),
)
