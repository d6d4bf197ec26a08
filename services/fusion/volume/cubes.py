"""Marching cubes over copied voxel blocks, in numba without the GIL (the map path's mesh).

Open3D's ``extract_triangle_mesh`` holds the GIL for its whole run (90 ms at Replica's
1200x680 and 3 cm, 3,000 active blocks), so a map thread calling it stops the frame path as
surely as calling it there. Here the frame path only copies the active blocks' arrays
(:class:`BlockCopy`, about 15 ms for 3,000 blocks into reused buffers) and the map thread
meshes the copy with these kernels, which release the GIL.

The mesh has Open3D's vertices: one per grid edge with a TSDF sign change between two voxels
of weight at least the threshold, in a cube all of whose eight voxels have that weight, at
the linear zero crossing, with the colour interpolated the same way. Its triangles are
those of this module's own case table (:func:`case_table`), generated from the cube's
geometry: each face's sign changes are joined so that inside corners stay apart (so two
cubes sharing a face agree and the surface is closed), the joins are chained into polygons,
and each polygon is fanned. Open3D's table may pick other diagonals; segments and
everything after them read vertices only.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from services.fusion.types import HypothesisMesh
from services.fusion.volume.mesh import canonical_order, merge_hypotheses

try:
    import numba
except ImportError:  # pragma: no cover - numba is in the fusion extra
    numba = None

CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.int64)
"""Cube corner k at this (x, y, z) offset from the cube's first voxel."""
EDGES = np.array([[0, 1], [1, 2], [3, 2], [0, 3], [4, 5], [5, 6], [7, 6], [4, 7], [0, 4], [1, 5], [2, 6], [3, 7]], np.int64)
"""Cube edge e joins these corners, the first one at the lower coordinate."""


def _edge_of(a: int, b: int) -> int:
    for e, (p, q) in enumerate(EDGES.tolist()):
        if {p, q} == {a, b}:
            return e
    raise KeyError((a, b))


def _faces_ccw() -> list[list[int]]:
    """Each cube face's four corners, counter-clockwise seen from outside the cube."""
    faces = []
    for axis in range(3):
        for side in (0, 1):
            ks = [k for k in range(8) if CORNERS[k, axis] == side]
            normal = np.zeros(3)
            normal[axis] = 1.0 if side else -1.0
            u = np.zeros(3)
            u[(axis + 1) % 3] = 1.0
            v = np.cross(normal, u)
            centre = CORNERS[ks].mean(axis=0)
            ang = [np.arctan2((CORNERS[k] - centre) @ v, (CORNERS[k] - centre) @ u) for k in ks]
            faces.append([ks[i] for i in np.argsort(ang)])
    return faces


@functools.lru_cache(maxsize=1)
def case_table() -> tuple[Annotated[np.ndarray, "(256, 16) int8 edge ids, -1 = end"], Annotated[np.ndarray, "(256,) int16 edge bits"]]:
    """Triangles (three cube edges each) and the edges with a vertex, per case: bit k of the
    case is set when corner k is inside (TSDF below 0).

    Walking a face counter-clockwise from outside, every sign change from outside to inside
    is joined to the next change from inside to outside; the join runs in that direction.
    Every edge lies on two faces and is walked in opposite directions on them, so it starts
    one join and ends another, and the joins chain into closed polygons."""
    faces = _faces_ccw()
    tris = np.full((256, 16), -1, np.int8)
    bits = np.zeros(256, np.int16)
    for case in range(256):
        inside = [(case >> k) & 1 == 1 for k in range(8)]
        nxt: dict[int, int] = {}
        for face in faces:
            walk = []
            for i in range(4):
                a, b = face[i], face[(i + 1) % 4]
                if inside[a] != inside[b]:
                    walk.append((_edge_of(a, b), inside[b]))  # True: outside -> inside
            for i, (e, entering) in enumerate(walk):
                if entering:
                    for j in range(1, len(walk)):
                        f, f_entering = walk[(i + j) % len(walk)]
                        if not f_entering:
                            nxt[e] = f
                            break
        row: list[int] = []
        seen: set[int] = set()
        for start in sorted(nxt):
            if start in seen:
                continue
            poly = [start]
            seen.add(start)
            e = nxt[start]
            while e != start:
                poly.append(e)
                seen.add(e)
                e = nxt[e]
            for i in range(1, len(poly) - 1):
                row += [poly[0], poly[i], poly[i + 1]]  # wound so the normal points out of the surface (to TSDF > 0)
        tris[case, : len(row)] = row
        for e in seen:
            bits[case] |= 1 << e
    return tris, bits


