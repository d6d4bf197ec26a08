"""3D footprints of tracks: back-projection, projection into another view, occlusion, merging."""

from __future__ import annotations

import numpy as np

from services.tracker.association import mask_iou
from services.tracker.footprints import mask_footprint, merge_footprints, project_footprint
from shared.geometry import Intrinsics

K = Intrinsics(fx=100.0, fy=100.0, cx=32.0, cy=24.0, width=64, height=48)


def pose(x: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def square(y0: int, x0: int, size: int = 12) -> np.ndarray:
    m = np.zeros((48, 64), bool)
    m[y0 : y0 + size, x0 : x0 + size] = True
    return m


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(mask_iou(a[None], b[None])[0, 0])


def test_same_view_gives_the_mask_back():
    depth = np.full((48, 64), 2.0, np.float32)
    mask = square(16, 20)
    fp = mask_footprint(mask, depth, K, pose())
    assert fp is not None and fp.points.shape[1] == 3
    np.testing.assert_allclose(fp.points[:, 2], 2.0)
    assert iou(project_footprint(fp, depth, K, pose()), mask) > 0.95


def test_sampled_footprint_is_closed_again():
    depth = np.full((48, 64), 2.0, np.float32)
    mask = square(8, 8, size=30)
    fp = mask_footprint(mask, depth, K, pose(), max_points=100)
    assert len(fp.points) <= 120
    assert iou(project_footprint(fp, depth, K, pose()), mask) > 0.8


def test_camera_motion_moves_the_prediction():
    depth = np.full((48, 64), 2.0, np.float32)
    fp = mask_footprint(square(16, 20), depth, K, pose())
    # The camera moves 0.2 m to the right: at 2 m the square moves fx * 0.2 / 2 = 10 px left.
    moved = project_footprint(fp, depth, K, pose(0.2))
    assert iou(moved, square(16, 10)) > 0.9
    # Out of view altogether.
    assert not project_footprint(fp, depth, K, pose(5.0)).any()


def test_hidden_points_are_dropped():
    depth = np.full((48, 64), 2.0, np.float32)
    fp = mask_footprint(square(16, 20), depth, K, pose())
    occluded = depth.copy()
    occluded[:, :26] = 1.0  # something 1 m in front covers the left half of the square
    seen = project_footprint(fp, occluded, K, pose())
    assert seen[:, 27:].sum() > 0 and not seen[:, :26].any()
    # Without a depth reading a point cannot be tested and counts as seen.
    assert iou(project_footprint(fp, np.zeros_like(depth), K, pose()), square(16, 20)) > 0.95


def test_points_the_camera_sees_through_are_dropped():
    depth = np.full((48, 64), 2.0, np.float32)
    fp = mask_footprint(square(16, 20), depth, K, pose())
    # The object has gone: where it stood the camera now sees the wall 1 m behind it.
    gone = depth.copy()
    gone[:, 26:] = 3.0
    seen = project_footprint(fp, gone, K, pose())
    assert seen[:, 20:25].any() and not seen[:, 27:].any()


def test_no_depth_no_footprint():
    assert mask_footprint(square(0, 0), np.zeros((48, 64), np.float32), K, pose()) is None


def test_merge_keeps_both_views_within_the_budget():
    depth = np.full((48, 64), 2.0, np.float32)
    a = mask_footprint(square(4, 4), depth, K, pose())
    b = mask_footprint(square(30, 40), depth, K, pose())
    both = merge_footprints(a, b, max_points=10_000)
    assert len(both.points) == len(a.points) + len(b.points)
    union = project_footprint(both, depth, K, pose())
    assert union[4:16, 4:16].all() and union[30:42, 40:52].all()
    thin = merge_footprints(a, b, max_points=50)
    assert len(thin.points) <= 50 and thin.spacing_m >= a.spacing_m
    assert merge_footprints(None, b) is b and merge_footprints(a, None) is a
