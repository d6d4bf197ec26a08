"""One pydantic model per wire message; ``docs/wire.md`` is generated from them."""

from shared.messages.base import REGISTRY, Envelope, Message, register
from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame, TrackObservation
from shared.messages.graph import (
    Edge,
    GraphDelta,
    GraphSnapshot,
    MeshChunk,
    PlaceNode,
    RoomNode,
    SegmentNode,
    SnapshotRequest,
)
from shared.messages.keyframes import (
    KeyframeMasks,
    KeyframeRequest,
    MaskFeatures,
    TrackFeature,
    TrackFeatures,
)
from shared.messages.poses import PoseCorrection
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryHit, QueryReply, QueryRequest
from shared.messages.status import InputCounters, ServiceStatus

__all__ = [
    "REGISTRY",
    "Edge",
    "EmbedReply",
    "EmbedRequest",
    "EndOfSequence",
    "Envelope",
    "Frame",
    "InputCounters",
    "FrameAck",
    "GraphDelta",
    "GraphSnapshot",
    "KeyframeMasks",
    "KeyframeRequest",
    "MaskFeatures",
    "MeshChunk",
    "PoseCorrection",
    "Message",
    "PlaceNode",
    "QueryHit",
    "QueryReply",
    "QueryRequest",
    "RoomNode",
    "SegmentNode",
    "ServiceStatus",
    "SnapshotRequest",
    "TrackFeature",
    "TrackFeatures",
    "TrackObservation",
    "TrackedFrame",
    "register",
]
