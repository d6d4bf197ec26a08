"""FastSAM masks and CLIP features at keyframes (paper section III-B)."""

from __future__ import annotations

from pydantic import Field

from shared.config.base import Device, StrictModel
from shared.perception.encoders.config import VLSection, vl_default
from shared.perception.segmenters.config import SegmenterSection, segmenter_default


class KeyframeVLConfig(StrictModel):
    """The keyframe_vl service."""

    segmenter: SegmenterSection = segmenter_default
    """Mask backend: ``backend`` (one of the segmenter registry's: ``fastsam``,
    ``fastsam_onnx``, ``classical``, ``simulated``) and that backend's fields."""
    vl: VLSection = vl_default
    """CLIP backend: ``backend`` (``openclip``, ``clip_onnx``, ``simulated``) and that
    backend's fields."""
    device: Device = "auto"
    """Torch device of FastSAM and CLIP: ``auto`` (CUDA when present), ``cpu``, ``cuda`` or
    ``cuda:N``."""
    fp16: bool = True
    """What ``precision: auto`` of the segmenter and the CLIP encoder means on a GPU: fp16
    when true, fp32 when false (ignored on CPU)."""
    embed_cache_size: int = Field(256, ge=0)
    """Text embeddings kept for repeated ``vl/embed`` queries."""

