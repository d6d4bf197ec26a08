"""Map viewer: Rerun recordings of the scene graph, PNG renders, and the live viewer node."""

from shared.registry import SERVICES, ServiceEntry

SERVICES.register(
    "viewer",
    ServiceEntry(
        "Rerun recording of the live map",
        node="services.viewer.node:build",
        out="file",
        out_help="the viewer needs --out FILE.rrd for its recording",
    ),
)
