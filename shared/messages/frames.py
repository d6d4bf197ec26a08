"""Frames from the source, and tracked frames from the tracker."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field, field_validator, model_validator

from shared.arrays import ArraySpec
from shared.geometry import Intrinsics, is_rigid
from shared.messages.base import SECONDS, Message, Units, register

RGB = Annotated[np.ndarray, ArraySpec(("uint8",), (None, None, 3), kind="rgb")]
Depth = Annotated[np.ndarray, ArraySpec(("uint16",), (None, None), kind="depth")]
Labels = Annotated[np.ndarray, ArraySpec(("int32",), (None, None), kind="label")]
Confidence = Annotated[np.ndarray, ArraySpec(("uint8",), (None, None), kind="label")]
Pose4 = Annotated[np.ndarray, ArraySpec(("float64",), (4, 4), finite=True)]


@register
class Frame(Message):
    """One RGB-D observation with its pose (``frames``)."""

    frame_index: int = Field(ge=0)
    """Index of the frame in its sequence (after striding, the original index)."""
    time_s: Annotated[float, SECONDS] = 0.0
    """Capture time in seconds."""
    rgb: RGB
    """(H, W, 3) uint8 colour image."""
    depth: Annotated[Depth, Units("1 / depth_scale m")]
    """(H, W) uint16 depth; metres = depth / depth_scale; 0 means no reading."""
    depth_scale: Annotated[float, Units("1 / m")] = Field(gt=0)
    """Depth units per metre (Replica 6553.5, TUM 5000, millimetres 1000)."""
    intrinsics: Intrinsics
    """Pinhole intrinsics at the resolution of ``rgb``."""
    T_world_cam: Annotated[Pose4, Units("m (translation)")]
    """(4, 4) camera-to-world pose, OpenCV camera axes (x right, y down, z forward)."""

    @field_validator("T_world_cam")
    @classmethod
    def _rigid(cls, v: np.ndarray) -> np.ndarray:
        """``T_world_cam`` is a rigid transform: an orthonormal rotation with determinant 1 and last row 0 0 0 1,
        each within 1e-3."""
        if not is_rigid(v):
            raise ValueError("T_world_cam is not a rigid transform")
        return v

    @model_validator(mode="after")
    def _sizes(self) -> Frame:
        """``depth`` is the size of ``rgb``, and ``intrinsics`` are for that size."""
        h, w = self.rgb.shape[:2]
        if self.depth.shape != (h, w):
            raise ValueError(f"depth shape {self.depth.shape} differs from rgb {(h, w)}")
        if (self.intrinsics.width, self.intrinsics.height) != (w, h):
            raise ValueError(
                f"intrinsics are for {self.intrinsics.width}x{self.intrinsics.height}, image is {w}x{h}"
            )
        return self

    def depth_m(self) -> Annotated[np.ndarray, "(H, W) float32 metres"]:
        return self.depth.astype(np.float32) / np.float32(self.depth_scale)


@register
class EndOfSequence(Message):
    """Sent by the source after the last frame of a sequence (``frames/end``), and passed on
    by the tracker once it has emitted everything for it (``tracks/end``)."""

    frames_published: int = Field(ge=0)
    """Frames put on the wire."""
    frames_dropped: int = Field(ge=0)
    """Frames dropped in live mode because a subscriber lagged."""
    last_frame_index: int = Field(ge=-1)
    """Index of the last frame published, -1 if none."""
    track_features_published: int | None = Field(None, ge=0)
    """On ``tracks/end``: how many ``tracks/features`` messages the tracker sent, so fusion
    can tell it has them all (the last keyframe's CLIP features come after its last frame)."""


@register
class FrameAck(Message):
    """``frames/ack``: a stage of the pipeline has finished with a frame. In lossless replay
    the source keeps at most ``source.window_frames`` frames ahead of the slowest stage it
    hears from, so no queue between them grows and no Zenoh thread ever has to wait."""

    frame_index: int = Field(ge=0)
    """The frame done with."""
    service: str = Field(min_length=1, max_length=32)
    """Who is done with it (``tracker``, ``fusion``)."""
    epoch: int | None = Field(None, ge=0)
    """fusion's acks: a number drawn when the fusion process started. A new one tells the
    tracker that fusion restarted, so it sends again what that fusion has not acknowledged."""
    features_through: int | None = Field(None, ge=0)
    """fusion's acks: every ``tracks/features`` message with a ``serial`` below this is in
    fusion's journal (or its map), so the tracker may let it go."""


class TrackObservation(Message):
    """What eq. 6 needs to weigh one track's mask in this frame."""

    track_id: int = Field(ge=0)
    """Source-track id, as in ``track_ids``."""
    keyframe: bool
    """True if this mask is a keyframe detection (gamma = 1 in eq. 6)."""
    frames_since_keyframe: int = Field(ge=0)
    """Delta_t(tau): frames since the last keyframe detection assigned to the track."""


@register
class TrackedFrame(Message):
    """A frame with its per-pixel source-track ids (``tracks/frame``)."""

    frame: Frame
    """The observation itself."""
    track_ids: Labels
    """(H, W) int32 source-track id per pixel, -1 for none."""
    tracks: list[TrackObservation]
    """One entry per track id present in ``track_ids``."""
    keyframe: bool = False
    """True if this frame was a keyframe."""
    confidence: Confidence | None = None
    """(H, W) probability of each pixel's track under the propagated distribution (eq. 1),
    scaled to 0-255; None where the labels are not propagated (keyframe masks)."""
    order: int | None = Field(None, ge=0)
    """Position in the tracker's output to fusion, numbered together with the feature
    messages (``TrackFeatures.order``), so fusion applies both in the order they were sent.
    None: applied as it comes."""
    stream: int | None = Field(None, ge=0)
    """The tracker's epoch, drawn at its start: a new one tells fusion ``order`` starts again."""

    @model_validator(mode="after")
    def _consistent(self) -> TrackedFrame:
        """``track_ids`` (and ``confidence``) are the size of the frame; ``tracks`` lists no track id twice."""
        if self.track_ids.shape != self.frame.depth.shape:
            raise ValueError(f"track_ids shape {self.track_ids.shape} differs from the frame {self.frame.depth.shape}")
        if self.confidence is not None and self.confidence.shape != self.track_ids.shape:
            raise ValueError(f"confidence shape {self.confidence.shape} differs from track_ids {self.track_ids.shape}")
        ids = [t.track_id for t in self.tracks]
        if len(ids) != len(set(ids)):
            raise ValueError("tracks lists a track id twice")
        return self
