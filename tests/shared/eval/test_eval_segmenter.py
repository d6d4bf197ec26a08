"""Per-image best IoU of segmenter masks (shared/eval/segmenter.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.eval import mean_best_iou


def gt() -> np.ndarray:
    m = np.full((20, 20), -1, np.int32)
    m[0:10, 0:10] = 3  # 100 px
    m[10:20, 10:20] = 8  # 100 px
    m[19, 0] = 5  # 1 px: below 0.5 % of 400 px, not scored
    return m


def test_perfect_masks():
    g = gt()
    masks = np.stack([g == 3, g == 8, g == 5])
    mean, per = mean_best_iou(masks, g)
    assert mean == 1.0 and per == {3: 1.0, 8: 1.0}


def test_best_mask_per_object_worked_by_hand():
    """Object 3 has two candidates: half of it (IoU 50/100) and itself plus 20 px (100/120);
    object 8 only overlaps a 10 x 5 corner mask (IoU 50/100). Overlapping masks are fine."""
    g = gt()
    half = np.zeros_like(g, bool)
    half[0:5, 0:10] = True
    bigger = g == 3
    bigger[10:12, 0:10] = True
    corner = np.zeros_like(g, bool)
    corner[10:20, 10:15] = True
    mean, per = mean_best_iou(np.stack([half, bigger, corner]), g)
    assert per == {3: pytest.approx(100 / 120), 8: pytest.approx(0.5)}
    assert mean == pytest.approx((100 / 120 + 0.5) / 2)


def test_no_masks_and_no_objects():
    mean, per = mean_best_iou(np.zeros((0, 20, 20), bool), gt())
    assert mean == 0.0 and per == {3: 0.0, 8: 0.0}
    mean, per = mean_best_iou(np.zeros((1, 20, 20), bool), np.full((20, 20), -1))
    assert math.isnan(mean) and per == {}


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="pred_masks"):
        mean_best_iou(np.zeros((1, 10, 10), bool), gt())
