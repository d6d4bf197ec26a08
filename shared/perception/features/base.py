"""What every dense-feature backend takes and returns, and the input-resize rule they share.

Kept free of torch at import time: the tracker's node and the CLI import this module to size
the patch grid before any backend (and its heavy dependencies) is built.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Annotated, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    import torch

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
"""DINOv3's LVD-1689M backbones (the paper's ViT-S+) were trained with ImageNet statistics."""


def _snap(length: float, patch_size: int) -> int:
    # Round half up (not Python's banker's rounding) so the rule is easy to state and pin.
    return max(patch_size, int(math.floor(length / patch_size + 0.5)) * patch_size)


def resized_shape(height: int, width: int, short_side: int, patch_size: int) -> tuple[int, int]:
    """Network input size (H', W'): the short side scaled to ``short_side``, aspect kept.

    Both sides are rounded to the nearest multiple of ``patch_size`` (half up), at least one
    patch. Examples (patch 16): 680x1200 at 720 -> 720x1264; 480x640 at 480 -> 480x640;
    680x1200 at 480 -> 480x848; 1200x680 at 720 -> 1264x720.
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    target_short = _snap(short_side, patch_size)
    scale = target_short / min(height, width)
    if height <= width:
        return target_short, _snap(width * scale, patch_size)
    return _snap(height * scale, patch_size), target_short


def grid_shape(height: int, width: int, short_side: int, patch_size: int) -> tuple[int, int]:
    """Patch grid (h, w) of an H x W image: ``resized_shape`` divided by the patch size."""
    rh, rw = resized_shape(height, width, short_side, patch_size)
    return rh // patch_size, rw // patch_size


@runtime_checkable
class DenseFeatures(Protocol):
    """Dense per-patch features (DINOv3 ViT-S+/16 in the paper)."""

    name: str
    patch_size: int
    dim: int
    appearance_dims: int
    """The leading channels that describe appearance whatever the viewpoint: eq. 2's mask
    prototypes, which must match an object seen again from elsewhere, use only these
    (renormalised). All of them for DINOv3."""

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        """Patch grid (h, w) that ``__call__`` returns for an H x W image."""
        ...

    def __call__(
        self,
        rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
        depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 = none"] | None = None,
    ) -> Annotated[torch.Tensor, "(h, w, D) float32, unit L2 norm per patch"]:
        """Features of one frame on the backend's device. Learned backends ignore depth."""
        ...


class PatchGridMixin(ABC):
    """The resize rule as methods, for backends that hold ``short_side`` and ``patch_size``,
    and the call they share: the frame is checked and its network input size worked out here,
    the features themselves come from the backend's :meth:`features`."""

    short_side: int
    patch_size: int

    def resized_shape(self, height: int, width: int) -> tuple[int, int]:
        return resized_shape(height, width, self.short_side, self.patch_size)

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        return grid_shape(height, width, self.short_side, self.patch_size)

    def __call__(
        self,
        rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
        depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 = none"] | None = None,
    ) -> Annotated[torch.Tensor, "(h, w, D) float32, unit L2 norm per patch"]:
        height, width = check_inputs(rgb, depth_m)
        return self.features(rgb, depth_m, self.resized_shape(height, width))

    @abstractmethod
    def features(
        self,
        rgb: Annotated[np.ndarray, "(H, W, 3) uint8, checked"],
        depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 = none"] | None,
        size: tuple[int, int],
    ) -> Annotated[torch.Tensor, "(h, w, D) float32, unit L2 norm per patch"]:
        """Features of one checked frame resized to ``size`` (H', W', whole patches)."""


def check_inputs(
    rgb: np.ndarray, depth_m: np.ndarray | None
) -> tuple[int, int]:
    """Validates one frame and returns (H, W); a bad frame is a caller bug, so it raises."""
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        desc = f"{rgb.dtype} {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise ValueError(f"rgb must be an (H, W, 3) uint8 array, got {desc}")
    height, width = rgb.shape[:2]
    if depth_m is not None and (not isinstance(depth_m, np.ndarray) or depth_m.shape != (height, width)):
        shape = depth_m.shape if isinstance(depth_m, np.ndarray) else type(depth_m).__name__
        raise ValueError(f"depth_m must be an ({height}, {width}) array, got {shape}")
    return height, width
