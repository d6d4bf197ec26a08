"""Per-image mask quality of a class-agnostic segmenter against ground-truth instances."""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np

MIN_AREA_FRAC = 0.005
"""Ground-truth objects smaller than this share of the image are not scored."""


def mean_best_iou(
    pred_masks: Annotated[np.ndarray, "(N, H, W) bool"],
    gt_instances: Annotated[np.ndarray, "(H, W) int, object id >= 0, negative = none"],
    min_area_frac: float = MIN_AREA_FRAC,
) -> tuple[float, dict[int, float]]:
    """For each ground-truth object covering at least ``min_area_frac`` of the image, the best
    IoU any predicted mask reaches with it (0 without masks). Returns the mean over those
    objects (NaN when there is none) and the per-object values by object id.

    Masks may overlap each other (a segmenter's raw output); each is compared on its own.
    """
    gt = np.asarray(gt_instances)
    if gt.ndim != 2:
        raise ValueError(f"gt_instances must be (H, W) (got {gt.shape})")
    masks = np.asarray(pred_masks, dtype=bool)
    if masks.ndim == 2:
        masks = masks[None]
    if masks.ndim != 3 or (len(masks) and masks.shape[1:] != gt.shape):
        raise ValueError(f"pred_masks must be (N, {gt.shape[0]}, {gt.shape[1]}) (got {masks.shape})")
    ids, inv, area = np.unique(gt.reshape(-1), return_inverse=True, return_counts=True)
    keep = (ids >= 0) & (area >= min_area_frac * gt.size)
    if not keep.any():
        return math.nan, {}
    row = np.full(len(ids), -1, np.int64)
    row[keep] = np.arange(int(keep.sum()))
    obj_of_pixel = row[inv.reshape(-1)]
    n_obj, n_masks = int(keep.sum()), len(masks)
    best = np.zeros(n_obj)
    if n_masks:
        flat = masks.reshape(n_masks, -1)
        m_idx, px = np.nonzero(flat)
        o = obj_of_pixel[px]
        ok = o >= 0
        inter = np.bincount(m_idx[ok] * n_obj + o[ok], minlength=n_masks * n_obj).reshape(n_masks, n_obj)
        union = flat.sum(axis=1)[:, None] + area[keep][None, :] - inter
        iou = np.divide(inter, union, out=np.zeros(inter.shape), where=union > 0)
        best = iou.max(axis=0)
    per_object = {int(i): float(b) for i, b in zip(ids[keep], best, strict=True)}
    return float(best.mean()), per_object
