"""One pydantic model per wire message (DESIGN.md section 2)."""

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
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryHit, QueryReply, QueryRequest

__all__ = [
    "REGISTRY",
    "Edge",
    "EmbedReply",
    "EmbedRequest",
    "EndOfSequence",
    "Envelope",
    "Frame",
    "FrameAck",
    "GraphDelta",
    "GraphSnapshot",
    "KeyframeMasks",
    "KeyframeRequest",
    "MaskFeatures",
    "MeshChunk",
    "Message",
    "PlaceNode",
    "QueryHit",
    "QueryReply",
    "QueryRequest",
    "RoomNode",
    "SegmentNode",
    "SnapshotRequest",
    "TrackFeature",
    "TrackFeatures",
    "TrackObservation",
    "TrackedFrame",
    "register",
]
