"""A keyframe's masks read inside their boxes (services/tracker/masks_numba.py): the cell
coverage, slot counts, footprints and painted labels equal those of whole-image passes."""

from __future__ import annotations

import numpy as np
import pytest

from services.tracker import masks_numba
from services.tracker.association import area_fractions, label_mask_iou, mask_iou
from services.tracker.core import paint_labels
from services.tracker.footprints import mask_footprint
from services.tracker.masks_numba import mask_areas, mask_boxes
from shared.geometry import Intrinsics


def _masks(n: int, height: int, width: int, seed: int) -> np.ndarray:
    """Blobs of many sizes (ellipses, some with holes, one empty, one whole-image)."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:height, 0:width]
    out = np.zeros((n, height, width), bool)
    for i in range(n - 2):
        cy, cx = rng.uniform(0, height), rng.uniform(0, width)
        ry, rx = rng.uniform(1, height / 3), rng.uniform(1, width / 3)
        out[i] = ((ys - cy) / ry) ** 2 + ((xs - cx) / rx) ** 2 <= 1
        if i % 3 == 0:
            out[i] &= rng.random((height, width)) > 0.3
    out[n - 1] = True  # and out[n - 2] stays empty
    return out


def _reference_fractions(masks: np.ndarray, h: int, w: int) -> np.ndarray:
    n, height, width = masks.shape
    cy, cx = np.arange(height) * h // height, np.arange(width) * w // width
    counts = np.zeros((n, h, w), np.int64)
    for i in range(n):
        np.add.at(counts[i], (cy[:, None].repeat(width, 1)[masks[i]], cx[None, :].repeat(height, 0)[masks[i]]), 1)
    area = np.maximum(np.bincount(cy)[:, None] * np.bincount(cx)[None, :], 1)
    return (counts / area).astype(np.float32)


@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize(("height", "width", "h", "w"), [(68, 120, 7, 12), (240, 320, 48, 64), (31, 17, 5, 3)])
def test_boxed_passes_equal_whole_image_passes(height, width, h, w, kernel, monkeypatch):
    if not kernel:
        monkeypatch.setattr(masks_numba, "numba", None)
    masks = _masks(12, height, width, seed=height + w)
    boxes = mask_boxes(masks)
    assert boxes[10].tolist() == [0, 0, 0, 0] and boxes[11].tolist() == [0, height, 0, width]
    for i, (y0, y1, x0, x1) in enumerate(boxes.tolist()):  # tight: every pixel inside, each edge touched
        assert masks[i].sum() == masks[i, y0:y1, x0:x1].sum()
        if masks[i].any():
            assert masks[i, y0].any() and masks[i, y1 - 1].any() and masks[i, :, x0].any() and masks[i, :, x1 - 1].any()
    np.testing.assert_array_equal(mask_areas(masks, boxes), masks.reshape(len(masks), -1).sum(1))
    np.testing.assert_array_equal(area_fractions(masks, h, w, boxes), _reference_fractions(masks, h, w))
    np.testing.assert_array_equal(area_fractions(masks, h, w), _reference_fractions(masks, h, w))
    # predicted tracks as a slot image (disjoint), against the stack: the dense IoU
    slots = paint_labels(masks[:6], [1, 2, 3, 4, 5, 6], height, width) + 1  # 0 = none
    slots[slots > 5] = 0  # slot 6 painted, then dropped: not among the m = 5 counted
    dense = np.stack([slots == s for s in range(1, 6)])
    np.testing.assert_allclose(label_mask_iou(slots, 5, masks, boxes), mask_iou(dense, masks), rtol=0, atol=1e-7)
    # painted labels and footprints: the same with and without boxes
    ids = list(range(100, 112))
    np.testing.assert_array_equal(paint_labels(masks, ids, height, width, boxes), paint_labels(masks, ids, height, width))
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 4.0, (height, width)).astype(np.float32)
    depth[rng.random((height, width)) < 0.1] = 0.0
    depth[0, :] = np.nan
    K = Intrinsics(fx=100.0, fy=100.0, cx=width / 2, cy=height / 2, width=width, height=height)
    T = np.eye(4)
    T[:3, 3] = (0.5, -0.2, 1.0)
    for i in range(len(masks)):
        for cap in (20, 4000):  # sampled every few pixels on the image's grid, and whole
            a = mask_footprint(masks[i], depth, K, T, max_points=cap, box=tuple(boxes[i]))
            b = mask_footprint(masks[i], depth, K, T, max_points=cap)
            assert (a is None) == (b is None)
            if a is not None:
                np.testing.assert_array_equal(a.points, b.points)
                assert a.spacing_m == b.spacing_m


def test_slot_image_by_table_equals_the_sorted_lookup():
    from services.tracker.core import slot_image

    rng = np.random.default_rng(5)
    labels = rng.integers(-1, 60, (40, 50)).astype(np.int32)
    for slots in ([7, 3, 59, 12], [5], list(range(0, 60, 2)), [70, 3], [3, 9, 3]):
        ids = np.asarray(slots, np.int64)
        order = np.argsort(ids, kind="stable")
        pos = np.clip(np.searchsorted(ids[order], labels), 0, len(ids) - 1)
        want = np.where(ids[order][pos] == labels, order[pos] + 1, 0)
        got = slot_image(labels, slots)
        assert got.dtype == np.int64 and np.array_equal(got, want), slots
    assert not slot_image(labels, []).any()
    huge = [2**40]  # sparse huge ids: the sorted lookup
    assert not slot_image(labels, huge).any()
