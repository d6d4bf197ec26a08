"""Per-voxel hypotheses of the TSDF: eq. 6 confidences and the slot rule of III-C on one voxel."""

from __future__ import annotations

import numpy as np
import pytest

from shared.config.fusion import TSDFConfig
from shared.geometry import Intrinsics
from shared.o3d import import_open3d

try:
    import_open3d()
except ImportError:
    pytest.skip("open3d is not installed (fusion extra)", allow_module_level=True)

from services.fusion.volume.hypotheses import confidence, numba_available  # noqa: E402
from services.fusion.volume.tsdf import HypothesisTSDF  # noqa: E402

BACKENDS = ["torch"] + (["numba"] if numba_available() else [])

# An 8x8 camera looking at a plane 1.5 m away: all 64 pixels land in voxel (0, 0, 50) at 3 cm
# (|u - 3.5| / 1000 * 1.5 <= 5.25 mm). Each frame labels the four 4x4 quadrants, so a track
# covers an exact fraction of the voxel's pixels.
K8 = Intrinsics(fx=1000.0, fy=1000.0, cx=3.5, cy=3.5, width=8, height=8)
DEPTH = np.full((8, 8), 1.5, np.float32)
RGB = np.full((8, 8, 3), 128, np.uint8)
VOXEL = np.array([[0.0, 0.0, 1.5]])


def _quadrants(tracks: list[int]) -> np.ndarray:
    return np.array(tracks, np.int32).reshape(2, 2).repeat(4, axis=0).repeat(4, axis=1)


def _frame(tsdf: HypothesisTSDF, tracks: list[int], gamma: dict[int, float]):
    return tsdf.integrate(DEPTH, RGB, K8, np.eye(4), _quadrants(tracks), gamma)


def _slots(tsdf: HypothesisTSDF) -> dict[int, float]:
    ids, w = tsdf.hypotheses_at(VOXEL)
    return {int(i): float(x) for i, x in zip(ids[0], w[0], strict=True) if i >= 0}


def test_confidence_eq6():
    assert confidence(True, 0, 0.25, 0.1) == 1.0
    assert confidence(True, 17, 0.25, 0.1) == 1.0
    assert confidence(False, 0, 0.25, 0.1) == pytest.approx(0.25)
    assert confidence(False, 5, 0.25, 0.1) == pytest.approx(0.25 / 1.5)
    assert confidence(False, 23, 0.25, 0.1) == pytest.approx(0.25 / 3.3)
    assert confidence(False, 10, 0.5, 0.0) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        confidence(False, -1, 0.25, 0.1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_slot_fill_replace_and_displaced_weight(backend):
    tsdf = HypothesisTSDF(TSDFConfig(hypotheses=2, vote_backend=backend), device="cpu")

    st = _frame(tsdf, [10, 10, 10, 10], {10: 1.0})
    assert _slots(tsdf) == {10: 1.0}
    assert (st.new_hypotheses, st.replaced, st.displaced) == (1, 0, {})
    assert (st.pixels_voted, st.voxels_voted) == (64, 1)

    # a known track accumulates gamma * (its pixels / the voxel's pixels); a new one fills the
    # empty slot
    st = _frame(tsdf, [10, 10, 11, 11], {10: 1.0, 11: 0.5})
    assert _slots(tsdf) == {10: 1.5, 11: 0.25}
    assert (st.new_hypotheses, st.replaced, st.displaced) == (1, 0, {})

    # all K slots full: the newcomer replaces the lowest weight, which is reported as displaced;
    # the unmasked pixel counts in the voxel's pixels but votes for nobody
    st = _frame(tsdf, [12, 12, 12, -1], {12: 1.0})
    assert _slots(tsdf) == {10: 1.5, 12: 0.75}
    assert (st.new_hypotheses, st.replaced, st.dropped) == (1, 1, 0)
    assert st.displaced == {11: 0.25}
    assert st.pixels_voted == 48

    # two newcomers in one frame: the stronger (13) takes the lowest slot (12); the weaker (14)
    # finds the lowest slot taken by 13 and is dropped rather than evicting track 10
    st = _frame(tsdf, [13, 13, 14, 10], {13: 1.0, 14: 1.0, 10: 1.0})
    assert _slots(tsdf) == {10: 1.75, 13: 0.5}
    assert (st.new_hypotheses, st.replaced, st.dropped) == (1, 1, 1)
    assert st.displaced == {12: 0.75, 14: 0.25}

    # a propagated mask (eq. 6) adds less
    g = confidence(False, 2, 0.25, 0.1)
    st = _frame(tsdf, [13, 13, 13, 13], {13: g})
    assert _slots(tsdf) == {10: 1.75, 13: float(np.float32(0.5) + np.float32(g))}
    assert st.displaced == {}


@pytest.mark.parametrize("backend", BACKENDS)
def test_lowest_weight_tie_takes_first_slot(backend):
    tsdf = HypothesisTSDF(TSDFConfig(hypotheses=2, vote_backend=backend), device="cpu")
    _frame(tsdf, [1, 1, 2, 2], {1: 1.0, 2: 1.0})
    assert _slots(tsdf) == {1: 0.5, 2: 0.5}
    ids, _ = tsdf.hypotheses_at(VOXEL)
    first = int(ids[0, 0])
    st = _frame(tsdf, [3, 3, 3, 3], {3: 0.2})
    assert st.displaced == {first: 0.5}
    assert int(tsdf.hypotheses_at(VOXEL)[0][0, 0]) == 3


@pytest.mark.parametrize("backend", BACKENDS)
def test_unknown_track_fails_before_any_change(backend):
    tsdf = HypothesisTSDF(TSDFConfig(vote_backend=backend), device="cpu")
    with pytest.raises(ValueError, match="99"):
        _frame(tsdf, [5, 99, 5, 5], {5: 1.0})
    assert tsdf.active_blocks == 0
    st = _frame(tsdf, [-1, -1, -1, -1], {})
    assert st.active_blocks > 0 and st.pixels_voted == 0
    assert _slots(tsdf) == {}


def test_input_validation():
    tsdf = HypothesisTSDF(TSDFConfig(), device="cpu")
    with pytest.raises(ValueError, match="intrinsics"):
        tsdf.integrate(np.ones((3, 2), np.float32), RGB, K8, np.eye(4))
    with pytest.raises(ValueError, match="rgb"):
        tsdf.integrate(DEPTH, RGB.astype(np.float32), K8, np.eye(4))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="rigid"):
        tsdf.integrate(DEPTH, RGB, K8, bad)
    with pytest.raises(ValueError, match="gamma"):
        _frame(tsdf, [1, 1, 1, 1], {1: float("nan")})


def test_depth_outside_range_is_ignored():
    tsdf = HypothesisTSDF(TSDFConfig(depth_min=0.5, depth_max=1.0), device="cpu")
    st = _frame(tsdf, [1, 1, 1, 1], {1: 1.0})
    assert (st.frame_blocks, st.active_blocks, st.pixels_voted) == (0, 0, 0)
    nan = np.full((8, 8), np.nan, np.float32)
    st = tsdf.integrate(nan, RGB, K8, np.eye(4), np.ones((8, 8), np.int32), {1: 1.0})
    assert st.active_blocks == 0
    # a single valid pixel that Open3D's strided block search does not sample
    one = np.zeros((8, 8), np.float32)
    one[3, 5] = 1.5
    st = tsdf.integrate(one, RGB, K8, np.eye(4))
    assert st.frame_blocks == tsdf.active_blocks
