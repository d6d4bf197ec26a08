"""Dense per-patch features for label propagation (DINOv3 ViT-S+/16 in the paper, III-B).

One factory, ``make_dense_features(cfg, device, fp16)``, builds the backend ``cfg`` describes
(a config registered in ``DENSE_FEATURES``, :mod:`.config`, from a module beside its code:
:mod:`.dinov3_config`, :mod:`.classical_config`); every backend returns ``(h, w, D)`` float32
torch tensors, unit norm per patch, on the grid ``grid_shape(H, W, cfg.short_side, cfg.patch_size)``. Importing this package
loads neither torch nor any model library: each backend imports its dependencies when built.
"""

from __future__ import annotations

import logging
from pathlib import Path

from shared.perception.features.base import DenseFeatures, grid_shape, resized_shape
from shared.perception.features.config import (
    DENSE_FEATURES,
    DenseFeaturesBackend,
    dense_features_config,
)

log = logging.getLogger(__name__)

__all__ = [
    "DENSE_FEATURES",
    "DenseFeatures",
    "DenseFeaturesBackend",
    "dense_features_config",
    "export_dinov3_onnx",
    "grid_shape",
    "make_dense_features",
    "resized_shape",
]


def make_dense_features(cfg: DenseFeaturesBackend, device: str = "cpu", fp16: bool = True) -> DenseFeatures:
    """The backend ``cfg`` describes (``cfg.build``, registered in ``DENSE_FEATURES``), ready to
    call on (H, W, 3) uint8 frames.

    ``dinov3`` and ``dinov3_onnx`` read local files only and raise FileNotFoundError naming
    the path and where the weights come from. ``device`` is ``cpu``, ``cuda``, ``cuda:N`` or
    ``auto``. ``dinov3`` runs in ``cfg.precision``; ``fp16`` says whether its ``auto`` may be
    half precision on CUDA (shared/devices.py).
    """
    from shared.devices import resolve_device

    return cfg.build(device=resolve_device(device, "tracker.device"), fp16=fp16)


def export_dinov3_onnx(cfg: DenseFeaturesBackend, out_path: str | Path, **kwargs) -> Path:
    """Exports the weights that ``cfg.loader`` / ``cfg.weights`` name to one ``.onnx`` file.

    Point a ``dinov3_onnx`` config's ``weights`` at the result. Keyword arguments go to
    ``onnx_backend.export_onnx`` (``opset``, ``example_hw``, ``max_side``).
    """
    from shared.perception.features.onnx_backend import export_onnx

    return export_onnx(cfg.loader, cfg.weights, out_path, **kwargs)
