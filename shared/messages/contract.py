"""Who talks on which key, how: the table ``docs/wire.md`` is generated from.

Every key of :class:`shared.topics.Topics` has one :class:`KeyContract`: its message type
(and reply type for a queryable), its delivery, the QoS of its publisher, which service
declares it, and who listens and with which subscriber policy. ``tests/shared/messages``
checks that the table covers every key ``Topics`` has.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import BaseModel

from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, SnapshotRequest
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures, TrackFeatures
from shared.messages.poses import PoseCorrection
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryReply, QueryRequest
from shared.messages.status import ServiceStatus

Delivery = Literal["pub/sub", "query/reply", "liveliness"]
Policy = Literal["fifo", "latest", "request"]


@dataclass(frozen=True)
class Listener:
    """One consumer of a key."""

    service: str
    """Who (a service name, or ``clients`` for anyone outside the system)."""
    policy: Policy
    """``fifo``: a bounded queue in order that drops the newest message when full (and
    counts it); ``latest``: keeps the newest messages only; ``request``: asks a queryable."""
    note: str = ""
    """When it listens, or why this policy."""


@dataclass(frozen=True)
class KeyContract:
    """One key of the wire."""

    name: str
    """Attribute of :class:`shared.topics.Topics` (``status`` and ``alive`` take a service)."""
    key: str
    """The key expression, with ``<robot_id>`` (and ``<service>``) placeholders."""
    delivery: Delivery
    message: type[BaseModel] | None
    """What is published, or the request of a queryable; None for a liveliness token."""
    reply: type[BaseModel] | None
    """The reply of a queryable."""
    declared_by: tuple[str, ...]
    """The publishers, the queryable, or the token's owners."""
    listeners: tuple[Listener, ...]
    summary: str
    congestion: Literal["BLOCK", "DROP"] | None = "BLOCK"
    """Publisher congestion control (replies and tokens: None)."""


_R = "trackgraph/<robot_id>"

CONTRACT: tuple[KeyContract, ...] = (
    KeyContract(
        "frames", f"{_R}/frames", "pub/sub", Frame, None, ("source",),
        (Listener("tracker", "fifo", "replay: the source stays source.window_frames ahead of frames/ack"),
         Listener("tracker", "latest", "live (source.mode: live): the newest frames only")),
        "RGB-D frames with their poses, in order.",
    ),
    KeyContract(
        "end_of_sequence", f"{_R}/frames/end", "pub/sub", EndOfSequence, None, ("source",),
        (Listener("tracker", "fifo"),), "After the last frame of a recorded sequence.",
    ),
    KeyContract(
        "frame_ack", f"{_R}/frames/ack", "pub/sub", FrameAck, None, ("tracker", "fusion"),
        (Listener("source", "fifo", "lossless replay paces itself on the slowest stage"),),
        "A stage is done with a frame.",
    ),
    KeyContract(
        "keyframe_request", f"{_R}/keyframe/request", "pub/sub", KeyframeRequest, None, ("tracker",),
        (Listener("keyframe_vl", "fifo"),), "Every K_f-th frame, for masks and CLIP features.",
    ),
    KeyContract(
        "keyframe_masks", f"{_R}/keyframe/masks", "pub/sub", KeyframeMasks, None, ("keyframe_vl",),
        (Listener("tracker", "fifo"),),
        "Class-agnostic masks of a keyframe, as soon as segmentation ends (one per request, `error` set on failure).",
    ),
    KeyContract(
        "keyframe_features", f"{_R}/keyframe/features", "pub/sub", MaskFeatures, None, ("keyframe_vl",),
        (Listener("tracker", "fifo"),),
        "One CLIP feature per mask of a keyframe, after its masks (`error` set on failure).",
    ),
    KeyContract(
        "tracks_frame", f"{_R}/tracks/frame", "pub/sub", TrackedFrame, None, ("tracker",),
        (Listener("fusion", "fifo"), Listener("viewer", "latest", "shows the newest frame only"),
         Listener("ros2", "latest", "the trajectory as a nav_msgs/Path")),
        "Each frame with its per-pixel source-track ids.",
    ),
    KeyContract(
        "tracks_features", f"{_R}/tracks/features", "pub/sub", TrackFeatures, None, ("tracker",),
        (Listener("fusion", "fifo"),), "Track features that changed, and each keyframe's view embedding.",
    ),
    KeyContract(
        "tracks_end", f"{_R}/tracks/end", "pub/sub", EndOfSequence, None, ("tracker",),
        (Listener("fusion", "fifo"),), "The tracker has emitted everything for the sequence.",
    ),
    KeyContract(
        "poses_correction", f"{_R}/poses/correction", "pub/sub", PoseCorrection, None, ("source",),
        (Listener("fusion", "fifo", "held until it has fused apply_after_frame; journaled with the frames"),),
        "Corrected poses of past frames after a loop closure, from a SLAM back end (any client may publish; "
        "the source replays a recorded one, source.corrections, or sends a ROS 2 SLAM's, ros2.input.corrections).",
    ),
    KeyContract(
        "graph_delta", f"{_R}/graph/delta", "pub/sub", GraphDelta, None, ("fusion",),
        (Listener("query", "fifo"), Listener("viewer", "fifo"), Listener("ros2", "fifo", "MarkerArray for RViz"),
         Listener("clients", "fifo", "a gap in graph_seq: ask graph/snapshot")),
        "Scene-graph changes, numbered by graph_seq.",
    ),
    KeyContract(
        "graph_snapshot", f"{_R}/graph/snapshot", "query/reply", SnapshotRequest, GraphSnapshot, ("fusion",),
        (Listener("query", "request", "at start and after a gap"), Listener("viewer", "request"), Listener("ros2", "request"),
         Listener("clients", "request")),
        "The whole graph at its current version.", congestion=None,
    ),
    KeyContract(
        "vl_embed", f"{_R}/vl/embed", "query/reply", EmbedRequest, EmbedReply, ("keyframe_vl",),
        (Listener("query", "request", "query.embed: remote"),
         Listener("fusion", "request", "the room labels (fusion.graph.room_labels), once, retried until answered"),
         Listener("clients", "request")),
        "A text or image in the VL encoder's space.", congestion=None,
    ),
    KeyContract(
        "query", f"{_R}/query", "query/reply", QueryRequest, QueryReply, ("query",),
        (Listener("clients", "request", "trackgraph query --live, services.query.client.QueryClient"),
         Listener("ros2", "request", "queries from ROS 2 (ros2.output.query_topic)")),
        "Ranked segments for a text or image query (eq. 10).", congestion=None,
    ),
    KeyContract(
        "status", f"{_R}/status/<service>", "pub/sub", ServiceStatus, None,
        ("source", "tracker", "keyframe_vl", "fusion", "query", "viewer", "ros2"),
        (Listener("launcher", "latest", "trackgraph launch's table"), Listener("clients", "latest", "trackgraph status, the bench")),
        "Each service's counters and progress, once a second and once at stop.",
    ),
    KeyContract(
        "alive", f"{_R}/alive/<service>", "liveliness", None, None,
        ("source", "tracker", "keyframe_vl", "fusion", "query", "viewer", "ros2"),
        (Listener("launcher", "latest", "a token gone for launch.unresponsive_s restarts the service"),),
        "A Zenoh liveliness token per running service (no payload).", congestion=None,
    ),
)  # fmt: skip


def contract(name: str) -> KeyContract:
    """The contract of the key ``Topics.<name>``."""
    for c in CONTRACT:
        if c.name == name:
            return c
    raise KeyError(f"no wire contract for key {name!r}")
