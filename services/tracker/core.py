"""The tracker core (paper III-B): source tracks carried between keyframes by DINOv3 label
propagation, corrected at keyframes by the segmenter's masks. No Zenoh here.

The core is asynchronous by design, so the same code serves the in-process pipeline and the
distributed node:

* ``begin_frame(frame)`` computes features, propagates the soft track distribution from the
  keyframe and recent frames (eq. 1), and returns a KeyframeRequest every K_f frames;
* ``apply_masks(frame_index, masks)`` corrects at that keyframe (eqs. 2-3), whenever the
  masks arrive, and re-propagates the frames after it from the feature history, so late
  masks give the same track ids as timely ones;
* ``apply_features(frame_index, features)`` folds CLIP features into the tracks (eq. 4);
* ``end_frame()`` gives the newest frame's TrackedFrame.

The in-process pipeline calls begin, apply (at once) and end; the node sends the request,
ends the frame at once, and applies the masks when they come.

Deviation: asynchronous masks (docs/method.md, T4). In the paper the keyframe's masks are at hand
when the keyframe is processed. Here keyframe_vl may be a remote GPU, so masks may come after
later frames; ``apply_masks`` corrects the keyframe then and re-propagates the kept frames
after it. A live tracker has already sent those frames, labelled from the previous keyframe;
``tracker.wait_for_masks`` holds each keyframe instead (lossless replay).

Deviation: keyframe labels start soft (docs/method.md, T5). ``masks_to_soft`` gives each patch
the share of its pixels in each mask, and a "no track" slot, rather than the paper's one-hot.

Keyframe correction follows III-B: the propagated masks of the active tracks are scored
against the detections with eq. 3 (w_iou IoU + w_feat max(cos, 0), the cosine between the
track's EMA DINOv3 feature and the eq. 2 prototype), pairs need IoU >= 0.15 and s >= 0.35,
and the greedy one-to-one assignment in descending s continues tracks; matched tracks update
their feature with the EMA (eta 0.2) and unmatched detections start tracks. Keyframe labels
paint larger masks first, so an object lying on a larger one keeps its own id; pixels no mask
covers form slot 0 ("no track"), propagated like any other slot.

Deviation (docs/method.md, T1): retiring unmatched tracks. The paper retires every active track left unmatched at a
keyframe and leaves re-identification to the 3D layer (III-E). Here such a track becomes
*lost* instead, and the detections the active tracks did not take are associated with the lost
tracks in a second pass with the same eq. 3 score, gates and greedy rule, a lost track's
predicted mask being its *footprint* (the world points under its keyframe masks, from the
keyframe's depth and pose) projected into this keyframe with a depth test
(``services.tracker.footprints``). A track matched there keeps its id. Why: the tracking
evaluation (``trackgraph eval tracking``) scores 2D identities over the whole sequence and counts a switch when an
object comes back under a new id, and a track goes unmatched for reasons that say nothing
about the object being gone: the segmenter missed, split or merged it at that keyframe, a
small object vanished from the propagated labels, or it left the view for a while. With
perfect masks and perfect propagation, retiring at once bounds IDF1 at 0.78 on the ``small``
preset (K_f = 24; 0.71 at K_f = 8) and at 0.63 on ``revisit``, whose camera comes back to the
first room (ground-truth simulation of that policy). Tracks are retired for good, and reported
in ``TrackFeatures.retired``, when the bounded lost pool (``tracks.MAX_LOST``) evicts its
longest-lost track, or when a lost track's footprint overlaps a detection it did not get at
IoU >= ``tracker.association.duplicate_iou`` (another track holds that surface now).
Propagation, as in the paper, carries the active tracks only.

Deviation (docs/method.md, T2): a static-world check on the first pass (``AssociationConfig.support_*``). Eq. 3 is
purely 2D, so when an object leaves the view its propagated label slides onto whatever comes in
next to it, and at the keyframe that neighbour's detection continues the departed track (the
commonest identity switch measured on the synthetic presets). The tracker has depth and poses,
so a pair also needs 3D support: some of the detection's back-projected points must lie near
the track's footprint, and not much fewer than near the best-supported candidate's. On the
``small`` preset this took switches from 1.04 to 0.75 per object per 100 frames (IDF1 0.655 to
0.679), and from 0.63 to 0.25 with noise-free masks. It assumes a static scene: a track that
moves more than its own size between keyframes restarts; ``support_radius_m: 0`` turns it off.

Deviation (docs/method.md, T3): fragments. A detection that no track took, that lies mostly inside the predicted
mask of a track that took another detection, on that track's footprint and alike to the piece
it took (``_absorb_fragments``, thresholds in ``tracker.fragments``), joins that track: a
segmenter that cuts an object in two at one keyframe would otherwise leave a second track that
competes for the whole object at the next (IDF1 0.679 to 0.717 and 0.75 to 0.54 switches on
``small`` at default noise).

Mask prototypes (eq. 2) use the backend's ``appearance_dims`` leading channels: all of
DINOv3's, and the colour and texture blocks of the classical descriptor, whose depth block
changes with the viewpoint.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np
import torch

from services.tracker.association import (
    associate_iou,
    label_mask_iou,
    mask_prototypes,
    sparse_mask_iou,
)
from services.tracker.footprints import (
    Footprint,
    mask_footprint,
    merge_footprints,
    project_footprint,
    support,
)
from services.tracker.masks_numba import Boxes, mask_areas, mask_boxes
from services.tracker.propagation import (
    masks_to_soft,
    propagate_with_config,
    upsample_confidence,
    upsample_ids,
)
from services.tracker.tracks import TrackBook
from shared.config.tracker import TrackerConfig
from shared.messages.frames import Frame, TrackedFrame, TrackObservation
from shared.messages.keyframes import KeyframeRequest, TrackFeature, TrackFeatures
from shared.perception import Masks
from shared.perception.features.base import DenseFeatures

log = logging.getLogger(__name__)

SINGLE_THREAD_MAX_CELLS = 3072
"""Patch grids up to this size (e.g. 48 x 64) propagate and upsample on one CPU thread."""


@contextmanager
def cpu_threads(features: torch.Tensor) -> Iterator[None]:
    """One torch thread for the per-frame work on small CPU grids, restored afterwards.

    The tensors of a small grid are too small for torch's intra-op pool to pay: on the
    2-core CI machine shared with other jobs, the tracker ran 4x faster on one thread
    (30 x 40 grid: 7.4 against 1.8 frames/s), and oversubscribed threads only wait.
    """
    cells = features.shape[0] * features.shape[1]
    if features.device.type != "cpu" or cells > SINGLE_THREAD_MAX_CELLS or torch.get_num_threads() == 1:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@dataclass
class FrameState:
    """What the tracker remembers of one processed frame."""

    count: int
    frame: Frame
    features: Annotated[torch.Tensor, "(h, w, D) float32"]
    epoch: int = -1
    soft: Annotated[torch.Tensor, "(h, w, C) float32"] | None = None
    keyframe: bool = False
    labels: Annotated[np.ndarray, "(H, W) int32 track ids"] | None = None
    """Full-resolution keyframe labels once this frame's masks are applied."""
    detected: set[int] = field(default_factory=set)


