"""What every segmenter and VL encoder takes and returns, whatever its backend."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Protocol

import numpy as np

from shared.geometry import Intrinsics


@dataclass(frozen=True)
class KeyframeImage:
    """One keyframe as the perception backends see it. It carries no ground truth: the
    simulated backends read theirs by ``frame_index`` from the source they were made with
    (:mod:`shared.datasets.ground_truth`)."""

    frame_index: int
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]
    depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 = none"] | None = None
    intrinsics: Intrinsics | None = None


@dataclass(frozen=True)
class Masks:
    """Class-agnostic masks of one keyframe, best score first."""

    masks: Annotated[np.ndarray, "(N, H, W) bool"]
    boxes: Annotated[np.ndarray, "(N, 4) float32 x0, y0, x1, y1 pixels"]
    scores: Annotated[np.ndarray, "(N,) float32"]

    def __len__(self) -> int:
        return int(self.masks.shape[0])

    @staticmethod
    def empty(height: int, width: int) -> Masks:
        return Masks(np.zeros((0, height, width), bool), np.zeros((0, 4), np.float32), np.zeros(0, np.float32))


class Segmenter(Protocol):
    """Class-agnostic segmentation backend (FastSAM in the paper)."""

    name: str

    def segment(self, image: KeyframeImage) -> Masks:
        """Masks filtered by area (config ``min_area_px``, ``max_area_frac``)."""
        ...


class VLEncoder(Protocol):
    """Vision-language encoder (CLIP in the paper). Every output row is L2-normalised."""

    name: str
    dim: int

    def encode_crops(self, image: KeyframeImage, masks: Masks) -> Annotated[np.ndarray, "(N, D) float32"]:
        """One feature per mask, from its padded bounding-box crop."""
        ...

    def encode_text(self, texts: list[str]) -> Annotated[np.ndarray, "(N, D) float32"]:
        ...

    def encode_image(self, rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]) -> Annotated[np.ndarray, "(D,) float32"]:
        """A whole image (an image query)."""
        ...

    def encode_view(self, image: KeyframeImage) -> Annotated[np.ndarray, "(D,) float32"]:
        """The whole keyframe, L2-normalised: what the place looks like (room naming).

        Optional: a caller that finds no ``encode_view`` on an encoder sends no view (the
        keyframe's ``MaskFeatures.view`` stays None)."""
        ...