@dataclass
class BlockCopy:
    """The active blocks' arrays, copied off the grid (the frame path's part of a mesh)."""

    keys: Annotated[np.ndarray, "(B, 3) int32 block coordinates"]
    tsdf: Annotated[np.ndarray, "(B, r, r, r) float32, [z, y, x]"]
    weight: Annotated[np.ndarray, "(B, r, r, r) float32"]
    color: Annotated[np.ndarray, "(B, r, r, r, 3) float32, 0-255"]
    hyp_id: Annotated[np.ndarray, "(B, r, r, r, K) int32, track + 1"]
    hyp_w: Annotated[np.ndarray, "(B, r, r, r, K) float32"]
    anchor: Annotated[np.ndarray, "(B, r, r, r) int32"]


if numba is not None:
    # Cube corner k's offset, each edge's first corner and axis (CORNERS and EDGES as literals).
    _CX = (0, 1, 1, 0, 0, 1, 1, 0)
    _CY = (0, 0, 1, 1, 0, 0, 1, 1)
    _CZ = (0, 0, 0, 0, 1, 1, 1, 1)
    _FIRST = (0, 1, 3, 0, 4, 5, 7, 4, 0, 1, 2, 3)
    _AXIS = (0, 1, 0, 1, 0, 1, 0, 1, 2, 2, 2, 2)

    @numba.njit(cache=True, nogil=True)
    def _block_lut(keys):  # pragma: no cover - compiled
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for a in range(3):
            lo[a] = keys[0, a] - 1
            hi[a] = keys[0, a] + 1
        for b in range(keys.shape[0]):
            for a in range(3):
                lo[a] = min(lo[a], keys[b, a] - 1)
                hi[a] = max(hi[a], keys[b, a] + 1)
        ext = hi - lo + 1
        lut = np.full((ext[0], ext[1], ext[2]), -1, np.int64)
        for b in range(keys.shape[0]):
            lut[keys[b, 0] - lo[0], keys[b, 1] - lo[1], keys[b, 2] - lo[2]] = b
        return lut, lo

    @numba.njit(cache=True, nogil=True, inline="always")
    def _at(lut, lo, keys, b, x, y, z, res):  # pragma: no cover - compiled
        """(block, x, y, z) of voxel (x, y, z) of block b, which may lie in a neighbour
        (each coordinate at most res); block -1 when that neighbour is not there."""
        if x < res and y < res and z < res:
            return b, x, y, z
        bx, by, bz = keys[b, 0], keys[b, 1], keys[b, 2]
        if x >= res:
            bx += 1
            x -= res
        if y >= res:
            by += 1
            y -= res
        if z >= res:
            bz += 1
            z -= res
        return lut[bx - lo[0], by - lo[1], bz - lo[2]], x, y, z

    @numba.njit(cache=True, nogil=True)
    def _cases(keys, tsdf, weight, thr, res, lut, lo, scan, cubes, cases):  # pragma: no cover - compiled
        """The cubes with a surface whose first voxel lies in a block with ``scan`` set: their
        first voxels (flat, into ``cubes``, in block order) and cases; the count. A cube counts
        when all its eight voxels have weight above ``thr``."""
        n = 0
        edge = res - 1
        for b in range(keys.shape[0]):
            if not scan[b]:
                continue
            for z in range(res):
                for y in range(res):
                    for x in range(res):
                        if weight[b, z, y, x] <= thr:
                            continue
                        case = 0
                        ok = True
                        if x < edge and y < edge and z < edge:  # all eight in this block
                            for k in range(8):
                                wz, wy, wx = z + _CZ[k], y + _CY[k], x + _CX[k]
                                if weight[b, wz, wy, wx] <= thr:
                                    ok = False
                                    break
                                if tsdf[b, wz, wy, wx] < 0:
                                    case |= 1 << k
                        else:
                            for k in range(8):
                                nb, nx, ny, nz = _at(lut, lo, keys, b, x + _CX[k], y + _CY[k], z + _CZ[k], res)
                                if nb < 0 or weight[nb, nz, ny, nx] <= thr:
                                    ok = False
                                    break
                                if tsdf[nb, nz, ny, nx] < 0:
                                    case |= 1 << k
                        if not ok or case == 0 or case == 255:
                            continue
                        cubes[n] = ((b * res + z) * res + y) * res + x
                        cases[n] = case
                        n += 1
        return n

    @numba.njit(cache=True, nogil=True)
    def _edges_and_faces(keys, res, lut, lo, tris, bits, cubes, cases, index, per_piece):  # pragma: no cover - compiled
        """In cube order: a vertex number for every edge with a surface crossing, its first
        voxel and axis (``owners``: block, z, y, x, axis) and block (``vpiece``), then the
        cube's triangles (``faces``) and block (``fpiece``). With ``per_piece`` each block's
        cubes (which come together) number their vertices apart, so a block's piece of the
        mesh holds its own copy of an edge it shares (:mod:`services.fusion.volume.incremental`);
        without, an edge has one vertex."""
        owners = np.empty((12 * len(cubes), 5), np.int64)
        vpiece = np.empty(12 * len(cubes), np.int64)
        faces = np.empty((5 * len(cubes), 3), np.int64)
        fpiece = np.empty(5 * len(cubes), np.int64)
        n = 0
        f = 0
        r3, r2 = res * res * res, res * res
        for i in range(len(cubes)):
            c = cubes[i]
            b, z, y, x = c // r3, (c // r2) % res, (c // res) % res, c % res
            eb = bits[cases[i]]
            for e in range(12):
                if (eb >> e) & 1:
                    q = _FIRST[e]
                    nb, nx, ny, nz = _at(lut, lo, keys, b, x + _CX[q], y + _CY[q], z + _CZ[q], res)
                    a = _AXIS[e]
                    v = index[nb, nz, ny, nx, a]
                    if v < 0 or (per_piece and vpiece[v] != b):
                        index[nb, nz, ny, nx, a] = n
                        owners[n, 0], owners[n, 1], owners[n, 2], owners[n, 3], owners[n, 4] = nb, nz, ny, nx, a
                        vpiece[n] = b
                        n += 1
            for j in range(0, 16, 3):  # every edge of this cube is numbered by now
                if tris[cases[i], j] < 0:
                    break
                for m in range(3):
                    e = tris[cases[i], j + m]
                    q = _FIRST[e]
                    nb, nx, ny, nz = _at(lut, lo, keys, b, x + _CX[q], y + _CY[q], z + _CZ[q], res)
                    faces[f, m] = index[nb, nz, ny, nx, _AXIS[e]]
                fpiece[f] = b
                f += 1
        return owners[:n], vpiece[:n], faces[:f], fpiece[:f]

    @numba.njit(cache=True, nogil=True)
    def _vertices(keys, tsdf, color, hyp_id, hyp_w, anchor, res, voxel, lut, lo, owners):  # pragma: no cover - compiled
        """Each numbered edge's vertex: position, colour, both ends' hypotheses scaled by their
        interpolation shares, the nearer end's anchor."""
        n = len(owners)
        k = hyp_id.shape[4]
        pos = np.empty((n, 3), np.float32)
        col = np.empty((n, 3), np.uint8)
        ids_a = np.empty((n, k), np.int32)
        ids_b = np.empty((n, k), np.int32)
        w_a = np.empty((n, k), np.float64)
        w_b = np.empty((n, k), np.float64)
        anc = np.empty(n, np.int32)
        for v in range(n):
            b, z, y, x, a = owners[v, 0], owners[v, 1], owners[v, 2], owners[v, 3], owners[v, 4]
            nb, nx, ny, nz = _at(lut, lo, keys, b, x + (1 if a == 0 else 0), y + (1 if a == 1 else 0), z + (1 if a == 2 else 0), res)
            f0 = tsdf[b, z, y, x]
            f1 = tsdf[nb, nz, ny, nx]
            # float32 throughout, in Open3D's order of operations: its vertices and colours to the bit
            r32 = (np.float32(0.0) - f0) / (f1 - f0)
            t = np.float64(r32)
            for c in range(3):
                g = np.float32(keys[b, c] * res + (x if c == 0 else y if c == 1 else z))
                if c == a:
                    g = g + r32
                pos[v, c] = g * voxel
                # Open3D's vertex colour is this over 255; the mesh keeps it back in 0-255
                cv = np.float32(np.float32((color[b, z, y, x, c] * (np.float32(1.0) - r32) + color[nb, nz, ny, nx, c] * r32) / np.float32(255.0)) * np.float32(255.0))
                col[v, c] = np.uint8(min(max(np.rint(cv), np.float32(0.0)), np.float32(255.0)))
            for s in range(k):
                ids_a[v, s] = hyp_id[b, z, y, x, s] - 1
                w_a[v, s] = np.float64(hyp_w[b, z, y, x, s]) * (1.0 - t)
                ids_b[v, s] = hyp_id[nb, nz, ny, nx, s] - 1
                w_b[v, s] = np.float64(hyp_w[nb, nz, ny, nx, s]) * t
            anc[v] = anchor[b, z, y, x] if 1.0 - t >= t else anchor[nb, nz, ny, nx]
        return pos, col, ids_a, w_a, ids_b, w_b, anc


