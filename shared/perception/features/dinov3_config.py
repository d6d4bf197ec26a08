"""DINOv3 ViT-S+/16's settings: the torch backend (``dinov3``, the paper's) and its ONNX export
on onnxruntime (``dinov3_onnx``). Torch-free: ``build`` imports the backbone."""

from __future__ import annotations

from typing import Literal

from shared.config.base import Precision
from shared.perception.features.config import DENSE_FEATURES, DenseFeaturesBackend


class _Dinov3Weights(DenseFeaturesBackend):
    """Where DINOv3 ViT-S+/16 comes from."""

    loader: Literal["transformers", "timm", "hub"] = "transformers"
    """How the weights are stored: a transformers folder, a timm file or a hub .pth (for
    ``dinov3_onnx``: the checkpoint an export was made from, named by ``models check``)."""
    weights: str = "weights/dinov3_vits16plus"
    """Local ViT-S+/16 weights; never downloaded."""


@DENSE_FEATURES.register("dinov3")
class Dinov3Config(_Dinov3Weights):
    """DINOv3 ViT-S+/16 on torch: the paper's backbone (III-B)."""

    backend: Literal["dinov3"] = "dinov3"
    """DINOv3 on torch (shared/perception/features/dinov3.py)."""
    precision: Precision = "auto"
    """DINOv3's arithmetic under torch autocast (the weights, the final norm and the
    per-patch normalisation stay fp32): ``fp32``, ``fp16`` or ``bf16``. ``auto`` is fp16 on
    CUDA (tensor cores run half precision at full rate) and fp32 on a CPU, where fp16 is
    emulated: a random-weight ViT-S+/16 at 112 px took 0.32 s fp32, 0.21 s bf16 and 1.74 s
    fp16 on this 2-core CPU, with patch cosines to fp32 of at least 0.99999 in both."""

    def build(self, device: str = "cpu", fp16: bool = True):
        from shared.devices import resolve_precision
        from shared.perception.features.dinov3 import Dinov3Features, load_patch_tokens

        model = load_patch_tokens(self.loader, self.weights)
        if model.patch_size != self.patch_size:
            raise ValueError(f"DINOv3 weights have patch size {model.patch_size}, tracker.features.patch_size says {self.patch_size}")
        return Dinov3Features(model, self.short_side, device, resolve_precision(self.precision, device, fp16))


@DENSE_FEATURES.register("dinov3_onnx")
class Dinov3OnnxConfig(_Dinov3Weights):
    """DINOv3 exported to one ONNX file (``trackgraph export-onnx``), run by onnxruntime in
    the precision of its export."""

    backend: Literal["dinov3_onnx"] = "dinov3_onnx"
    """DINOv3's ONNX export on onnxruntime (shared/perception/features/onnx_backend.py)."""
    weights: str = "weights/dinov3_vits16plus.onnx"
    """The ``.onnx`` export; never downloaded."""

    def build(self, device: str = "cpu", fp16: bool = True):
        from shared.perception.features.onnx_backend import Dinov3OnnxFeatures

        return Dinov3OnnxFeatures(self.weights, self.short_side, self.patch_size, device)
