"""Voxel anchors: the numba kernel updates the grid's views in place exactly as the numpy rule
computes them (new voxels, voxels the frame added weight to, voxels it left alone)."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.volume import anchors


@pytest.mark.skipif(anchors.numba is None, reason="numba is not installed")
@pytest.mark.parametrize("seed", range(4))
def test_the_kernel_equals_the_rule_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    cap, res = 40, 8
    weight = rng.choice([0.0, 1.0, 2.0, 7.5, 30.0], size=(cap, res, res, res, 1)).astype(np.float32)
    anchor = rng.integers(0, 500, (cap, res, res, res, 1)).astype(np.int32)
    bufs = rng.choice(cap, 25, replace=False).astype(np.int64)
    # before: the frame's blocks as they were; some voxels new (0), some untouched (= after)
    after = weight[bufs].reshape(len(bufs), -1)
    before = np.where(rng.random(after.shape) < 0.3, after, np.maximum(after - rng.choice([0.0, 1.0, 2.0], after.shape), 0)).astype(np.float32)
    before[rng.random(after.shape) < 0.2] = 0.0
    frame = 517
    want = anchor.copy()
    want[bufs] = anchors.anchor_rule(after.astype(np.float64), anchor[bufs].reshape(len(bufs), -1).astype(np.float64), before, frame).reshape(len(bufs), res, res, res, 1)
    got = anchor.copy()
    assert anchors.anchor_in_place(weight, got, bufs, before, frame)
    np.testing.assert_array_equal(got, want)
    # every case was there: new voxels, weighted means, voxels the frame left alone
    added = after - before
    assert (added > 0).any() and ((added <= 0) & (before > 0)).any() and ((added <= 0) & (before <= 0)).any()
    assert (got[bufs].reshape(len(bufs), -1)[(added > 0) & (before > 0)] != frame).any()


def test_views_that_are_not_contiguous_numpy_take_the_numpy_rule():
    weight = np.zeros((4, 2, 2, 2, 2), np.float32)[..., :1]  # a strided view
    anchor = np.zeros((4, 2, 2, 2, 1), np.int32)
    assert not anchors.anchor_in_place(weight, anchor, np.array([0]), np.zeros((1, 8), np.float32), 3)
