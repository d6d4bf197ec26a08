"""The mesh again at each graph update, marching only the blocks that changed since the last one.

A block's *piece* of the mesh is the triangles of the cubes whose first voxel lies in it, with
a copy of every vertex they use. A cube reads its own block and the seven blocks above it
(+x, +y, +z and their combinations), so a piece changes only when one of those eight blocks
was written (fused, voted, restored, moved, archived out or dropped). The grid notes the
blocks it writes (:meth:`~services.fusion.volume.grid.BlockGrid.touched`); at an update the
frame path copies the pieces to redo and the blocks above them (:class:`BlockUpdate`, 40-50%
of the active window at Replica's 1200x680 on the demo walk), and the map path marches those
pieces and keeps the rest (:class:`MeshCache`).

Pieces that meet share the vertices on their common edges, each as its own copy (the same
numbers: a vertex reads only its edge's two voxels). The copies are joined by edge (owner
block, voxel, axis) and the mesh is put in the canonical order, so it is the mesh that
marching every block gives (:func:`services.fusion.volume.cubes.hypothesis_mesh`), vertex for
vertex and face for face (``tests/services/fusion/volume/test_incremental.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from services.fusion.types import HypothesisMesh
from services.fusion.volume import cubes
from services.fusion.volume.cubes import BlockCopy
from services.fusion.volume.mesh import canonical_order, merge_hypotheses
from services.fusion.volume.window import pack_keys

numba = cubes.numba

_UP = np.array([(dx << 42) + (dy << 21) + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], np.int64)
"""A block and its seven upper neighbours as offsets of packed keys (``pack_keys``)."""


@dataclass
class BlockUpdate:
    """What the frame path copies for an incremental mesh (:meth:`HypothesisTSDF.copy_changed`)."""

    blocks: BlockCopy
    """The blocks whose pieces are redone and the active blocks above them."""
    redo: Annotated[np.ndarray, "(B,) bool"]
    """Which of ``blocks`` are pieces to mesh again."""
    active: Annotated[np.ndarray, "(N,) int64 packed keys"]
    """Every active block: pieces of blocks not among them are dropped."""
    full: bool
    """``blocks`` is the whole active window, all redone: the pieces kept so far are dropped."""
    seq: int
    """The capture's number; an incremental one applies only on top of the one before it."""


def changed_rows(
    active: Annotated[np.ndarray, "(N,) int64 packed keys"], touched: Annotated[np.ndarray, "(T,) int64 packed keys"]
) -> tuple[Annotated[np.ndarray, "(C,) int64 rows of active to copy"], Annotated[np.ndarray, "(C,) bool redo"]]:
    """The active blocks a mesh update must copy, given the blocks written since the last one:
    every active block with a written block among itself and its upper neighbours (its piece
    is redone), and the active blocks above those (its cubes read them)."""
    if len(touched) == 0 or len(active) == 0:
        return np.zeros(0, np.int64), np.zeros(0, bool)
    redo = np.isin(active, (touched[:, None] - _UP[None, :]).ravel())
    copy = redo | np.isin(active, (active[redo][:, None] + _UP[None, :]).ravel())
    rows = np.flatnonzero(copy)
    return rows, redo[rows]


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _join(a, b):  # pragma: no cover - compiled
        """Rows with equal (a, b) joined, in order of first appearance (open addressing):
        each distinct pair's first row, and each row's pair number."""
        n = len(a)
        size = 16
        while size < 2 * n:
            size <<= 1
        mask = np.uint64(size - 1)
        slot = np.full(size, -1, np.int64)
        first = np.empty(n, np.int64)
        inverse = np.empty(n, np.int64)
        u = 0
        for i in range(n):
            h = np.uint64(a[i]) * np.uint64(0x9E3779B97F4A7C15) ^ np.uint64(b[i])
            h ^= h >> np.uint64(31)
            h *= np.uint64(0xBF58476D1CE4E5B9)
            h ^= h >> np.uint64(29)
            j = h & mask
            while True:
                r = slot[j]
                if r < 0:
                    slot[j] = i
                    first[u] = i
                    inverse[i] = u
                    u += 1
                    break
                if a[r] == a[i] and b[r] == b[i]:
                    inverse[i] = inverse[r]
                    break
                j = (j + np.uint64(1)) & mask
        return first[:u], inverse