def available() -> bool:
    """The kernels need numba."""
    return numba is not None


def march(
    blocks: BlockCopy, voxel_size: float, weight_threshold: float
) -> tuple[
    Annotated[np.ndarray, "(V, 3) float32 m"], Annotated[np.ndarray, "(V, 3) uint8"], Annotated[np.ndarray, "(F, 3) int64"],
    tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], Annotated[np.ndarray, "(V,) int32"],
]:  # fmt: skip
    """Vertices, colours, faces, each vertex's two ends' hypotheses (ids of the lower end,
    their weights times its share, the same of the upper end) and its nearer end's anchor."""
    n, res = len(blocks.keys), blocks.tsdf.shape[1]
    k = blocks.hyp_id.shape[-1]
    if n == 0:
        e2 = np.zeros((0, k), np.int32), np.zeros((0, k)), np.zeros((0, k), np.int32), np.zeros((0, k))
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.int64), e2, np.zeros(0, np.int32)
    tris, bits = case_table()
    keys = np.ascontiguousarray(blocks.keys, np.int64)
    lut, lo = _block_lut(keys)
    cubes = np.empty(n * res**3, np.int64)
    cases = np.empty(n * res**3, np.uint8)
    scan = np.ones(n, np.bool_)
    m = _cases(keys, blocks.tsdf, blocks.weight, np.float32(weight_threshold), res, lut, lo, scan, cubes, cases)
    cubes, cases = cubes[:m], cases[:m]
    index = np.full((n, res, res, res, 3), -1, np.int32)
    owners, _, faces, _ = _edges_and_faces(keys, res, lut, lo, tris, bits, cubes, cases, index, False)
    pos, col, ids_a, w_a, ids_b, w_b, anc = _vertices(keys, blocks.tsdf, blocks.color, blocks.hyp_id, blocks.hyp_w, blocks.anchor,
                                                      res, np.float32(voxel_size), lut, lo, owners)  # fmt: skip
    return pos, col, faces, (ids_a, w_a, ids_b, w_b), anc


