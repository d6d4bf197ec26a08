"""The keyframe_vl core a config asks for (segmenter and VL encoder), built when asked:
importing this module loads no model."""

from __future__ import annotations

from shared.config.root import TrackGraphConfig


def build_keyframe_vl(cfg: TrackGraphConfig):
    """A :class:`~services.keyframe_vl.core.KeyframeVLCore` of ``cfg.keyframe_vl``."""
    from services.keyframe_vl.core import KeyframeVLCore

    return KeyframeVLCore(cfg.keyframe_vl)