class MeshCache:
    """The pieces of the active window's mesh, kept between graph updates (the map path's)."""

    def __init__(self, k: int) -> None:
        self.k = int(k)
        self.seq = 0
        """The last :class:`BlockUpdate` applied."""
        self._reset()

    def _reset(self) -> None:
        k = self.k
        self.pieces = np.zeros(0, np.int64)  # packed key of each block with a piece
        self.v_piece = np.zeros(0, np.int64)  # per vertex copy: index into pieces
        self.v_owner = np.zeros(0, np.int64)  # its edge: packed key of the first voxel's block,
        self.v_local = np.zeros(0, np.int64)  # and ((z * r + y) * r + x) * 3 + axis in it
        self.pos = np.zeros((0, 3), np.float32)
        self.col = np.zeros((0, 3), np.uint8)
        self.hyp_ids = np.zeros((0, k), np.int32)
        self.hyp_w = np.zeros((0, k), np.float32)
        self.anchor = np.zeros(0, np.int32)
        self.f_piece = np.zeros(0, np.int64)
        self.faces = np.zeros((0, 3), np.int64)  # rows of the vertex copies

    @property
    def vertex_copies(self) -> int:
        return len(self.pos)

    def apply(self, update: BlockUpdate, voxel_size: float, weight_threshold: float) -> HypothesisMesh:
        """Redo the update's pieces, drop those of blocks no longer active, and the mesh of all."""
        if update.full:
            self._reset()
        elif update.seq != self.seq + 1:
            raise RuntimeError(f"mesh update {update.seq} does not follow the last applied, {self.seq}")
        blocks, redo = update.blocks, np.asarray(update.redo, bool)
        packed = pack_keys(blocks.keys) if len(blocks.keys) else np.zeros(0, np.int64)
        keep = np.isin(self.pieces, update.active) & ~np.isin(self.pieces, packed[redo])
        self._keep(keep)
        if redo.any():
            self._add(blocks, redo, packed, voxel_size, weight_threshold)
        self.seq = update.seq
        return self.mesh()

    def _keep(self, keep: Annotated[np.ndarray, "(P,) bool"]) -> None:
        if keep.all():
            return
        kv, kf = keep[self.v_piece], keep[self.f_piece]
        row = np.cumsum(kv) - 1
        renum = np.cumsum(keep) - 1
        self.faces = row[self.faces[kf]]
        self.f_piece = renum[self.f_piece[kf]]
        self.v_piece = renum[self.v_piece[kv]]
        for name in ("v_owner", "v_local", "pos", "col", "hyp_ids", "hyp_w", "anchor"):
            setattr(self, name, getattr(self, name)[kv])
        self.pieces = self.pieces[keep]

    def _add(self, blocks: BlockCopy, redo: np.ndarray, packed: np.ndarray, voxel_size: float, weight_threshold: float) -> None:
        n, res = len(blocks.keys), blocks.tsdf.shape[1]
        tris, bits = cubes.case_table()
        keys = np.ascontiguousarray(blocks.keys, np.int64)
        lut, lo = cubes._block_lut(keys)
        scan = np.ascontiguousarray(redo)
        size = int(scan.sum()) * res**3
        cube_at, cases = np.empty(size, np.int64), np.empty(size, np.uint8)
        m = cubes._cases(keys, blocks.tsdf, blocks.weight, np.float32(weight_threshold), res, lut, lo, scan, cube_at, cases)
        index = np.full((n, res, res, res, 3), -1, np.int32)
        owners, vpiece, faces, fpiece = cubes._edges_and_faces(keys, res, lut, lo, tris, bits, cube_at[:m], cases[:m], index, True)
        pos, col, ids_a, w_a, ids_b, w_b, anc = cubes._vertices(keys, blocks.tsdf, blocks.color, blocks.hyp_id, blocks.hyp_w, blocks.anchor,
                                                                res, np.float32(voxel_size), lut, lo, owners)  # fmt: skip
        hyp_ids, hyp_w = merge_hypotheses(ids_a, w_a, ids_b, w_b, self.k)
        piece_of_row = np.full(n, -1, np.int64)
        piece_of_row[redo] = len(self.pieces) + np.arange(int(redo.sum()))
        base = len(self.pos)
        self.pieces = np.concatenate([self.pieces, packed[redo]])
        self.v_piece = np.concatenate([self.v_piece, piece_of_row[vpiece]])
        self.v_owner = np.concatenate([self.v_owner, packed[owners[:, 0]]])
        self.v_local = np.concatenate([self.v_local, ((owners[:, 1] * res + owners[:, 2]) * res + owners[:, 3]) * 3 + owners[:, 4]])
        self.pos = np.concatenate([self.pos, pos])
        self.col = np.concatenate([self.col, col])
        self.hyp_ids = np.concatenate([self.hyp_ids, hyp_ids])
        self.hyp_w = np.concatenate([self.hyp_w, hyp_w])
        self.anchor = np.concatenate([self.anchor, anc])
        self.f_piece = np.concatenate([self.f_piece, piece_of_row[fpiece]])
        self.faces = np.concatenate([self.faces, faces + base])

    def mesh(self) -> HypothesisMesh:
        """The pieces' vertex copies joined by edge, in canonical order."""
        if len(self.pos) == 0:
            return HypothesisMesh.empty(self.k)
        first, inverse = _join(self.v_owner, self.v_local)
        pos = self.pos[first]
        perm, faces = canonical_order(pos, inverse[self.faces], tiebreak=(self.v_owner[first], self.v_local[first]))
        rows = first[perm]
        return HypothesisMesh(
            vertices=np.ascontiguousarray(pos[perm]), colors=self.col[rows], faces=faces,
            hyp_ids=self.hyp_ids[rows], hyp_weights=self.hyp_w[rows], anchors=self.anchor[rows],
        )  # fmt: skip


def warm_up() -> None:
    """Load (or compile) the kernels once per process (the first graph update's otherwise)."""
    if numba is None:
        return
    _join(np.zeros(2, np.int64), np.arange(2, dtype=np.int64))
    tris, bits = cubes.case_table()
    keys = np.zeros((1, 3), np.int64)
    lut, lo = cubes._block_lut(keys)
    cubes._edges_and_faces(keys, 2, lut, lo, tris, bits, np.zeros(0, np.int64), np.zeros(0, np.uint8), np.full((1, 2, 2, 2, 3), -1, np.int32), True)
