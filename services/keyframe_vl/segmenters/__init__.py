"""Class-agnostic keyframe segmenters behind one factory, :func:`make_segmenter`.

Backends (``SegmenterConfig.backend``): ``fastsam`` (ultralytics, the paper's FastSAM-x),
``fastsam_onnx`` (an ONNX export on onnxruntime), ``classical`` (graph-based RGB-D
segmentation, no weights) and ``simulated`` (noisy ground truth, synthetic scenes only).
Heavy libraries are imported only by the backend that needs them, so importing this package
stays light.
"""

from __future__ import annotations

from shared.config.keyframe_vl import SegmenterConfig
from shared.perception import Segmenter

BACKENDS = ("fastsam", "fastsam_onnx", "classical", "simulated")

__all__ = ["BACKENDS", "make_segmenter"]


def make_segmenter(cfg: SegmenterConfig, device: str = "cpu", fp16: bool = False) -> Segmenter:
    """The segmenter ``cfg.backend`` names. ``device`` ("cpu", "cuda", "cuda:N" or "auto":
    CUDA when present) and ``fp16`` (CUDA only) matter to the FastSAM backends only. Missing
    weights raise FileNotFoundError naming the path; nothing is ever downloaded."""
    if cfg.backend == "fastsam":
        from services.keyframe_vl.segmenters.fastsam import FastSAMSegmenter

        return FastSAMSegmenter(cfg, device=device, fp16=fp16)
    if cfg.backend == "fastsam_onnx":
        from services.keyframe_vl.segmenters.fastsam_onnx import FastSAMOnnxSegmenter

        return FastSAMOnnxSegmenter(cfg, device=device, fp16=fp16)
    if cfg.backend == "classical":
        from services.keyframe_vl.segmenters.classical import ClassicalSegmenter

        return ClassicalSegmenter(cfg)
    if cfg.backend == "simulated":
        from services.keyframe_vl.segmenters.simulated import SimulatedSegmenter

        return SimulatedSegmenter(cfg)
    raise ValueError(f"unknown segmenter backend {cfg.backend!r}; choose one of: {', '.join(BACKENDS)}")