class TrackerCore:
    """Source tracks over a frame stream; see the module docstring for the call protocol (a
    :class:`~services.tracker.protocol.MaskTracker`)."""

    takes_masks = True

    def __init__(self, cfg: TrackerConfig, features: DenseFeatures) -> None:
        self.cfg = cfg
        self.features = features
        self.book = TrackBook()
        self.history: deque[FrameState] = deque(maxlen=cfg.history_frames)
        self.count = 0
        self.epoch = 0
        self.epoch_slots: dict[int, list[int]] = {}
        self.anchor: FrameState | None = None
        """The keyframe of the current epoch: the reference every later frame propagates from."""
        self.mask_tracks: dict[int, list[int]] = {}
        self.pending_features: dict[int, np.ndarray] = {}
        self.stale_masks = 0

    # ------------------------------------------------------------------ frames

    def begin_frame(self, frame: Frame) -> KeyframeRequest | None:
        feats = self.features(frame.rgb, frame.depth_m())
        st = FrameState(count=self.count, frame=frame, features=feats)
        if self.anchor is not None and self.cfg.mode == "propagation":
            st.epoch = self.epoch
            with cpu_threads(feats):
                st.soft = self._propagate(st)
        self.history.append(st)
        self.count += 1
        st.keyframe = self.cfg.mode == "per_frame" or st.count % self.cfg.keyframe_interval == 0
        if not st.keyframe:
            return None
        return KeyframeRequest(
            frame_index=frame.frame_index,
            rgb=frame.rgb,
            depth=frame.depth,
            depth_scale=frame.depth_scale,
            intrinsics=frame.intrinsics,
        )

    def end_frame(self) -> TrackedFrame:
        """The newest frame with its per-pixel track ids and, on a propagated frame, how
        confident propagation is of each."""
        st = self.history[-1]
        confidence = None
        with cpu_threads(st.features):
            labels, present = self._labels_and_ids(st)
            if st.labels is None and st.soft is not None:
                confidence = upsample_confidence(st.soft, *labels.shape)
        obs = []
        for tid in present:
            track = self.book.tracks[int(tid)]
            obs.append(
                TrackObservation(
                    track_id=int(tid),
                    keyframe=int(tid) in st.detected,
                    frames_since_keyframe=max(0, st.count - track.last_detection),
                )
            )
        return TrackedFrame(
            frame=st.frame,
            track_ids=labels,
            tracks=obs,
            keyframe=bool(st.detected) or st.labels is not None,
            confidence=confidence,
        )

    # ------------------------------------------------------------------ keyframes

    def apply_masks(self, frame_index: int, masks: Masks) -> bool:
        """Keyframe correction at ``frame_index``; False if that frame is no longer usable."""
        st = self._state(frame_index)
        if st is None or (self.anchor is not None and st.count <= self.anchor.count):
            self.stale_masks += 1
            log.warning("masks for frame %d arrived too late or out of order; ignored", frame_index)
            return False
        with cpu_threads(st.features):
            self._correct(st, masks)
            if self.cfg.mode == "propagation":
                for later in self._after(st):
                    later.epoch = self.epoch
                    later.soft = self._propagate(later)
        self._prune()
        pending = self.pending_features.pop(frame_index, None)
        if pending is not None:
            self.apply_features(frame_index, pending)
        return True

    def _correct(self, st: FrameState, masks: Masks) -> None:
        """Eqs. 2-3 at one keyframe, then the keyframe's labels become the new anchor."""
        H, W = st.frame.depth.shape
        active = list(self.book.active)
        feats_np = st.features.float().cpu().numpy()
        boxes = mask_boxes(masks.masks)  # each mask is read only inside its box from here on
        det_feat = mask_prototypes(appearance(feats_np, self.features.appearance_dims), masks.masks, boxes)
        # The predicted masks of the active tracks are disjoint (one label per pixel): their
        # IoUs with the detections come from one slot image, not a stack of full masks.
        predicted = slot_image(self._predicted_labels(st, H, W), active)
        iou = label_mask_iou(predicted, len(active), masks.masks, boxes)
        depth = st.frame.depth_m()
        seen = [mask_footprint(m, depth, st.frame.intrinsics, st.frame.T_world_cam, box=tuple(b))
                for m, b in zip(masks.masks, boxes.tolist(), strict=True)]  # fmt: skip
        self._geometric_gate(active, seen, iou)
        a = associate_iou(iou, self._dino(active, det_feat.shape[-1]), det_feat, self.cfg.association)
        ids = [-1] * len(masks)
        for i, j in a.matches:
            ids[j] = active[i]
        self.book.lose([active[i] for i in a.retired_tracks], st.count)
        areas = mask_areas(masks.masks, boxes)
        revived = self._reidentify(st, masks.masks, det_feat, a.new_detections, ids, areas)
        absorbed = self._absorb_fragments(predicted, active, masks.masks, det_feat, seen, ids, boxes, areas)
        for j, tid in enumerate(ids):
            if tid >= 0:
                self.book.tracks[tid].detected(det_feat[j], st.count, self.cfg.association.ema)
                self.book.changed.add(tid)
            else:
                ids[j] = self.book.new(det_feat[j], st.count).id
        for j, tid in enumerate(ids):
            track = self.book.tracks[tid]
            track.footprint = merge_footprints(track.footprint, seen[j])
        self.book.active = list(ids)
        self.mask_tracks[st.frame.frame_index] = ids
        log.debug(
            "keyframe %d: %d masks, %d matched, %d re-identified, %d fragments, %d new, %d lost",
            st.frame.frame_index, len(ids), len(a.matches), revived, absorbed,
            len(ids) - len(a.matches) - revived - absorbed, len(self.book.lost),
        )

        st.labels = paint_labels(masks.masks, ids, H, W, boxes)
        st.detected = set(ids)
        self.epoch += 1
        self.epoch_slots[self.epoch] = list(ids)
        st.epoch = self.epoch
        st.soft = masks_to_soft(slot_image(st.labels, ids), *feats_np.shape[:2], num_slots=len(ids) + 1, device=st.features.device)
        self.anchor = st

    def _geometric_gate(self, active: list[int], seen: list[Footprint | None], iou: Annotated[np.ndarray, "(M, N) float32"]) -> None:
        """Veto (in place) the candidate pairs whose detection barely touches, in 3D, what
        the track was seen as at its keyframes (``support_min``), or touches it much less than
        it touches another candidate's (``support_relative`` of the best): the track's
        propagated label has drifted onto another object, typically one coming into view next
        to where the track's object left it, or onto a neighbour of similar colour. Pairs
        without a footprint on either side are kept."""
        cfg = self.cfg.association
        if cfg.support_radius_m <= 0 or iou.size == 0:
            return
        rows, cols = np.nonzero(iou >= cfg.iou_min)
        found: dict[tuple[int, int], float] = {}
        best = np.zeros(iou.shape[1], np.float32)
        trees: dict[int, Any] = {}  # one k-d tree per track footprint, whatever its candidates
        for i, j in zip(rows.tolist(), cols.tolist(), strict=True):
            fp = self.book.tracks[active[i]].footprint
            if fp is None or seen[j] is None:
                continue
            found[i, j] = v = support(fp, seen[j], cfg.support_radius_m, trees)
            best[j] = max(best[j], v)
        for (i, j), v in found.items():
            if v < cfg.support_min or v < cfg.support_relative * best[j]:
                iou[i, j] = 0.0

    def _absorb_fragments(
        self,
        predicted: Annotated[np.ndarray, "(H, W) int64 slot image of the active tracks"],
        active: list[int],
        masks: Annotated[np.ndarray, "(N, H, W) bool"],
        det_feat: Annotated[np.ndarray, "(N, D) float32"],
        seen: list[Footprint | None],
        ids: list[int],
        boxes: Boxes,
        areas: Annotated[np.ndarray, "(N,) int64"],
    ) -> int:
        """Detections left without a track that are a piece of an object whose track took
        another piece: mostly (``tracker.fragments.cover``) inside that track's predicted mask,
        mostly on the surface the track was seen as before (``tracker.fragments.support``, so a
        neighbour that propagation labelled with the track does not join it), and alike
        (``tracker.fragments.sim``, above eq. 7's theta_sim) to the piece it took. They join
        that track instead of starting one, so a segmenter that cuts an object in two at one
        keyframe does not leave a second track to compete for the whole object at the next.
        Fills ``ids`` in place; returns how many joined."""
        slot_of = {tid: s + 1 for s, tid in enumerate(active)}
        taken = {ids[j]: j for j in range(len(ids)) if ids[j] in slot_of}
        joined = 0
        frag, radius = self.cfg.fragments, self.cfg.association.support_radius_m
        for j in [j for j, tid in enumerate(ids) if tid < 0]:
            area = int(areas[j])
            if area == 0 or not taken:
                continue
            y0, y1, x0, x1 = boxes[j].tolist()
            inside = np.bincount(predicted[y0:y1, x0:x1][masks[j, y0:y1, x0:x1]], minlength=len(active) + 1)
            best = max(taken, key=lambda tid: inside[slot_of[tid]])
            if inside[slot_of[best]] < frag.cover * area:
                continue
            if float(det_feat[j] @ det_feat[taken[best]]) < frag.sim:
                continue
            fp = self.book.tracks[best].footprint
            if fp is not None and seen[j] is not None and support(fp, seen[j], radius) >= frag.support:
                ids[j] = best
                joined += 1
        return joined

    def _reidentify(
        self,
        st: FrameState,
        masks: Annotated[np.ndarray, "(N, H, W) bool"],
        det_feat: Annotated[np.ndarray, "(N, D) float32"],
        unmatched: list[int],
        ids: list[int],
        areas: Annotated[np.ndarray, "(N,) int64"] | None = None,
    ) -> int:
        """Second pass of eq. 3: detections no active track took, against the lost tracks,
        whose predicted masks are their footprints projected into this keyframe. Fills
        ``ids`` in place and returns how many tracks came back.

        A lost track that is not taken although its footprint overlaps a detection at
        IoU >= ``tracker.association.duplicate_iou`` is retired: another track already holds
        that surface, and keeping both would hand the object back and forth between them at
        later keyframes.
        """
        if not self.book.lost or len(masks) == 0:
            return 0
        depth = st.frame.depth_m()
        cands: list[int] = []
        projected: list[np.ndarray] = []
        for tid in reversed(self.book.lost):  # most recently lost first
            fp = self.book.tracks[tid].footprint
            if fp is None:
                continue
            m = project_footprint(fp, depth, st.frame.intrinsics, st.frame.T_world_cam)
            if m.any():
                cands.append(tid)
                projected.append(m)
        if not cands:
            return 0
        iou = sparse_mask_iou(projected, masks, areas)  # (L, N), every detection
        revived: set[int] = set()
        if unmatched:
            b = associate_iou(iou[:, unmatched], self._dino(cands, det_feat.shape[-1]), det_feat[unmatched], self.cfg.association)
            for i, j in b.matches:
                ids[unmatched[j]] = cands[i]
                self.book.revive(cands[i])
                revived.add(i)
        dup_iou = self.cfg.association.duplicate_iou
        duplicates = [tid for i, tid in enumerate(cands) if i not in revived and iou[i].max() >= dup_iou]
        if duplicates:
            self.book.retire(duplicates)
        return len(revived)

    def _dino(self, ids: list[int], dim: int) -> Annotated[np.ndarray, "(M, D) float32"]:
        if not ids:
            return np.zeros((0, dim), np.float32)
        return np.stack([self.book.tracks[t].dino for t in ids])

    def apply_features(self, frame_index: int, features: Annotated[np.ndarray, "(N, D) float32"]) -> None:
        """Eq. 4: fold the keyframe's CLIP features into the tracks its masks went to."""
        ids = self.mask_tracks.get(frame_index)
        if ids is None:
            # CLIP results can overtake their masks on another key: hold them briefly.
            if frame_index in {s.frame.frame_index for s in self.history}:
                self.pending_features[frame_index] = features
            return
        if len(ids) != features.shape[0]:
            log.warning("frame %d: %d CLIP features for %d masks; ignored", frame_index, features.shape[0], len(ids))
            return
        for tid, f in zip(ids, features, strict=True):
            if tid >= 0:
                self.book.tracks[tid].add_clip(np.asarray(f, np.float32))
                self.book.changed.add(tid)

    def take_track_features(self, frame_index: int) -> TrackFeatures | None:
        """Changed tracks since the last call, or None if nothing changed."""
        changed, retired = self.book.take_changes()
        if not changed and not retired:
            return None
        return TrackFeatures(
            frame_index=frame_index,
            tracks=[TrackFeature(track_id=t.id, dino=t.dino, clip=t.clip, clip_count=t.clip_count) for t in changed],
            retired=retired,
        )

    # ------------------------------------------------------------------ internals

    def _state(self, frame_index: int) -> FrameState | None:
        for s in reversed(self.history):
            if s.frame.frame_index == frame_index:
                return s
        return None

    def _after(self, st: FrameState) -> list[FrameState]:
        return [s for s in self.history if s.count > st.count]

    def _propagate(self, st: FrameState) -> torch.Tensor:
        anchor = self.anchor
        assert anchor is not None and anchor.soft is not None
        recent = [
            s for s in self.history
            if anchor.count < s.count < st.count and s.epoch == self.epoch and s.soft is not None
        ][-self.cfg.propagation.context_frames :] if self.cfg.propagation.context_frames else []  # fmt: skip
        refs = [(anchor.features, anchor.soft)] + [(s.features, s.soft) for s in recent]
        return propagate_with_config(st.features, refs, self.cfg.propagation)

    def _labels(self, st: FrameState) -> np.ndarray:
        return self._labels_and_ids(st)[0]

    def _labels_and_ids(self, st: FrameState) -> tuple[Annotated[np.ndarray, "(H, W) int32 track ids"], list[int]]:
        """The frame's track id per pixel (its keyframe labels, or its propagated
        distributions upsampled) and the ids in it, ascending."""
        H, W = st.frame.depth.shape
        if st.labels is not None:
            return st.labels, _ids_present(st.labels)
        if st.soft is None:
            return np.full((H, W), -1, np.int32), []
        return upsample_ids(st.soft, H, W, self.epoch_slots[st.epoch])

    def _predicted_labels(self, st: FrameState, H: int, W: int) -> Annotated[np.ndarray, "(H, W) int32 track ids"]:
        """Where the active tracks are predicted at keyframe ``st``: propagated there (eq. 1),
        or in ``per_frame`` mode the labels of the previous keyframe (every frame is one; the
        paper's per-frame baseline associates with BoT-SORT instead, docs/method.md, T7)."""
        if self.cfg.mode == "per_frame":
            prev = [s for s in self.history if s.count < st.count and s.labels is not None]
            return prev[-1].labels if prev else np.full((H, W), -1, np.int32)
        return self._labels(st)

    def _prune(self) -> None:
        alive = {s.frame.frame_index for s in self.history}
        for k in [k for k in self.mask_tracks if k not in alive]:
            del self.mask_tracks[k]
        for k in [k for k in self.pending_features if k not in alive]:
            del self.pending_features[k]
        # Slot lists of epochs no kept frame refers to any more.
        used = {s.epoch for s in self.history} | {self.epoch}
        for k in [k for k in self.epoch_slots if k not in used]:
            del self.epoch_slots[k]


