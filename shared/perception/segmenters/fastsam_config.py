"""FastSAM's settings: the ultralytics backend (``fastsam``, the paper's FastSAM-x) and its
ONNX export on onnxruntime (``fastsam_onnx``). Torch-free: ``build`` imports the segmenter."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.config.base import Precision
from shared.perception.segmenters.config import SEGMENTERS, SegmenterBackend


class _FastSAMFields(SegmenterBackend):
    """FastSAM's settings, shared by the ultralytics and the ONNX runtime backends."""

    weights: str = "weights/FastSAM-x.pt"
    """Local FastSAM checkpoint (.pt) or ONNX export; never downloaded."""
    imgsz: int = Field(1024, ge=32)
    """FastSAM inference size (long side, pixels)."""
    conf: float = Field(0.4, ge=0, le=1)
    """FastSAM confidence threshold."""
    iou: float = Field(0.9, ge=0, le=1)
    """FastSAM NMS IoU threshold."""
    retina_masks: bool = True
    """Upsample masks to full image resolution before thresholding."""


@SEGMENTERS.register("fastsam")
class FastSAMConfig(_FastSAMFields):
    """FastSAM on ultralytics: the paper's FastSAM-x (III-B)."""

    backend: Literal["fastsam"] = "fastsam"
    """FastSAM on ultralytics (shared/perception/segmenters/fastsam.py)."""
    precision: Precision = "auto"
    """FastSAM's arithmetic: ``fp32``, ``fp16`` (on CUDA ultralytics' own half-precision
    model; on a CPU torch autocast around predict) or ``bf16`` (torch autocast; the weights
    stay fp32). ``auto`` is fp16 on CUDA
    when ``keyframe_vl.fp16`` (tensor cores run half precision at full rate) and fp32 on a
    CPU, where fp16 is emulated: on this 2-core CPU a random-weight FastSAM-s took 0.55 s a
    320 px keyframe in fp16 against 0.12 s in bf16."""

    def build(self, device: str = "cpu", fp16: bool = False):
        from shared.perception.segmenters.fastsam import FastSAMSegmenter

        return FastSAMSegmenter(self, device=device, fp16=fp16)


@SEGMENTERS.register("fastsam_onnx")
class FastSAMOnnxConfig(_FastSAMFields):
    """FastSAM exported to ONNX (``trackgraph export-onnx``), run by onnxruntime. It runs in
    the precision it was exported in."""

    backend: Literal["fastsam_onnx"] = "fastsam_onnx"
    """FastSAM's ONNX export on onnxruntime (shared/perception/segmenters/fastsam_onnx.py)."""
    weights: str = "weights/FastSAM-x.onnx"
    """Local FastSAM ONNX export (``trackgraph export-onnx``); never downloaded."""

    def build(self, device: str = "cpu", fp16: bool = False):
        from shared.perception.segmenters.fastsam_onnx import FastSAMOnnxSegmenter

        return FastSAMOnnxSegmenter(self, device=device, fp16=fp16)
