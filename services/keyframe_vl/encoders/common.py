"""Small helpers every VL encoder backend shares (numpy only)."""

from __future__ import annotations

from typing import Annotated

import numpy as np


def unit_rows(x: Annotated[np.ndarray, "(N, D) float"]) -> Annotated[np.ndarray, "(N, D) float32"]:
    """Rows scaled to unit L2 norm in float32; an all-zero row stays zero rather than NaN."""
    x = np.asarray(x, dtype=np.float32)
    norms = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.maximum(norms, np.float32(1e-12))


def check_rgb(rgb: np.ndarray) -> Annotated[np.ndarray, "(H, W, 3) uint8"]:
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        got = f"{rgb.dtype} {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {got}")
    if rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError(f"empty image {rgb.shape}")
    return rgb
