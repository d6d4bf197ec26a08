"""Class-agnostic keyframe segmenters.

Each backend is a config model registered in ``SEGMENTERS`` (shared/config/keyframe_vl.py:
``fastsam``, ultralytics, the paper's FastSAM-x; ``fastsam_onnx``, an ONNX export on
onnxruntime; ``classical``, graph-based RGB-D segmentation with no weights; ``simulated``,
noisy ground truth on synthetic scenes) whose ``build`` imports its module here. Importing this
package stays light.
"""

from __future__ import annotations

from shared.config.keyframe_vl import SEGMENTERS, SegmenterBackend
from shared.perception import Segmenter

__all__ = ["SEGMENTERS", "make_segmenter"]


def make_segmenter(cfg: SegmenterBackend, device: str = "cpu", fp16: bool = False) -> Segmenter:
    """The segmenter ``cfg`` describes (``cfg.build``). ``device`` ("cpu", "cuda", "cuda:N" or
    "auto": CUDA when present) and ``fp16`` (CUDA only) matter to the FastSAM backends only.
    Missing weights raise FileNotFoundError naming the path; nothing is ever downloaded."""
    return cfg.build(device=device, fp16=fp16)
