"""What the tracker session drives: the typed protocols of a tracker core.

Two cores satisfy them: :class:`~services.tracker.core.TrackerCore` propagates tracks between
keyframes and takes keyframe_vl's masks and CLIP features (a :class:`MaskTracker`); the
ground-truth tracker (:mod:`services.tracker.oracle`) reads identities from the sequence's
ground truth, asks for no keyframe and takes no answer (a :class:`FrameTracker` only).
"""

from __future__ import annotations

from typing import Annotated, Protocol

import numpy as np

from shared.messages.frames import Frame, TrackedFrame
from shared.messages.keyframes import KeyframeRequest, TrackFeatures
from shared.perception import Masks


class FrameTracker(Protocol):
    """A frame begun (a keyframe asks for its masks), ended into its tracks, and the features
    of the tracks changed since the last take."""

    takes_masks: bool
    """Whether the core is a :class:`MaskTracker`, applying keyframe_vl's masks and CLIP
    features; when not, its identities come from elsewhere and a stray answer is dropped."""

    def begin_frame(self, frame: Frame) -> KeyframeRequest | None:
        """Start tracking ``frame``; the request for its masks when it is a keyframe."""

    def end_frame(self) -> TrackedFrame:
        """The tracks of the frame begun last."""

    def take_track_features(self, frame_index: int) -> TrackFeatures | None:
        """The tracks changed since the last call, sent with frame ``frame_index``; None if none."""


class MaskTracker(FrameTracker, Protocol):
    """A tracker corrected at each keyframe by keyframe_vl's answers (``takes_masks`` True)."""

    def apply_masks(self, frame_index: int, masks: Masks) -> bool:
        """Correct the tracks at keyframe ``frame_index``; False if it is no longer held (stale)."""

    def apply_features(self, frame_index: int, features: Annotated[np.ndarray, "(N, D) float32"]) -> None:
        """The CLIP features of keyframe ``frame_index``'s masks, in their order."""