def appearance(
    features: Annotated[np.ndarray, "(h, w, D) float32 unit"], dims: int
) -> Annotated[np.ndarray, "(h, w, dims) float32 unit"]:
    """The first ``dims`` channels of each patch feature, renormalised (``DenseFeatures.
    appearance_dims``)."""
    if dims >= features.shape[-1]:
        return features
    part = features[..., :dims]
    return part / np.maximum(np.linalg.norm(part, axis=-1, keepdims=True), 1e-12)


def paint_labels(
    masks: Annotated[np.ndarray, "(N, H, W) bool"], ids: list[int], H: int, W: int, boxes: Boxes | None = None
) -> Annotated[np.ndarray, "(H, W) int32"]:
    """One track id per pixel from possibly overlapping masks: larger masks are painted
    first, so a small object lying on a large one keeps its own id. ``boxes``: where each
    mask's pixels are (:func:`~services.tracker.masks_numba.mask_boxes`)."""
    out = np.full((H, W), -1, np.int32)
    if len(ids) == 0:
        return out
    if boxes is None:
        boxes = np.tile(np.array([0, H, 0, W], np.int64), (len(ids), 1))
    crops = [masks[j, y0:y1, x0:x1] for j, (y0, y1, x0, x1) in enumerate(boxes.tolist())]
    order = np.argsort(-np.array([int(c.sum()) for c in crops], np.int64), kind="stable")
    for j in order:
        y0, y1, x0, x1 = boxes[j].tolist()
        out[y0:y1, x0:x1][crops[j]] = ids[j]
    return out


