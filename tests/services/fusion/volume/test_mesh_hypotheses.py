"""Hypotheses carried onto marching-cubes vertices from both voxels of their grid edge."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.volume.mesh import edge_ends, merge_hypotheses

VS = 0.03


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("t", [0.0, 0.25, 0.5, 0.9])
def test_edge_ends_and_shares(axis, t):
    base = np.array([4.0, -7.0, 12.0])
    g = base.copy()
    g[axis] += t
    (lo, hi), (s_lo, s_hi) = edge_ends(np.array([g * VS], np.float32), VS)
    step = np.zeros(3)
    step[axis] = 1.0
    if t == 0.0:
        # On a voxel centre: that voxel, whole, along whichever axis argmax picks.
        np.testing.assert_allclose(lo[0] / VS, base, atol=1e-4)
        assert s_lo[0] == pytest.approx(1.0, abs=1e-4) and s_hi[0] == pytest.approx(0.0, abs=1e-4)
        return
    np.testing.assert_allclose(lo[0] / VS, base, atol=1e-4)
    np.testing.assert_allclose(hi[0] / VS, base + step, atol=1e-4)
    assert s_lo[0] == pytest.approx(1 - t, abs=1e-4)
    assert s_hi[0] == pytest.approx(t, abs=1e-4)


def test_edge_ends_of_negative_coordinates():
    (lo, hi), (s_lo, s_hi) = edge_ends(np.array([[-0.7 * VS, 2 * VS, -3 * VS]]), VS)
    np.testing.assert_allclose(lo[0] / VS, [-1, 2, -3], atol=1e-9)
    np.testing.assert_allclose(hi[0] / VS, [0, 2, -3], atol=1e-9)
    assert s_lo[0] == pytest.approx(0.7) and s_hi[0] == pytest.approx(0.3)


def test_merge_adds_shared_tracks_and_keeps_the_k_heaviest():
    ids_a = np.array([[3, 5, -1, -1]], np.int32)
    w_a = np.array([[2.0, 1.0, 0.0, 0.0]])
    ids_b = np.array([[5, 9, 11, 12]], np.int32)
    w_b = np.array([[1.5, 0.5, 3.0, 0.1]])
    ids, w = merge_hypotheses(ids_a, w_a, ids_b, w_b, 4)
    # 5: 1.0 + 1.5; 12 (0.1) is the lightest of five and drops out
    assert ids.tolist() == [[11, 5, 3, 9]]
    np.testing.assert_allclose(w, [[3.0, 2.5, 2.0, 0.5]])
    assert ids.dtype == np.int32 and w.dtype == np.float32


def test_merge_drops_zero_weight_and_pads_empty_slots():
    ids_a = np.array([[7, -1], [-1, -1]], np.int32)
    w_a = np.array([[1.0, 0.0], [0.0, 0.0]])
    ids_b = np.array([[8, -1], [4, -1]], np.int32)
    w_b = np.array([[0.0, 0.0], [0.2, 0.0]])  # a share of 0: the far end of an edge
    ids, w = merge_hypotheses(ids_a, w_a, ids_b, w_b, 2)
    assert ids.tolist() == [[7, -1], [4, -1]]
    np.testing.assert_allclose(w, [[1.0, 0.0], [0.2, 0.0]])


def test_merge_ties_keep_the_first_set_first():
    ids, _ = merge_hypotheses(
        np.array([[2, -1]], np.int32), np.array([[1.0, 0.0]]),
        np.array([[1, -1]], np.int32), np.array([[1.0, 0.0]]), 2,
    )  # fmt: skip
    assert ids.tolist() == [[2, 1]]


def test_winner_is_the_interpolated_strongest():
    # the near end holds track 1 weakly, the far end track 2 strongly: at t = 0.3 track 2 wins
    # (0.3 * 5 > 0.7 * 1), at t = 0.1 track 1 (0.1 * 5 < 0.9 * 1)
    for t, winner in ((0.3, 2), (0.1, 1)):
        ids, w = merge_hypotheses(
            np.array([[1]], np.int32), np.array([[1.0 * (1 - t)]]),
            np.array([[2]], np.int32), np.array([[5.0 * t]]), 1,
        )  # fmt: skip
        assert int(ids[0, 0]) == winner


@pytest.mark.parametrize("seed", range(6))
def test_the_kernel_equals_the_numpy_rule_bit_for_bit(seed):
    from services.fusion.volume.mesh import merge_hypotheses_numpy, numba

    if numba is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(seed)
    v, ka, kb = 5000, int(rng.integers(1, 6)), int(rng.integers(1, 6))

    def hypotheses(k):
        # each track at most once per set; empties, zero weights (an edge end's share of 0),
        # equal weights (ties) and -1 ids with a weight, as voxels and edge shares give them
        ids = np.stack([rng.permutation(12)[:k] for _ in range(v)]).astype(np.int32)
        ids[rng.random((v, k)) < 0.3] = -1
        w = rng.choice([0.0, 0.5, 1.0, 2.0], size=(v, k)) * rng.choice([1.0, 0.25], size=(v, 1))
        smooth = rng.random(v) < 0.5
        w[smooth] = rng.random((int(smooth.sum()), k))
        return ids, w

    ids_a, w_a = hypotheses(ka)
    ids_b, w_b = hypotheses(kb)
    w_b[:, 0] = rng.random(v)  # continuous weights too
    for k in {1, min(4, ka + kb), ka + kb, ka + kb + 2}:
        got = merge_hypotheses(ids_a, w_a, ids_b, w_b, k)
        want = merge_hypotheses_numpy(ids_a, w_a, ids_b, w_b, k)
        assert got[0].dtype == want[0].dtype == np.int32 and got[1].dtype == want[1].dtype == np.float32
        assert np.array_equal(got[0], want[0]), (k, np.argwhere(got[0] != want[0])[:5])
        assert np.array_equal(got[1].view(np.uint32), want[1].view(np.uint32)), k
