"""Keyframe requests, masks and CLIP features, and track features."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from shared.arrays import ArraySpec
from shared.geometry import Intrinsics
from shared.messages.base import PIXELS, Message, Units, register
from shared.messages.frames import RGB, Depth

Masks = Annotated[np.ndarray, ArraySpec(("bool",), (None, None, None), kind="mask")]
Boxes = Annotated[np.ndarray, ArraySpec(("float32",), (None, 4), finite=True)]
Scores = Annotated[np.ndarray, ArraySpec(("float32",), (None,), finite=True)]
FeatureRows = Annotated[np.ndarray, ArraySpec(("float32", "float16"), (None, None), finite=True)]
Vector = Annotated[np.ndarray, ArraySpec(("float32", "float16"), (None,), finite=True)]


@register
class KeyframeRequest(Message):
    """Ask keyframe_vl for masks and CLIP features of one keyframe (``keyframe/request``)."""

    frame_index: int = Field(ge=0)
    """The keyframe's frame index; replies carry it back."""
    rgb: RGB
    """(H, W, 3) uint8 image (JPEG over the network)."""
    depth: Annotated[Depth | None, Units("1 / depth_scale m")] = None
    """(H, W) uint16 depth, for the classical RGB-D segmenter."""
    depth_scale: Annotated[float | None, Units("1 / m")] = Field(None, gt=0)
    """Depth units per metre, with ``depth``."""
    intrinsics: Intrinsics | None = None
    """Intrinsics, with ``depth``."""

    @model_validator(mode="after")
    def _sizes(self) -> KeyframeRequest:
        """``depth``, when given, is the size of ``rgb`` and comes with ``depth_scale``."""
        hw = self.rgb.shape[:2]
        if self.depth is not None and self.depth.shape != hw:
            raise ValueError(f"depth shape {self.depth.shape} differs from rgb {hw}")
        if self.depth is not None and self.depth_scale is None:
            raise ValueError("depth needs depth_scale")
        return self


@register
class KeyframeMasks(Message):
    """Class-agnostic masks of one keyframe, sent as soon as segmentation ends (``keyframe/masks``)."""

    frame_index: int = Field(ge=0)
    """The keyframe's frame index."""
    masks: Masks
    """(N, H, W) bool masks."""
    boxes: Annotated[Boxes, PIXELS]
    """(N, 4) float32 boxes x0, y0, x1, y1 in pixels."""
    scores: Scores
    """(N,) float32 segmenter confidences."""
    error: str | None = None
    """Set, with N = 0, when the keyframe could not be segmented."""

    @model_validator(mode="after")
    def _counts(self) -> KeyframeMasks:
        """``masks``, ``boxes`` and ``scores`` have the same number N of rows."""
        n = self.masks.shape[0]
        if self.boxes.shape[0] != n or self.scores.shape[0] != n:
            raise ValueError(f"{n} masks but {self.boxes.shape[0]} boxes and {self.scores.shape[0]} scores")
        return self


@register
class MaskFeatures(Message):
    """One CLIP feature per mask of a keyframe, sent when CLIP finishes (``keyframe/features``)."""

    frame_index: int = Field(ge=0)
    """The keyframe's frame index."""
    features: FeatureRows
    """(N, D) L2-normalised CLIP features, row i for mask i of the KeyframeMasks."""
    model: str
    """Encoder name, so features from different models are never mixed."""
    error: str | None = None
    """Set, with N = 0, when the features could not be computed."""
    view: Vector | None = None
    """(D,) L2-normalised embedding of the whole keyframe, in the space of ``features``: what
    the place looks like, for naming the room the camera is in. None from an encoder that
    does not make one (fusion then names rooms from their segments alone)."""


class TrackFeature(Message):
    """A source track's aggregated features (tau_i in III-B)."""

    track_id: int = Field(ge=0)
    """Source-track id."""
    dino: Vector
    """Aggregated DINOv3 feature (EMA, eta in III-B)."""
    clip: Vector | None = None
    """Running-mean CLIP feature (eq. 4); None until the first CLIP feature arrives."""
    clip_count: int = Field(0, ge=0)
    """n_i^ov, CLIP features folded into ``clip``."""

    @model_validator(mode="after")
    def _clip_count(self) -> TrackFeature:
        """``clip`` and ``clip_count`` are both set (count >= 1) or both empty."""
        if (self.clip is None) != (self.clip_count == 0):
            raise ValueError("clip and clip_count must be both set or both empty")
        return self


@register
class TrackFeatures(Message):
    """Track features that changed since the last message (``tracks/features``)."""

    frame_index: int = Field(ge=0)
    """Frame at which these values hold."""
    tracks: list[TrackFeature]
    """Changed tracks."""
    retired: list[int] = Field(default_factory=list)
    """Tracks retired at this frame."""
    serial: int | None = Field(None, ge=0)
    """The tracker's running number of this message (0, 1, ... in the order sent). A message
    sent again after a fusion restart keeps it, so fusion applies each one once. None from a
    sender that never sends again."""
    order: int | None = Field(None, ge=0)
    """Position in the tracker's output to fusion: tracked frames and feature messages are
    numbered together from 0, so fusion applies them in the order they were sent, whatever
    overtakes what on the way (a resend after a fusion restart). None: applied as it comes."""
    stream: int | None = Field(None, ge=0)
    """The tracker's epoch, drawn at its start: a new one tells fusion ``order`` starts again."""
    view: Vector | None = None
    """The keyframe ``frame_index``'s whole-image embedding (``MaskFeatures.view``), passed on
    by the tracker for fusion's room features; None when the keyframe had none."""