def slot_image(labels: Annotated[np.ndarray, "(H, W) int32 track ids"], slots: list[int]) -> Annotated[np.ndarray, "(H, W) int64, 0 = no track"]:
    """Track ids to slot indices of the current epoch (slot s + 1 holds ``slots[s]``)."""
    if not slots:
        return np.zeros(labels.shape, np.int64)
    ids = np.asarray(slots, np.int64)
    top = int(ids.max())
    if ids.min() >= 0 and top <= 4 * labels.size + 1024 and labels.dtype.kind == "i" and labels.size:
        # a table over -1 .. max(id): one lookup per pixel (the tracker's ids are sequential;
        # sorting the pixels into the slots took 13 ms at 1200x680)
        lo, hi = int(labels.min()), int(labels.max())
        if lo >= -1:
            lut = np.zeros(max(hi, top) + 2, np.int64)
            lut[ids[::-1] + 1] = np.arange(len(ids), 0, -1)  # a repeated id keeps its first slot
            return lut[labels + 1]
    order = np.argsort(ids)
    pos = np.searchsorted(ids[order], labels)
    pos = np.clip(pos, 0, len(ids) - 1)
    hit = ids[order][pos] == labels
    return np.where(hit, order[pos] + 1, 0).astype(np.int64)


def _ids_present(labels: Annotated[np.ndarray, "(H, W) int track id per pixel, -1 = none"]) -> list[int]:
    """The track ids in ``labels``, ascending, without -1: ``np.unique``'s answer from one
    counting pass (1-2 ms at 1200x680, where sorting the pixels took 7-15 ms), for ids as
    small as the tracker's sequential ones."""
    flat = labels.ravel()
    if flat.size == 0:
        return []
    top = int(flat.max())
    if top < 0:
        return []
    if top > 4 * flat.size + 1024:  # sparse huge ids: a count table that size is not worth it
        return [int(t) for t in np.unique(flat) if t >= 0]
    return (np.flatnonzero(np.bincount(flat + 1, minlength=top + 2)[1:])).tolist()
