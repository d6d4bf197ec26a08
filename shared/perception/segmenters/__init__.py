"""Class-agnostic keyframe segmenters.

Each backend is a config model registered in ``SEGMENTERS`` (:mod:`.config`), kept beside its
code: ``fastsam``, ultralytics, the paper's FastSAM-x, and ``fastsam_onnx``, an ONNX export on
onnxruntime (:mod:`.fastsam_config`); ``classical``, graph-based RGB-D segmentation with no
weights (:mod:`.classical_config`); ``simulated``, noisy ground truth on synthetic scenes
(:mod:`.simulated_config`). A config's ``build`` imports its module here. Importing this
package stays light.
"""

from __future__ import annotations

from shared.perception import Segmenter
from shared.perception.segmenters.config import SEGMENTERS, SegmenterBackend, segmenter_config

__all__ = ["SEGMENTERS", "SegmenterBackend", "make_segmenter", "segmenter_config"]


def make_segmenter(cfg: SegmenterBackend, device: str = "cpu", fp16: bool = False) -> Segmenter:
    """The segmenter ``cfg`` describes (``cfg.build``). ``device`` ("cpu", "cuda", "cuda:N" or
    "auto": CUDA when present) and ``fp16`` (CUDA only) matter to the FastSAM backends only.
    Missing weights raise FileNotFoundError naming the path; nothing is ever downloaded."""
    return cfg.build(device=device, fp16=fp16)
