"""The incremental mesh (services/fusion/volume/incremental.py): which blocks an update copies
and redoes, and that the kept and redone pieces make the mesh that marching every block
gives, through edits of the blocks, a fused scene, the window, a pose correction and a reload."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.volume import cubes

if not cubes.available():
    pytest.skip("numba is not installed (fusion extra)", allow_module_level=True)

from services.fusion.corrections.poses import PoseBook  # noqa: E402
from services.fusion.types import HypothesisMesh  # noqa: E402
from services.fusion.volume.cubes import BlockCopy, hypothesis_mesh  # noqa: E402
from services.fusion.volume.incremental import BlockUpdate, MeshCache, changed_rows  # noqa: E402
from services.fusion.volume.mesh import canonical_order  # noqa: E402
from services.fusion.volume.tsdf import HypothesisTSDF  # noqa: E402
from services.fusion.volume.window import pack_keys  # noqa: E402
from shared.config.fusion import TSDFConfig  # noqa: E402
from shared.messages.poses import PoseCorrection  # noqa: E402
from tests.services.fusion.volume.test_cubes import _sphere_blocks  # noqa: E402
from tests.services.fusion.volume.test_tsdf_scene import GAMMA, K, look_at, render  # noqa: E402


def assert_same(a: HypothesisMesh, b: HypothesisMesh) -> None:
    assert len(a) == len(b)
    for name in ("vertices", "colors", "faces", "hyp_ids", "hyp_weights", "anchors"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _cube(n: int) -> np.ndarray:
    return np.array([[x, y, z] for x in range(n) for y in range(n) for z in range(n)], np.int64)


def test_a_written_block_redoes_itself_and_the_blocks_below_and_copies_those_above():
    keys = _cube(3)
    active = pack_keys(keys)
    rows, redo = changed_rows(active, pack_keys(np.array([[1, 1, 1]])))
    redone = {tuple(k) for k in keys[rows[redo]].tolist()}
    assert redone == {tuple(k) for k in _cube(2).tolist()}  # (1,1,1) minus each of {0,1}^3
    assert len(rows) == 27  # and every block above one of those, to read
    # a dropped block (no longer active) redoes the active blocks whose cubes read it
    rows, redo = changed_rows(active, pack_keys(np.array([[3, 3, 3], [3, 0, 0]])))
    assert {tuple(k) for k in keys[rows[redo]].tolist()} == {(2, 2, 2), (2, 0, 0)}
    assert changed_rows(active, np.zeros(0, np.int64))[0].size == 0


def _subset(blocks: BlockCopy, rows: np.ndarray) -> BlockCopy:
    return BlockCopy(**{name: np.ascontiguousarray(getattr(blocks, name)[rows]) for name in blocks.__dataclass_fields__})


class _Grid:
    """Blocks held as a BlockCopy, with the writes noted as the grid notes them."""

    def __init__(self, blocks: BlockCopy) -> None:
        self.blocks, self.touched, self.seq = blocks, None, 0

    def write(self, rows: np.ndarray, **fields: np.ndarray) -> None:
        for name, value in fields.items():
            getattr(self.blocks, name)[rows] = value
        self._note(self.blocks.keys[rows])

    def drop(self, rows: np.ndarray) -> None:
        self._note(self.blocks.keys[rows])
        self.blocks = _subset(self.blocks, np.setdiff1d(np.arange(len(self.blocks.keys)), rows))

    def _note(self, keys: np.ndarray) -> None:
        if self.touched is not None:
            self.touched = np.union1d(self.touched, pack_keys(keys))

    def capture(self) -> BlockUpdate:
        active = pack_keys(self.blocks.keys)
        if self.touched is None:
            rows, redo = np.arange(len(active)), np.ones(len(active), bool)
        else:
            rows, redo = changed_rows(active, self.touched)
        self.touched, self.seq = np.zeros(0, np.int64), self.seq + 1
        return BlockUpdate(blocks=_subset(self.blocks, rows), redo=redo, active=active, full=self.seq == 1, seq=self.seq)


def test_kept_and_redone_pieces_make_the_whole_mesh_through_edits():
    centre = np.array([0.05, 0.12, -0.07])
    grid = _Grid(_sphere_blocks(0.55, centre))
    cache = MeshCache(2)

    def check() -> int:
        update = grid.capture()
        assert_same(cache.apply(update, 0.1, 1.0), hypothesis_mesh(grid.blocks, 0.1, 2, 1.0))
        return int(update.redo.sum())

    n = len(grid.blocks.keys)
    assert check() == n  # the first: whole
    assert check() == 0  # nothing written: nothing redone, the same mesh
    keys = grid.blocks.keys
    # a bump on one side of the sphere: only the blocks there change
    side = np.flatnonzero(keys[:, 0] >= 1)
    moved = _sphere_blocks(0.55, centre + np.array([0.04, 0.0, 0.0]))
    grid.write(side, tsdf=moved.tsdf[side], hyp_w=grid.blocks.hyp_w[side] * 2)
    assert 0 < check() < n
    # votes and colour in one block; a block that falls below the weight threshold
    grid.write(np.array([5]), hyp_id=grid.blocks.hyp_id[[5]] + 1, color=grid.blocks.color[[5]] * 0.5)
    grid.write(np.array([n // 2]), weight=np.zeros_like(grid.blocks.weight[[n // 2]]))
    assert 0 < check() < 20
    # blocks leave (archived or erased), then one comes back
    gone = np.flatnonzero((keys[:, 1] == 0) & (keys[:, 2] == 0))
    back = _subset(grid.blocks, gone[:1])
    grid.drop(gone)
    assert 0 < check() < n
    grid.blocks = BlockCopy(**{name: np.concatenate([getattr(grid.blocks, name), getattr(back, name)]) for name in back.__dataclass_fields__})
    grid._note(back.keys)
    assert 0 < check() <= 8


def test_an_update_out_of_turn_is_refused_and_a_missed_one_makes_the_next_capture_whole():
    grid = _Grid(_sphere_blocks(0.3, np.zeros(3)))
    cache = MeshCache(2)
    cache.apply(grid.capture(), 0.1, 1.0)
    grid.capture()  # captured, never applied (a failed update)
    with pytest.raises(RuntimeError, match="does not follow"):
        cache.apply(grid.capture(), 0.1, 1.0)

    tsdf = HypothesisTSDF(TSDFConfig(vote_backend="numba"), device="cpu")
    T = look_at(np.array([0.0, -0.3, 0.0]), (0.0, 0.2, 2.5))
    depth, rgb, ids = render(T)
    tsdf.integrate(depth, rgb, K, T, ids, GAMMA)
    assert tsdf.copy_changed().full  # the first
    tsdf.integrate(depth, rgb, K, T, ids, GAMMA)
    assert len(tsdf.mesh_of_update(tsdf.copy_changed())) > 0
    tsdf.integrate(depth, rgb, K, T, ids, GAMMA)
    assert not tsdf.copy_changed().full  # the one before was applied
    assert tsdf.copy_changed().full  # the one before was not


def test_on_a_fused_scene_it_follows_the_window_a_correction_and_a_reload():
    cfg = TSDFConfig(vote_backend="numba", voxel_size=0.04, active_window_m=4.0)
    tsdf = HypothesisTSDF(cfg, device="cpu")
    book = PoseBook()
    tsdf.epoch_motion = book.epoch_motion
    redone = []

    def check() -> None:
        update = tsdf.copy_changed()
        redone.append(update.redo.sum() / max(len(update.active), 1))
        assert_same(tsdf.mesh_of_update(update), tsdf.mesh_of(tsdf.copy_active()))

    # a walk along the wall: the window drops blocks behind and brings them back on the way back
    xs = list(np.linspace(-3.0, 3.0, 13)) + list(np.linspace(2.5, -3.0, 12))
    for f, x in enumerate(xs):
        T = look_at(np.array([x, -0.3, 0.0]), (x, 0.2, 2.5))
        depth, rgb, ids = render(T)
        tsdf.integrate(depth, rgb, K, book.add(f, T), ids, GAMMA, frame_index=f)
        tsdf.update_window(T[:3, 3])
        if f % 2 == 1:
            check()
    assert tsdf.archived_blocks > 0 and min(redone[1:]) < 0.9  # pieces were kept
    # a loop closure moves the last frames' voxels
    D = np.eye(4)
    D[:3, 3] = (0.08, 0.0, 0.04)
    last = list(range(len(xs) - 5, len(xs)))
    fix = PoseCorrection(correction_id=1, frame_index=last[-1], frames=np.asarray(last, np.int64),
                         poses=np.stack([D @ book.raw[book.frames.index(f)] for f in last]))  # fmt: skip
    assert tsdf.move(book.correct(fix), book.epoch).voxels_moved > 0
    check()
    # a reload replaces the grid: the next update is whole, and right
    state = {k: np.asarray(v).copy() for k, v in tsdf.state_dict().items()}
    tsdf.load_state_dict(state)
    update = tsdf.copy_changed()
    assert update.full
    assert_same(tsdf.mesh_of_update(update), tsdf.mesh_of(tsdf.copy_active()))


def test_vertices_at_one_position_are_ordered_by_the_tiebreak():
    # three edges meeting at a voxel where the TSDF is exactly zero give three vertices there
    v = np.array([[0, 0, 0], [1, 1, 1], [0, 0, 0], [0, 0, 0]], np.float32)
    faces = np.array([[0, 1, 2], [2, 1, 3]])
    perm_a, faces_a = canonical_order(v, faces, tiebreak=(np.array([5, 0, 3, 4]),))
    assert perm_a.tolist() == [2, 3, 0, 1]
    perm_b, faces_b = canonical_order(v[[3, 1, 0, 2]], np.array([[2, 1, 3], [3, 1, 0]]), tiebreak=(np.array([4, 0, 5, 3]),))
    # the same vertices in another input order come out in the same order, with the same faces
    assert [3, 1, 0, 2][perm_b[0]] == 2 and np.array_equal(faces_a, faces_b)
