"""Dense per-patch features for label propagation (DINOv3 ViT-S+/16 in the paper, III-B).

One factory, ``make_dense_features(cfg, device, fp16)``, builds the backend named by
``cfg.backend``; every backend returns ``(h, w, D)`` float32 torch tensors, unit norm per patch,
on the grid ``grid_shape(H, W, cfg.short_side, cfg.patch_size)``. Importing this package
loads neither torch nor any model library: each backend imports its dependencies when built.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from services.tracker.features.base import DenseFeatures, grid_shape, resized_shape

if TYPE_CHECKING:
    from shared.config.tracker import DenseFeaturesConfig

log = logging.getLogger(__name__)

__all__ = ["DenseFeatures", "export_dinov3_onnx", "grid_shape", "make_dense_features", "resized_shape"]


def make_dense_features(cfg: DenseFeaturesConfig, device: str = "cpu", fp16: bool = True) -> DenseFeatures:
    """The configured backend, ready to call on (H, W, 3) uint8 frames.

    ``dinov3`` and ``dinov3_onnx`` read local files only and raise FileNotFoundError naming
    the path and where the weights come from. ``device`` is ``cpu``, ``cuda``, ``cuda:N`` or
    ``auto``. ``dinov3`` runs in ``cfg.precision``; ``fp16`` says whether its ``auto`` may be
    half precision on CUDA (shared/devices.py).
    """
    from shared.devices import resolve_device, resolve_precision

    device = resolve_device(device, "tracker.device")
    if cfg.backend == "classical":
        from services.tracker.features.classical import ClassicalFeatures

        return ClassicalFeatures(cfg.short_side, cfg.patch_size, device)
    if cfg.backend == "dinov3":
        from services.tracker.features.dinov3 import Dinov3Features, load_patch_tokens

        model = load_patch_tokens(cfg.loader, cfg.weights)
        if model.patch_size != cfg.patch_size:
            raise ValueError(f"DINOv3 weights have patch size {model.patch_size}, config says {cfg.patch_size}")
        return Dinov3Features(model, cfg.short_side, device, resolve_precision(cfg.precision, device, fp16))
    if cfg.backend == "dinov3_onnx":
        from services.tracker.features.onnx_backend import Dinov3OnnxFeatures

        return Dinov3OnnxFeatures(cfg.weights, cfg.short_side, cfg.patch_size, device)
    raise ValueError(f"unknown dense-feature backend {cfg.backend!r}")


def export_dinov3_onnx(cfg: DenseFeaturesConfig, out_path: str | Path, **kwargs) -> Path:
    """Exports the weights that ``cfg.loader`` / ``cfg.weights`` name to one ``.onnx`` file.

    Point a ``dinov3_onnx`` config's ``weights`` at the result. Keyword arguments go to
    ``onnx_backend.export_onnx`` (``opset``, ``example_hw``, ``max_side``).
    """
    from services.tracker.features.onnx_backend import export_onnx

    return export_onnx(cfg.loader, cfg.weights, out_path, **kwargs)
