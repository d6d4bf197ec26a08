"""A pose correction moves the hypothesis TSDF rigidly, voxel by voxel, with each voxel's frame."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.fusion.corrections.poses import PoseBook
from services.fusion.volume.tsdf import HypothesisTSDF
from shared.config.fusion import TSDFConfig
from shared.geometry import Intrinsics
from shared.messages.poses import PoseCorrection

K = Intrinsics(fx=200, fy=200, cx=79.5, cy=59.5, width=160, height=120)
DEPTH = np.full((120, 160), 2.0, np.float32)  # a wall 2 m ahead
RGB = np.full((120, 160, 3), 128, np.uint8)
IDS = np.zeros((120, 160), np.int32)
IDS[:, 80:] = 1


def _delta(deg: float, t: tuple[float, float, float]) -> np.ndarray:
    a = math.radians(deg)
    D = np.eye(4)
    D[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    D[:3, 3] = t
    return D


def _mapped(frames: int = 6, **cfg) -> tuple[HypothesisTSDF, PoseBook]:
    tsdf = HypothesisTSDF(TSDFConfig(vote_backend="numba", **cfg), device="cpu")
    book = PoseBook()
    tsdf.epoch_motion = book.epoch_motion
    for f in range(frames):
        T = np.eye(4)
        T[0, 3] = 0.02 * f
        tsdf.integrate(DEPTH, RGB, K, book.add(f, T), IDS, {0: 1.0, 1: 1.0}, frame_index=f)
    return tsdf, book


def _correct(book: PoseBook, D: np.ndarray, frames: list[int], cid: int = 1) -> PoseCorrection:
    poses = np.stack([D @ book.raw[book.frames.index(f)] for f in frames])
    return PoseCorrection(correction_id=cid, frame_index=frames[-1], frames=np.asarray(frames, np.int64), poses=poses)


def _state(tsdf: HypothesisTSDF) -> dict[str, np.ndarray]:
    return {k: np.asarray(v).copy() for k, v in tsdf.state_dict().items()}


def test_mesh_vertices_carry_the_mean_frame_they_were_fused_from():
    tsdf, _ = _mapped(3)  # the wall seen by frames 0, 1 and 2
    mesh = tsdf.extract_mesh()
    assert len(mesh) > 500 and set(np.unique(mesh.anchors).tolist()) == {1}
    tsdf, _ = _mapped(6)  # the camera slides: the wall's middle is seen by all six, its edges by fewer
    vals, counts = np.unique(tsdf.extract_mesh().anchors, return_counts=True)
    assert vals[counts.argmax()] in (2, 3) and set(vals.tolist()) <= set(range(6))


@pytest.mark.parametrize("deg", [0.0, 5.0])
def test_a_correction_moves_the_surface_rigidly_within_rounding_to_the_grid(deg):
    tsdf, book = _mapped()
    before = tsdf.extract_mesh()
    D = _delta(deg, (0.1, 0.0, 0.05))
    stats = tsdf.move(book.correct(_correct(book, D, list(range(6)))), book.epoch)
    after = tsdf.extract_mesh()
    want = before.vertices.astype(np.float64) @ D[:3, :3].T + D[:3, 3]
    got_to_want, _ = cKDTree(want).query(after.vertices)
    want_to_got, _ = cKDTree(after.vertices).query(want)
    # each voxel lands on the voxel nearest to its moved centre: at most half a voxel off along
    # the surface normal (a turned wall crosses the grid, so a little more for a few vertices)
    assert np.mean(got_to_want) < 0.35 * tsdf.cfg.voxel_size
    assert max(got_to_want.max(), want_to_got.max()) <= 0.6 * tsdf.cfg.voxel_size
    assert stats.voxels_moved > 10_000
    # a turn leaves rounding gaps between filled voxels, which are filled; a shift leaves none
    assert (stats.gaps_filled > 0) == (deg != 0.0)
    # the hypotheses moved with their voxels: the right half of the wall is still track 1
    win = after.winners()
    right = after.vertices[:, 0] > np.median(after.vertices[:, 0]) + 0.2
    assert np.mean(win[right] == 1) > 0.95


def test_the_same_correction_again_leaves_the_grid_bit_for_bit():
    tsdf, book = _mapped()
    c = _correct(book, _delta(3.0, (0.05, 0.02, 0.0)), list(range(6)))
    tsdf.move(book.correct(c), book.epoch)
    once = _state(tsdf)
    tsdf.move(book.correct(c), book.epoch)  # the same message: nothing to move
    tsdf.move(book.correct(c.model_copy(update={"correction_id": 2})), book.epoch)  # the same poses again
    twice = _state(tsdf)
    assert once.keys() == twice.keys()
    for k in once:
        if k != "epoch":
            assert np.array_equal(once[k], twice[k]), k


def test_only_the_corrected_frames_content_moves():
    tsdf, book = _mapped(4)
    # a second wall seen from frames 4, 5 only, 1 m further
    for f in (4, 5):
        T = np.eye(4)
        T[0, 3] = 3.0
        tsdf.integrate(DEPTH + 1.0, RGB, K, book.add(f, T), IDS, {0: 1.0, 1: 1.0}, frame_index=f)
    before = tsdf.extract_mesh()
    # frames 4 and 5 move 0.3 m up; 0..3 stay (listed with their own poses)
    frames = list(range(6))
    poses = np.stack([book.raw[k] if k < 4 else _delta(0, (0, -0.3, 0)) @ book.raw[k] for k in range(6)])
    c = PoseCorrection(correction_id=1, frame_index=5, frames=np.asarray(frames), poses=poses)
    tsdf.move(book.correct(c), book.epoch)
    after = tsdf.extract_mesh()
    old_near = before.vertices[before.anchors < 4]
    new_near = after.vertices[after.anchors < 4]
    assert np.array_equal(np.sort(old_near, axis=0), np.sort(new_near, axis=0))
    far_before = before.vertices[before.anchors >= 4]
    far_after = after.vertices[after.anchors >= 4]
    assert far_after[:, 1].mean() == pytest.approx(far_before[:, 1].mean() - 0.3, abs=0.02)


def test_archived_blocks_move_when_they_are_read():
    tsdf, book = _mapped(4, active_window_m=3.0)
    far = np.array([50.0, 0.0, 0.0])
    tsdf.update_window(far)  # everything leaves the window
    assert tsdf.active_blocks == 0 and tsdf.archived_blocks > 0
    before = tsdf.extract_archived_mesh()
    D = _delta(0.0, (0.0, 0.0, 0.4))
    tsdf.move(book.correct(_correct(book, D, list(range(4)))), book.epoch)
    after = tsdf.extract_archived_mesh()
    assert len(after) == len(before)
    np.testing.assert_allclose(np.sort(after.vertices[:, 2]), np.sort(before.vertices[:, 2] + 0.4), atol=0.016)
    # kept, as placed, through a save and a load; read again it is where the estimates put it
    again = HypothesisTSDF(TSDFConfig(active_window_m=3.0, vote_backend="numba"), device="cpu")
    again.load_state_dict(tsdf.state_dict())
    again.epoch_motion = book.epoch_motion
    np.testing.assert_allclose(again.extract_archived_mesh().vertices, after.vertices)


def test_with_restore_the_archive_moves_at_once():
    tsdf, book = _mapped(4, active_window_m=3.0, restore_archived=True)
    tsdf.update_window(np.array([50.0, 0.0, 0.0]))
    keys_before = tsdf.archive.keys().copy()
    stats = tsdf.move(book.correct(_correct(book, _delta(0.0, (0.0, 0.0, 0.48)), list(range(4)))), book.epoch)
    assert stats.archived_moved == len(keys_before)
    # 0.48 m is exactly two blocks of 8 x 3 cm along z: the blocks with distances shift by two
    # (votes follow the surface, and may sit in a neighbour block of their own)
    keys, attrs = tsdf.archive.peek(tsdf.archive.lookup(tsdf.archive.keys()))
    geometric = (attrs["weight"].reshape(len(keys), -1) > 0).any(axis=1)
    assert {tuple(k) for k in keys[geometric]} == {(k[0], k[1], k[2] + 2) for k in keys_before}
    assert len(tsdf.archive.rows_before(tsdf.epoch)) == 0


def test_numba_and_numpy_paths_agree():
    """The per-voxel kernels run in numba when it is installed; numpy does the same."""
    from services.fusion.volume import move, move_numba

    if move.numba is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(3)
    tsdf = rng.uniform(-1, 1, (5, 8, 8, 8)).astype(np.float32)
    filled = rng.random((5, 8, 8, 8)) > 0.3
    fast = move._gradient(tsdf, filled)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(move, "numba", None)
        slow = move._gradient(tsdf, filled)
    np.testing.assert_allclose(fast[filled], slow[filled], atol=1e-6)
    vox = rng.integers(-50, 50, (400, 3))
    row = rng.integers(-1, 2, 400)
    deltas = np.stack([_delta(4.0, (0.05, -0.02, 0.01)), _delta(-2.0, (0.0, 0.1, 0.0))])
    t = rng.uniform(-0.9, 0.9, 400)
    g = rng.normal(0, 0.25, (400, 3))
    off = rng.uniform(-0.5, 0.5, (400, 3))
    a = move_numba.move_voxels(vox, row, deltas, t, g, off, 0.03, move.MAX_VOTE_SHIFT)
    b = move._move_numpy(vox, row, deltas, t, g, off, 0.03)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y, atol=1e-9)


def test_the_one_pass_kernel_moves_as_the_step_by_step_path():
    from services.fusion.volume import move

    if move.numba is None:
        pytest.skip("numba is not installed")
    tsdf, book = _mapped()
    bufs, keys = tsdf._active()
    attrs = tsdf._read_blocks(bufs)
    motion = book.correct(_correct(book, _delta(4.0, (0.07, -0.03, 0.02)), list(range(6))))
    k1, a1, c1 = move.move_blocks(keys, attrs, motion, tsdf.res, tsdf.cfg.voxel_size, tsdf._layout)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(move, "FUSED_LAYOUT", set())
        k2, a2, c2 = move.move_blocks(keys, attrs, motion, tsdf.res, tsdf.cfg.voxel_size, tsdf._layout)
    assert c1.voxels_moved == c2.voxels_moved > 0 and c1.gaps_filled == c2.gaps_filled
    o1, o2 = np.lexsort(k1.T[::-1]), np.lexsort(k2.T[::-1])
    assert np.array_equal(k1[o1], k2[o2])
    for name in a1:
        np.testing.assert_allclose(a1[name][o1], a2[name][o2], atol=1e-5, err_msg=name)


def test_gap_filling_in_numba_equals_numpy():
    from services.fusion.volume import move

    if move.numba is None:
        pytest.skip("numba is not installed")
    tsdf, _ = _mapped()
    bufs, _ = tsdf._active()
    out = tsdf._read_blocks(bufs)
    holes = np.random.default_rng(5).random(out["weight"].shape[:4]) < 0.05  # a turned grid's rounding gaps
    out["weight"][holes] = 0
    out["hyp_w"][holes] = 0
    a = {k: v.copy() for k, v in out.items()}
    b = {k: v.copy() for k, v in out.items()}
    fast = move._fill_gaps(a, tsdf.res)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(move, "numba", None)
        slow = move._fill_gaps(b, tsdf.res)
    assert fast == slow > 0
    for name in a:
        np.testing.assert_allclose(a[name], b[name], atol=1e-6, err_msg=name)
