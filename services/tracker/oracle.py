"""A tracker with perfect identities, for synthetic scenes: masks are the ground-truth
instances, and an object keeps its track while in view. It isolates the fusion stages from
tracking errors (``tracker.mode: ground_truth``, ground-truth tracked frames) and gives the upper bound of the
mapping. Like a real tracker it can retire a track whose object left the view and start a
new one when it returns, which is what long-term re-identification must merge.

The identities come from an :class:`~shared.datasets.ground_truth.InstanceSource` (by default
the sequence folder of ``tracker.ground_truth``), read by frame index: a :class:`Frame`
carries no ground truth.

With an encoder, each keyframe's crops are embedded here (no keyframe_vl), and so is its
view (``encode_view``, when the encoder has one): the TrackFeatures taken for that frame
carries it, even when no track changed."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import numpy as np

from shared.datasets.ground_truth import GroundTruthError, InstanceSource, SequenceGroundTruth
from shared.messages.frames import Frame, TrackedFrame, TrackObservation
from shared.messages.keyframes import TrackFeature, TrackFeatures
from shared.perception import KeyframeImage, Masks, VLEncoder

log = logging.getLogger(__name__)

DINO_DIM = 64


def identity_feature(track_id: int, dim: int = DINO_DIM) -> Annotated[np.ndarray, "(dim,) float32 unit"]:
    """A fixed random unit vector per object: distinct objects are nearly orthogonal, the
    same object always matches itself, as a perfect appearance descriptor would."""
    v = np.random.default_rng(1_000_003 + track_id).standard_normal(dim)
    return (v / np.linalg.norm(v)).astype(np.float32)


class GroundTruthTracker:
    """A :class:`~services.tracker.protocol.FrameTracker`: the call protocol of
    :class:`services.tracker.core.TrackerCore`, minus the masks (it asks for none)."""

    takes_masks = False
    """Identities come from the ground truth: keyframe_vl's answers are not for it."""

    def __init__(
        self,
        keyframe_interval: int = 24,
        encoder: VLEncoder | None = None,
        retire_frames: int = 0,
        ground_truth: InstanceSource | str | Path | None = None,
    ) -> None:
        """``ground_truth`` is the source of each frame's instance ids, or the sequence folder
        to read them from (``tracker.ground_truth``)."""
        if ground_truth is None or isinstance(ground_truth, (str, Path)):
            ground_truth = SequenceGroundTruth(ground_truth, field="tracker.ground_truth", user="ground_truth tracker")
        self.ground_truth = ground_truth
        self.keyframe_interval = keyframe_interval
        self.encoder = encoder
        self.retire_frames = retire_frames
        self.count = 0
        self.track_of: dict[int, int] = {}
        """Object id -> its current track id."""
        self.object_of: dict[int, int] = {}
        self.last_seen: dict[int, int] = {}
        self.next_track = 0
        self.clip: dict[int, tuple[np.ndarray, int]] = {}
        self.changed: set[int] = set()
        self._frame: Frame | None = None
        self._view: tuple[int, np.ndarray] | None = None
        """The last keyframe's index and view, until the TrackFeatures of that frame takes it."""

    def begin_frame(self, frame: Frame) -> None:
        try:
            instances = np.asarray(self.ground_truth.frame_instances(frame.frame_index))
        except GroundTruthError as exc:
            raise GroundTruthError(f"Frame {frame.frame_index}: the ground_truth tracker has no ground truth: {exc}") from None
        if instances.shape != frame.depth.shape:
            raise GroundTruthError(
                f"Frame {frame.frame_index}: the ground-truth instances are {instances.shape[1]}x{instances.shape[0]} but the frame "
                f"is {frame.depth.shape[1]}x{frame.depth.shape[0]}: is tracker.ground_truth the sequence being replayed?"
            )
        self._frame = frame
        objects = [int(i) for i in np.unique(instances) if i >= 0]
        for obj in objects:
            gone = self.count - self.last_seen.get(obj, self.count)
            if obj not in self.track_of or (self.retire_frames and gone > self.retire_frames):
                self.track_of[obj] = self.next_track
                self.object_of[self.next_track] = obj
                self.changed.add(self.next_track)
                self.next_track += 1
            self.last_seen[obj] = self.count
        lut = np.full(max(objects, default=0) + 1, -1, np.int32)
        for obj in objects:
            lut[obj] = self.track_of[obj]
        self._labels = np.where(instances >= 0, lut[np.maximum(instances, 0)], -1).astype(np.int32)
        if self.encoder is not None and self.count % self.keyframe_interval == 0:
            image = KeyframeImage(frame_index=frame.frame_index, rgb=frame.rgb, depth_m=frame.depth_m(), intrinsics=frame.intrinsics)
            self._embed(image, instances, objects)
            self._take_view(image)
        self.count += 1
        return None

    def _take_view(self, image: KeyframeImage) -> None:
        """Keep the keyframe's view for its TrackFeatures; an encoder without ``encode_view``,
        or one that fails, leaves none (the crops' features still go out)."""
        encode_view = getattr(self.encoder, "encode_view", None)
        self._view = None
        if encode_view is None:
            return
        try:
            self._view = (image.frame_index, np.asarray(encode_view(image), np.float32))
        except Exception as exc:  # noqa: BLE001 - a view is an extra; tracking goes on without it
            log.warning("keyframe %d: no view from %s (%s: %s)", image.frame_index, self.encoder.name, type(exc).__name__, exc)

    def _embed(self, image: KeyframeImage, instances: np.ndarray, ids: list[int]) -> None:
        masks = instances[None] == np.asarray(ids)[:, None, None]
        keep = masks.reshape(len(ids), -1).sum(1) >= 50
        if not keep.any():
            return
        ids = [i for i, k in zip(ids, keep, strict=True) if k]
        masks = masks[keep]
        boxes = np.stack([_box(m) for m in masks]).astype(np.float32)
        feats = self.encoder.encode_crops(image, Masks(masks, boxes, np.ones(len(ids), np.float32)))
        for obj, f in zip(ids, feats, strict=True):
            tid = self.track_of[obj]
            mean, n = self.clip.get(tid, (np.zeros_like(f), 0))
            self.clip[tid] = ((n * mean + f) / (n + 1), n + 1)
            self.changed.add(tid)

    def end_frame(self) -> TrackedFrame:
        fr = self._frame
        assert fr is not None
        labels = self._labels
        obs = [TrackObservation(track_id=int(t), keyframe=True, frames_since_keyframe=0) for t in np.unique(labels) if t >= 0]
        return TrackedFrame(frame=fr, track_ids=labels, tracks=obs, keyframe=True)

    def take_track_features(self, frame_index: int) -> TrackFeatures | None:
        """Changed tracks since the last call, with the view of keyframe ``frame_index`` if it
        has one; None if neither."""
        view = None
        if self._view is not None and self._view[0] <= frame_index:
            # A view of an earlier frame was never taken (that frame failed): it is dropped,
            # as fusion would place it at the wrong keyframe.
            kept, self._view = self._view, None
            view = kept[1] if kept[0] == frame_index else None
        if not self.changed and view is None:
            return None
        out = []
        for tid in sorted(self.changed):
            mean, n = self.clip.get(tid, (None, 0))
            out.append(TrackFeature(track_id=tid, dino=identity_feature(self.object_of[tid]), clip=mean, clip_count=n))
        self.changed.clear()
        return TrackFeatures(frame_index=frame_index, tracks=out, view=view)


def _box(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float32)
