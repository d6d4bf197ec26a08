"""OpenCLIP's settings: the torch backend (``openclip``, the paper's ViT-H-14) and its ONNX
export on onnxruntime (``clip_onnx``). Torch-free: ``build`` imports the encoder."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.config.base import Precision
from shared.perception.encoders.config import VL_ENCODERS, VLEncoderBackend


class _ClipFields(VLEncoderBackend):
    """An OpenCLIP model's settings, shared by the torch and the ONNX runtime backends."""

    model: str = "ViT-H-14"
    """OpenCLIP architecture; ViT-H-14 in the paper (IV-A), ViT-B-32 onboard."""
    weights: str = "weights/open_clip_vit_h14.bin"
    """Local OpenCLIP checkpoint or ONNX folder; never downloaded."""
    crop_padding: float = Field(0.1, ge=0, le=1)
    """Padding of each mask's bounding-box crop, as a fraction of its size (III-B)."""
    crop_mode: Literal["pad_square", "center_crop"] = "pad_square"
    """How the padded box becomes CLIP's square input. ``pad_square``: the crop is centred on
    a square of CLIP's mean colour (zero after normalisation) and resized whole, so every
    pixel of the object is seen. ``center_crop``: OpenCLIP's own transform, which resizes the
    short side and cuts the middle square; an elongated crop loses its ends (a 165x6 box keeps
    4% of its width). Image queries always use OpenCLIP's own transform."""
    batch_size: int = Field(16, ge=1)
    """Crops per forward pass."""


@VL_ENCODERS.register("openclip")
class OpenClipConfig(_ClipFields):
    """OpenCLIP from a local checkpoint: the paper's ViT-H-14 (IV-A)."""

    backend: Literal["openclip"] = "openclip"
    """OpenCLIP on torch (shared/perception/encoders/openclip.py)."""
    precision: Precision = "auto"
    """CLIP's arithmetic, under torch autocast (the weights stay fp32): ``fp32``, ``fp16`` or
    ``bf16``. ``auto`` is fp16 on CUDA when ``keyframe_vl.fp16`` (tensor cores run half
    precision at full rate) and fp32 on a CPU, where fp16 is emulated and slower. On random
    ViT-S-32 weights, crop features in bf16 have cosine 0.9999 to fp32's, in fp16 1.0000
    (tests/shared/perception/encoders/test_enc_precision.py)."""

    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        from shared.devices import resolve_device, resolve_precision
        from shared.perception.encoders.openclip import OpenClipEncoder

        device = resolve_device(device)
        return OpenClipEncoder(
            self.model, self.weights, device=device, precision=resolve_precision(self.precision, device, fp16),
            crop_padding=self.crop_padding, batch_size=self.batch_size, crop_mode=self.crop_mode,
        )  # fmt: skip


@VL_ENCODERS.register("clip_onnx")
class ClipOnnxConfig(_ClipFields):
    """OpenCLIP's towers exported to ONNX (``trackgraph export-onnx``), run by onnxruntime in
    the precision they were exported in."""

    backend: Literal["clip_onnx"] = "clip_onnx"
    """OpenCLIP's ONNX export on onnxruntime (shared/perception/encoders/clip_onnx.py)."""

    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        from shared.devices import resolve_device
        from shared.perception.encoders.clip_onnx import ClipOnnxEncoder

        return ClipOnnxEncoder(
            self.weights, arch=self.model, device=resolve_device(device),
            crop_padding=self.crop_padding, batch_size=self.batch_size, crop_mode=self.crop_mode,
        )  # fmt: skip
