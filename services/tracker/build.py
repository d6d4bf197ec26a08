"""The tracker core a config asks for: :class:`~services.tracker.core.TrackerCore` with its
dense features, or the ground-truth tracker (``tracker.mode: ground_truth``). Heavy imports
happen here, when one is built, not when the service is imported."""

from __future__ import annotations

from typing import Any

from shared.config.root import TrackGraphConfig


def build_tracker(cfg: TrackGraphConfig) -> Any:
    """The tracker core of ``cfg.tracker.mode``: a ``TrackerCore``, or a ``GroundTruthTracker``
    (its keyframes embedded by the configured VL encoder, no masks asked for)."""
    if cfg.tracker.mode == "ground_truth":
        from services.tracker.oracle import GroundTruthTracker
        from shared.perception.encoders import make_vl_encoder

        encoder = make_vl_encoder(cfg.keyframe_vl.vl, device=cfg.keyframe_vl.device, fp16=cfg.keyframe_vl.fp16)
        return GroundTruthTracker(cfg.tracker.keyframe_interval, encoder, cfg.tracker.oracle_retire_frames, ground_truth=cfg.tracker.ground_truth)
    from services.tracker.core import TrackerCore
    from shared.perception.features import make_dense_features

    features = make_dense_features(cfg.tracker.features, device=cfg.tracker.device)
    return TrackerCore(cfg.tracker, features)


def asks_for_keyframes(cfg: TrackGraphConfig) -> bool:
    """Whether this tracker sends keyframe requests (the ground-truth tracker does not)."""
    return cfg.tracker.mode != "ground_truth"