def block_copy(keys: Annotated[np.ndarray, "(B, 3) int32"], attrs: dict[str, np.ndarray]) -> BlockCopy:
    """A :class:`BlockCopy` of blocks read off a grid or the archive (attribute arrays of
    shape (B, r, r, r, C), as ``BlockGrid._read_blocks`` and ``BlockArchive.peek`` give them)."""
    def one(a: np.ndarray) -> np.ndarray:  # (B, r, r, r, 1) -> (B, r, r, r): a view when contiguous
        return np.ascontiguousarray(np.asarray(a).reshape(a.shape[:-1]))

    return BlockCopy(
        keys=np.ascontiguousarray(keys, np.int32), tsdf=one(attrs["tsdf"]), weight=one(attrs["weight"]),
        color=np.ascontiguousarray(attrs["color"]), hyp_id=np.ascontiguousarray(attrs["hyp_id"]),
        hyp_w=np.ascontiguousarray(attrs["hyp_w"]), anchor=one(attrs["anchor"]),
    )  # fmt: skip


def hypothesis_mesh(blocks: BlockCopy, voxel_size: float, k: int, weight_threshold: float) -> HypothesisMesh:
    """Marching cubes over ``blocks`` with vertex colours and hypotheses, in the order
    :func:`~services.fusion.volume.mesh.extract_hypothesis_mesh` gives (vertices by position):
    its vertices, colours, hypotheses and anchors, from kernels that release the GIL."""
    pos, col, faces, (ids_a, w_a, ids_b, w_b), anc = march(blocks, voxel_size, weight_threshold)
    if len(pos) == 0:
        return HypothesisMesh.empty(k)
    perm, faces = canonical_order(pos, faces)
    hyp_ids, hyp_weights = merge_hypotheses(ids_a[perm], w_a[perm], ids_b[perm], w_b[perm], k)
    return HypothesisMesh(
        vertices=np.ascontiguousarray(pos[perm]), colors=np.ascontiguousarray(col[perm]), faces=faces,
        hyp_ids=hyp_ids, hyp_weights=hyp_weights, anchors=anc[perm],
    )  # fmt: skip


_WARM = False


def warm_up() -> None:
    """Load (or compile) the kernels once per process, on two small blocks with a surface
    between them: the first graph update would otherwise pay for it on the map thread."""
    global _WARM
    if _WARM or numba is None:
        return
    res, k = 2, 2
    tsdf = np.full((2, res, res, res), 0.5, np.float32)
    tsdf[0] = -0.5
    shape = tsdf.shape
    blocks = BlockCopy(keys=np.array([[0, 0, 0], [1, 0, 0]], np.int32), tsdf=tsdf, weight=np.full(shape, 2.0, np.float32),
                       color=np.zeros((*shape, 3), np.float32), hyp_id=np.ones((*shape, k), np.int32),
                       hyp_w=np.ones((*shape, k), np.float32), anchor=np.zeros(shape, np.int32))  # fmt: skip
    hypothesis_mesh(blocks, 0.1, k, 1.0)
    _WARM = True
