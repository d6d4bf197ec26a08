"""Source-track propagation between keyframes (paper section III-B, eqs. 1-4)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from shared.config.base import Device, StrictModel
from shared.perception.features.config import DenseFeaturesSection, features_default


class PropagationConfig(StrictModel):
    """Label propagation between keyframes (eq. 1, the DINOv3 recipe)."""

    context_frames: int = Field(7, ge=0)
    """Recent frames used as references besides the keyframe (eq. 1's r)."""
    window_radius: int = Field(12, ge=1)
    """Reference patches q lie within this many patches of p (eq. 1's K_t(p))."""
    topk: int = Field(5, ge=1)
    """References kept per patch, by cosine similarity (eq. 1)."""
    temperature: float = Field(0.2, gt=0)
    """Softmax temperature giving a_pqr (eq. 1)."""


class AssociationConfig(StrictModel):
    """Keyframe correction: propagated masks versus new detections (eqs. 2-3)."""

    w_iou: float = Field(0.5, ge=0, le=1)
    """Weight of mask IoU in s_ij (eq. 3)."""
    w_feat: float = Field(0.5, ge=0, le=1)
    """Weight of DINOv3 cosine in s_ij (eq. 3); w_iou + w_feat = 1."""
    iou_min: float = Field(0.15, ge=0, le=1)
    """Gate: candidate pairs need IoU at least this (eq. 3)."""
    score_min: float = Field(0.35, ge=0, le=1)
    """Gate: candidate pairs need s_ij at least this (eq. 3)."""
    ema: float = Field(0.2, ge=0, le=1)
    """eta, the track DINOv3 feature EMA rate (III-B)."""
    support_radius_m: float = Field(0.05, ge=0)
    """Not in the paper: an active track and a detection are a candidate pair only if some
    of the detection's back-projected points lie within this distance of the track's 3D
    footprint (the surface its keyframe masks covered), i.e. the static-world check that
    stops a label that drifted onto a neighbour from taking the neighbour's detection.
    0 turns the check off (the paper's purely 2D eq. 3; docs/method.md, T2)."""
    support_min: float = Field(0.02, ge=0, le=1)
    """Share of the detection's points that must have such support (see
    ``support_radius_m``)."""
    support_relative: float = Field(0.5, ge=0, le=1)
    """And at least this fraction of the best support any candidate track gives the same
    detection: a floor label that propagation moved onto the rug lying on it touches the
    rug's points only along its edge, the rug's own track all over."""
    duplicate_iou: float = Field(0.5, ge=0, le=1)
    """Not in the paper (docs/method.md, T1): a lost track that the second eq. 3 pass did not
    take, although its footprint projected into the keyframe overlaps a detection at this IoU
    or more, is retired: another track already holds that surface, and keeping both would
    hand the object back and forth between them at later keyframes. 0.5 is the usual
    same-object IoU; 1 never retires this way (only the bounded lost pool evicts)."""

    @model_validator(mode="after")
    def _weights_sum(self) -> AssociationConfig:
        if abs(self.w_iou + self.w_feat - 1.0) > 1e-6:
            raise ValueError(f"w_iou + w_feat must be 1 (eq. 3), got {self.w_iou + self.w_feat}")
        return self


class FragmentsConfig(StrictModel):
    """Not in the paper (docs/method.md, T3): a detection no track took joins the track that
    took another detection when it is a piece of that track's object, so a segmenter that
    cuts an object in two at one keyframe does not leave a second track to compete for the
    whole object at the next (IDF1 0.679 to 0.717, switches 0.75 to 0.54 per object per 100
    frames on ``small`` at default mask noise). All three conditions must hold."""

    cover: float = Field(0.5, ge=0, le=1)
    """Share of the detection's pixels that must lie in the predicted (propagated) mask of
    the track: mostly inside it."""
    sim: float = Field(0.85, ge=-1, le=1)
    """Cosine the detection's eq. 2 prototype must reach with the prototype of the piece the
    track took. Above eq. 7's theta_sim of 0.8: classical features put a book lying on a
    table at 0.80-0.81 to the table, and that book must keep its own track."""
    support: float = Field(0.5, ge=0, le=1)
    """Share of the detection's back-projected points that must lie on the track's 3D
    footprint (within ``association.support_radius_m``): mostly on the surface the track was
    seen as before, so a neighbour that propagation labelled with the track does not join
    it."""


class TrackerConfig(StrictModel):
    """The tracker service."""

    mode: Literal["propagation", "per_frame", "ground_truth"] = "propagation"
    """propagation: the paper's method. per_frame: segment every frame and associate by
    IoU + appearance (eq. 3 against the previous frame's labels), the baseline of the tracker
    ablation; the paper's baseline uses BoT-SORT (docs/method.md, T7). ground_truth: perfect identities
    from a synthetic scene's instance images, to measure fusion alone."""
    keyframe_interval: int = Field(24, ge=1)
    """K_f, frames between keyframes (III-B)."""
    features: DenseFeaturesSection = features_default
    """Dense feature backend: ``backend`` (``dinov3``, ``dinov3_onnx``, ``classical``) and that
    backend's fields."""
    propagation: PropagationConfig = Field(default_factory=PropagationConfig)
    """Eq. 1 parameters."""
    association: AssociationConfig = Field(default_factory=AssociationConfig)
    """Eqs. 2-3 parameters."""
    fragments: FragmentsConfig = Field(default_factory=FragmentsConfig)
    """When an unmatched detection joins the track that took another piece of its object
    (not in the paper)."""
    keyframe_timeout_s: float = Field(5.0, gt=0)
    """Masks not back after this long count as lost; the tracker keeps propagating and
    retries at the next keyframe (not in the paper, which has no late masks; docs/method.md,
    T4)."""
    wait_for_masks: bool = False
    """Hold each keyframe until its masks arrive (up to ``keyframe_timeout_s``) before
    emitting it: lossless replay then gives the in-process result. False never waits, as a
    live robot should: the keyframe goes out propagated and is corrected on arrival."""
    resend_frames: int = Field(32, ge=0)
    """Tracked frames (with the track-feature messages between them) kept until fusion
    acknowledges them, and sent again when a restarted fusion announces itself or after
    ``resend_after_s``, so nothing in flight at a fusion crash is lost. Lossless pacing holds
    the source within ``source.window_frames`` of fusion, so about that many wait at most;
    past this bound the oldest is let go (counted). 0: keep none."""
    resend_after_s: float = Field(5.0, gt=0)
    """A frame fusion has not acknowledged after this long is sent again, with everything
    after it (a message lost on the link, a fusion restarted before its first ack)."""
    history_frames: int = Field(48, ge=1)
    """Recent feature maps kept to re-propagate when keyframe masks arrive late."""
    oracle_retire_frames: int = Field(30, ge=0)
    """ground_truth mode only: an object unseen for this many frames gets a new track id when
    it comes back, as a real tracker retires tracks that leave the view (III-B), so long-term
    re-identification has revisits to merge. 0 keeps one id per object for ever."""
    ground_truth: str | None = None
    """ground_truth mode only: the synthetic sequence folder (``SEQ_DIR`` with
    ``instances/``) whose instance images give each frame's identities, by frame index.
    ``trackgraph map``, ``launch`` and ``serve --sequence`` set it to the sequence when unset."""
    device: Device = "auto"
    """Torch device of the dense features and propagation: ``auto`` (CUDA when present),
    ``cpu``, ``cuda`` or ``cuda:N``."""
