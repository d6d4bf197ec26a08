"""Small helpers every VL encoder backend shares (numpy only)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Annotated

import numpy as np

from shared.perception import KeyframeImage


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


class ImageTowerMixin(ABC):
    """Whole images through a CLIP image tower: what the OpenCLIP encoder and its ONNX export
    share once each has its own ``_forward_images``."""

    @abstractmethod
    def _forward_images(self, images: Sequence[np.ndarray]) -> Annotated[np.ndarray, "(N, D) float32"]:
        """Unit-norm features of (H, W, 3) uint8 images, through the tower's own preprocessing."""

    def encode_image(self, rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]) -> Annotated[np.ndarray, "(D,) float32"]:
        """A whole image (an image query), through OpenCLIP's own transform (or the ONNX
        backend's numpy copy of it)."""
        return self._forward_images([check_rgb(rgb)])[0]

    def encode_view(self, image: KeyframeImage) -> Annotated[np.ndarray, "(D,) float32"]:
        """The whole keyframe through the image tower, as an image query: CLIP's own embedding
        of the place (a photo of a bedroom lies near "bedroom"), for naming rooms."""
        return self.encode_image(image.rgb)
