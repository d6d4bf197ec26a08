"""Padded bounding-box crops of keyframe masks (paper III-B), and batching.

Boxes are taken from each mask's own pixels, not from ``Masks.boxes``: segmenters may round
or pad their boxes differently, and the pixels are unambiguous. A box is half-open,
``[x0, x1) x [y0, y1)``, and is padded by ``padding`` times its width (height) on the left
and right (top and bottom), rounded outwards to whole pixels and clipped to the image. The paper
gives no padding; ``keyframe_vl.vl.crop_padding`` defaults to 0.1.

CLIP sees a square. ``keyframe_vl.vl.crop_mode`` says how a crop becomes one:
``pad_square`` (the default) centres it on a square of CLIP's mean colour, so the resize that
follows keeps every pixel; ``center_crop`` leaves it to OpenCLIP's transform, which resizes
the short side and keeps only the middle square (a 165x6 crop keeps 6 of its 165 columns).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Annotated, Literal, TypeVar

import numpy as np

T = TypeVar("T")

CropMode = Literal["pad_square", "center_crop"]
CROP_MODES: tuple[CropMode, ...] = ("pad_square", "center_crop")


def fill_colour(mean: tuple[float, float, float] | list[float]) -> tuple[int, int, int]:
    """The uint8 colour that normalises to (about) zero under CLIP's ``mean``: padding with it
    adds no signal to the crop."""
    return tuple(int(round(255.0 * float(m))) for m in mean)  # type: ignore[return-value]


def square_offsets(h: int, w: int) -> tuple[int, int, int]:
    """``(side, top, left)``: the square a ``h`` x ``w`` crop is centred on."""
    side = max(h, w)
    return side, (side - h) // 2, (side - w) // 2


def pad_to_square(
    crop: Annotated[np.ndarray, "(h, w, 3) uint8"], fill: tuple[int, int, int]
) -> Annotated[np.ndarray, "(s, s, 3) uint8, s = max(h, w)"]:
    """``crop`` centred on a square of ``fill``; a square crop comes back as it is."""
    h, w = crop.shape[:2]
    if h == w:
        return crop
    side, top, left = square_offsets(h, w)
    out = np.empty((side, side, 3), np.uint8)
    out[...] = np.asarray(fill, np.uint8)
    out[top : top + h, left : left + w] = crop
    return out


def shape_crops(
    crops: list[np.ndarray], mode: CropMode, fill: tuple[int, int, int]
) -> list[np.ndarray]:
    """The crops as ``mode`` hands them to CLIP's own transform (see the module doc)."""
    if mode == "center_crop":
        return crops
    if mode == "pad_square":
        return [pad_to_square(c, fill) for c in crops]
    raise ValueError(f"crop mode {mode!r}: expected one of {', '.join(CROP_MODES)}")


def mask_box(mask: Annotated[np.ndarray, "(H, W) bool"]) -> tuple[int, int, int, int] | None:
    """Tight half-open box ``(x0, y0, x1, y1)`` of the mask's pixels; None when it is empty."""
    cols = np.flatnonzero(mask.any(axis=0))
    if cols.size == 0:
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def pad_box(
    box: tuple[float, float, float, float], padding: float, width: int, height: int
) -> tuple[int, int, int, int]:
    """``box`` grown by ``padding`` x its size on each side, in whole pixels, clipped to the
    image; never empty (at least one pixel, even for a degenerate box)."""
    x0, y0, x1, y1 = (float(v) for v in box)
    px = padding * max(x1 - x0, 0.0)
    py = padding * max(y1 - y0, 0.0)
    # The small tolerance keeps exact products (e.g. 0.1 * 30 = 3.0000000000000004) from
    # being rounded out by a whole extra pixel.
    eps = 1e-9
    cx0 = min(max(math.floor(x0 - px + eps), 0), width - 1)
    cy0 = min(max(math.floor(y0 - py + eps), 0), height - 1)
    cx1 = max(min(math.ceil(x1 + px - eps), width), cx0 + 1)
    cy1 = max(min(math.ceil(y1 + py - eps), height), cy0 + 1)
    return cx0, cy0, cx1, cy1


def padded_boxes(
    masks: Annotated[np.ndarray, "(N, H, W) bool"],
    fallback_boxes: Annotated[np.ndarray, "(N, 4) float x0, y0, x1, y1"] | None,
    padding: float,
) -> Annotated[np.ndarray, "(N, 4) int64 x0, y0, x1, y1, half-open"]:
    """The padded crop box of every mask. An empty mask falls back to its ``fallback_boxes``
    row (the segmenter's box), as the pixels then say nothing."""
    n, height, width = masks.shape
    out = np.zeros((n, 4), np.int64)
    for j in range(n):
        box = mask_box(masks[j])
        if box is None:
            if fallback_boxes is None:
                raise ValueError(f"mask {j} is empty and no fallback box was given")
            box = tuple(float(v) for v in fallback_boxes[j])
        out[j] = pad_box(box, padding, width, height)
    return out


def padded_crops(
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
    masks: Annotated[np.ndarray, "(N, H, W) bool"],
    padding: float,
    fallback_boxes: Annotated[np.ndarray, "(N, 4) float"] | None = None,
) -> list[Annotated[np.ndarray, "(h, w, 3) uint8"]]:
    """One contiguous uint8 copy of the padded bounding-box crop of each mask."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {rgb.dtype} {rgb.shape}")
    if masks.ndim != 3 or masks.shape[1:] != rgb.shape[:2]:
        raise ValueError(f"masks of shape {masks.shape} do not match the image {rgb.shape[:2]}")
    boxes = padded_boxes(masks, fallback_boxes, padding)
    return [np.ascontiguousarray(rgb[y0:y1, x0:x1]) for x0, y0, x1, y1 in boxes]


def batched(items: Sequence[T], size: int) -> Iterator[Sequence[T]]:
    """Consecutive slices of at most ``size`` items (the last may be shorter)."""
    if size < 1:
        raise ValueError(f"batch size must be at least 1 (got {size})")
    for start in range(0, len(items), size):
        yield items[start : start + size]
