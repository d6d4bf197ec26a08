"""The shared mask filter: area limits, the per-keyframe budget, boxes."""

from __future__ import annotations

import numpy as np
import pytest

from shared.perception.segmenters.base import (
    boxes_from_masks,
    finalize,
    finalize_labels,
    require_file,
)
from shared.perception.segmenters.config import segmenter_config


def _rect(h, w, y0, y1, x0, x1):
    m = np.zeros((h, w), bool)
    m[y0:y1, x0:x1] = True
    return m


def test_boxes_are_tight_with_exclusive_far_edges():
    masks = np.stack([_rect(20, 30, 2, 5, 3, 9), np.zeros((20, 30), bool), _rect(20, 30, 0, 20, 29, 30)])
    boxes = boxes_from_masks(masks)
    assert boxes.dtype == np.float32
    np.testing.assert_array_equal(boxes, [[3, 2, 9, 5], [0, 0, 0, 0], [29, 0, 30, 20]])


def test_finalize_filters_by_area_and_keeps_best_scores():
    h, w = 40, 50
    masks = np.stack(
        [
            _rect(h, w, 0, 5, 0, 5),  # 25 px: below min_area_px
            _rect(h, w, 0, 40, 0, 50),  # whole image: above max_area_frac
            _rect(h, w, 10, 20, 10, 20),  # 100 px
            _rect(h, w, 20, 35, 20, 35),  # 225 px
            _rect(h, w, 0, 12, 30, 45),  # 180 px
            np.zeros((h, w), bool),
        ]
    )
    scores = np.array([0.99, 0.98, 0.5, 0.9, 0.7, 1.0])
    cfg = segmenter_config(min_area_px=50, max_area_frac=0.9, max_masks=2)
    out = finalize(masks, scores, cfg)
    assert len(out) == 2
    assert out.masks.dtype == bool and out.masks.shape == (2, h, w)
    np.testing.assert_allclose(out.scores, [0.9, 0.7])
    np.testing.assert_array_equal(out.masks[0], masks[3])
    np.testing.assert_array_equal(out.boxes, [[20, 20, 35, 35], [30, 0, 45, 12]])


def test_finalize_labels_matches_finalize_on_the_same_masks():
    rng = np.random.default_rng(3)
    labels = rng.integers(-1, 6, (30, 40))
    labels[:15, :20] = 2
    scores = rng.random(6)
    cfg = segmenter_config(min_area_px=60, max_masks=4)
    a = finalize_labels(labels, scores, cfg)
    b = finalize(np.stack([labels == i for i in range(6)]), scores, cfg)
    np.testing.assert_array_equal(a.masks, b.masks)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.scores, b.scores)


def test_finalize_rejects_mismatched_scores():
    with pytest.raises(ValueError, match="scores"):
        finalize(np.zeros((2, 4, 4), bool), np.zeros(3), segmenter_config())


def test_require_file_names_the_path(tmp_path):
    missing = tmp_path / "nope" / "FastSAM-x.pt"
    with pytest.raises(FileNotFoundError, match="nope/FastSAM-x.pt"):
        require_file(missing, "FastSAM checkpoint", "get it somewhere")
