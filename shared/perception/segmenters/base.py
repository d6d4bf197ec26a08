"""What every segmenter backend shares: the area filter, the per-keyframe mask budget, boxes
from masks, and label images turned into masks. Every backend builds its :class:`Masks` here,
so the filtering rules of ``SegmenterBackend`` hold whichever backend runs."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import numpy as np

from shared.perception import Masks
from shared.perception.segmenters.config import SegmenterBackend

log = logging.getLogger(__name__)


def boxes_from_masks(
    masks: Annotated[np.ndarray, "(N, H, W) bool"],
) -> Annotated[np.ndarray, "(N, 4) float32 x0, y0, x1, y1 pixels, x1 and y1 exclusive"]:
    """Tight box of each mask. The far edges are exclusive so ``rgb[y0:y1, x0:x1]`` is exactly
    the box (an empty mask gets an all-zero box)."""
    n = masks.shape[0]
    out = np.zeros((n, 4), np.float32)
    if n == 0:
        return out
    rows = masks.any(axis=2)
    cols = masks.any(axis=1)
    has = rows.any(axis=1)
    h, w = masks.shape[1:]
    # argmax finds the first True; on the reversed axis it finds the last one.
    out[:, 0] = cols.argmax(axis=1)
    out[:, 1] = rows.argmax(axis=1)
    out[:, 2] = w - cols[:, ::-1].argmax(axis=1)
    out[:, 3] = h - rows[:, ::-1].argmax(axis=1)
    out[~has] = 0
    return out


def finalize(
    masks: Annotated[np.ndarray, "(N, H, W) bool"],
    scores: Annotated[np.ndarray, "(N,) float"],
    cfg: SegmenterBackend,
) -> Masks:
    """Apply the area filter (``min_area_px``, ``max_area_frac``; empty masks always go), keep
    the ``max_masks`` best by score (stable for ties) and attach tight boxes."""
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3:
        raise ValueError(f"masks must be (N, H, W) (got {masks.shape})")
    scores = np.asarray(scores, dtype=np.float32).reshape(-1)
    if scores.shape[0] != masks.shape[0]:
        raise ValueError(f"{masks.shape[0]} masks but {scores.shape[0]} scores")
    h, w = masks.shape[1:]
    area = masks.reshape(masks.shape[0], -1).sum(axis=1)
    keep = (area > 0) & (area >= cfg.min_area_px) & (area <= cfg.max_area_frac * h * w)
    idx = np.flatnonzero(keep)
    idx = idx[np.argsort(-scores[idx], kind="stable")][: cfg.max_masks]
    if len(idx) < masks.shape[0]:
        log.debug("kept %d of %d masks after area filter and max_masks", len(idx), masks.shape[0])
    kept = np.ascontiguousarray(masks[idx])
    return Masks(kept, boxes_from_masks(kept), scores[idx].copy())


def finalize_labels(
    labels: Annotated[np.ndarray, "(H, W) int, label >= 0, negative = no mask"],
    scores: Annotated[np.ndarray, "(L,) float, score of each label 0 .. L-1"],
    cfg: SegmenterBackend,
) -> Masks:
    """Masks of a label image (one per label), filtered like :func:`finalize`. The filter runs on
    label areas first so a fine partition never materialises hundreds of full-size masks."""
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"labels must be (H, W) (got {labels.shape})")
    scores = np.asarray(scores, dtype=np.float32).reshape(-1)
    flat = labels.reshape(-1)
    valid = flat >= 0
    if valid.any() and int(flat[valid].max()) >= len(scores):
        raise ValueError(f"label {int(flat[valid].max())} has no score ({len(scores)} scores)")
    area = np.bincount(flat[valid], minlength=len(scores))
    h, w = labels.shape
    keep = (area > 0) & (area >= cfg.min_area_px) & (area <= cfg.max_area_frac * h * w)
    idx = np.flatnonzero(keep)
    idx = idx[np.argsort(-scores[idx], kind="stable")][: cfg.max_masks]
    masks = labels[None, :, :] == idx[:, None, None]
    return Masks(masks, boxes_from_masks(masks), scores[idx].copy())


def check_image(rgb: np.ndarray) -> tuple[int, int]:
    """(H, W) of an (H, W, 3) uint8 image; anything else is a ValueError."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8 (got {rgb.shape} {rgb.dtype})")
    return int(rgb.shape[0]), int(rgb.shape[1])


def require_file(path: str | Path, what: str, how_to_get: str) -> Path:
    """``path`` as a Path if it is a file; otherwise a FileNotFoundError that names the path and
    how to obtain the file. Weights are never downloaded: robots and GPU servers may be offline,
    and a silent download hides which weights a map was built with."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"{what} not found at {p.resolve()}: {how_to_get}")
    return p
