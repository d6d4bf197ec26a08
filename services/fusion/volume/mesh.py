"""Marching cubes of the active grid with the per-voxel hypotheses moved onto the vertices (III-C).

Open3D's ``extract_triangle_mesh`` interpolates positions and colours but carries no custom
attribute, so the hypotheses are carried over here. A marching-cubes vertex lies on the grid
edge between two voxel centres, the two voxels whose signed distances put it there: its
supporting voxels. The vertex takes both voxels' hypotheses, each weight scaled by the same
linear interpolation factor Open3D applies to the colours along that edge, with one slot per
track (weights of a track present in both added) and the K strongest kept.

Deviation from the paper (docs/method.md, F4), whose vertex inherits the hypotheses of one
supporting voxel. Taking both ends, not only the nearer one, matters because the pixel vote lands in one voxel
per pixel, ``round(p / voxel_size)`` (:mod:`services.fusion.volume.hypotheses`): where only a few
frames voted (keyframes, when propagated pixels are too unsure to vote), the nearer end of an
edge is often a voxel no pixel landed in while the farther end holds the votes. On the
``small`` preset with noise-free keyframe masks, nearest-voxel transfer left 23% of the
vertices without any hypothesis (and so without a segment); both ends leave 7%.

Open3D's vertex order follows its hash-map buffer layout and thread scheduling, which a saved
and reloaded grid does not reproduce. Vertices are therefore sorted by position and faces by
their (rotated) indices, so equal grids give equal meshes, on any run and after a reload.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np

from services.fusion.types import HypothesisMesh

try:
    import numba
except ImportError:  # numpy does the same, slower
    numba = None


def voxel_flat_index(
    vbg: Any,
    points: Annotated[np.ndarray, "(N, 3) float world metres"],
    voxel_size: float,
    res: int,
) -> Annotated[np.ndarray, "(N,) int64 index into (capacity * res^3) attribute rows, -1 = none"]:
    """Flat attribute row of the voxel nearest to each point (hash-map lookup of its block)."""
    o3c = _o3c()
    if len(points) == 0:
        return np.zeros(0, np.int64)
    ivox = np.floor(np.asarray(points, np.float64) * (1.0 / voxel_size) + 0.5).astype(np.int64)
    blk = np.floor_divide(ivox, res)
    loc = ivox - blk * res
    hm = vbg.hashmap()
    dev = hm.key_tensor().device
    buf, found = hm.find(o3c.Tensor(blk.astype(np.int32)).to(dev))
    buf = buf.cpu().numpy().astype(np.int64)
    found = found.cpu().numpy()
    flat = buf * res**3 + (loc[:, 2] * res + loc[:, 1]) * res + loc[:, 0]
    return np.where(found, flat, -1)


def attribute_array(vbg: Any, name: str) -> Any:
    """Attribute ``name`` as (capacity, res, res, res, C), zero-copy: a numpy view on CPU, a
    torch tensor (DLPack) on CUDA. Open3D's own tensor indexing is about 60x slower than
    either on CPU. Re-read it after the grid grows, which reallocates."""
    t = vbg.attribute(name)
    if t.device.get_type() == _o3c().Device.DeviceType.CPU:
        return t.numpy()
    from torch.utils.dlpack import from_dlpack

    return from_dlpack(t.to_dlpack())


def index_like(arr: Any, idx: Annotated[np.ndarray, "(N,) int64"]) -> Any:
    """``idx`` as an index for ``arr`` (numpy as is, a torch tensor on the array's device)."""
    if isinstance(arr, np.ndarray):
        return idx
    import torch

    return torch.from_numpy(np.ascontiguousarray(idx, np.int64)).to(arr.device)


def like(arr: Any, value: np.ndarray) -> Any:
    """Host array ``value`` where ``arr`` lives (itself for numpy, a device copy for torch)."""
    if isinstance(arr, np.ndarray):
        return value
    import torch

    return torch.from_numpy(np.ascontiguousarray(value)).to(arr.device)


def to_host(x: Any) -> np.ndarray:
    return x if isinstance(x, np.ndarray) else x.cpu().numpy()


def gather_rows(
    vbg: Any, name: str, flat: Annotated[np.ndarray, "(N,) int64, -1 = none"], fill: float
) -> Annotated[np.ndarray, "(N, C) host copy"]:
    """Rows ``flat`` of attribute ``name`` viewed as (capacity * res^3, C); ``fill`` where -1."""
    arr = attribute_array(vbg, name)
    rows = arr.reshape(-1, arr.shape[-1])
    ok = flat >= 0
    got = to_host(rows[index_like(rows, np.where(ok, flat, 0))])
    got[~ok] = fill
    return got


def canonical_order(
    vertices: Annotated[np.ndarray, "(V, 3) float32"],
    faces: Annotated[np.ndarray, "(F, 3) int"],
    tiebreak: tuple[Annotated[np.ndarray, "(V,) int"], ...] = (),
) -> tuple[
    Annotated[np.ndarray, "(V,) int64 new -> old vertex"], Annotated[np.ndarray, "(F, 3) int32"]
]:
    """A vertex order by position (x, then y, then z) and the faces renumbered, each rotated to
    start at its smallest index (winding kept) and sorted. Vertices at the same position (a
    zero crossing exactly on a voxel, where up to six edges meet) keep their input order, or
    follow ``tiebreak`` (keys in order of precedence) where given."""
    perm = np.lexsort((vertices[:, 2], vertices[:, 1], vertices[:, 0]))
    if tiebreak and len(perm) > 1:
        v = vertices[perm]
        if np.any(np.all(v[1:] == v[:-1], axis=1)):  # rare: sort again with the tiebreak keys
            perm = np.lexsort((*tiebreak[::-1], vertices[:, 2], vertices[:, 1], vertices[:, 0]))
    inv = np.empty(len(perm), np.int64)
    inv[perm] = np.arange(len(perm))
    f = inv[faces]
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    # rotate (a, b, c) to (b, c, a) where b is smallest, (c, a, b) where c is (ties: the first)
    at_b = (b < a) & (b <= c)
    at_c = (c < a) & (c < b)
    f = np.stack([np.where(at_b, b, np.where(at_c, c, a)), np.where(at_b, c, np.where(at_c, a, b)), np.where(at_b, a, np.where(at_c, b, c))], axis=1)
    n = max(len(perm), 1)
    if n < 2**21:  # one int64 key per face: a stable sort of it is the lexicographic order, 3x faster
        order = np.argsort((f[:, 0] * n + f[:, 1]) * n + f[:, 2], kind="stable")
    else:
        order = np.lexsort((f[:, 2], f[:, 1], f[:, 0]))
    return perm, f[order].astype(np.int32)


def extract_hypothesis_mesh(
    vbg: Any, voxel_size: float, res: int, k: int, weight_threshold: float
) -> HypothesisMesh:
    """Marching cubes over every block of ``vbg`` with vertex colours and hypotheses."""
    if vbg.hashmap().size() == 0:  # Open3D raises on an empty grid
        return HypothesisMesh.empty(k)
    mesh = vbg.extract_triangle_mesh(weight_threshold=weight_threshold).cpu()
    if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0:
        return HypothesisMesh.empty(k)
    pos = mesh.vertex.positions.numpy().astype(np.float32)
    faces = (
        mesh.triangle.indices.numpy() if "indices" in mesh.triangle else np.zeros((0, 3), np.int64)
    )
    if "colors" in mesh.vertex:
        col = np.clip(np.rint(mesh.vertex.colors.numpy() * 255.0), 0, 255).astype(np.uint8)
    else:
        col = np.zeros((len(pos), 3), np.uint8)
    perm, faces = canonical_order(pos, faces)
    pos, col = pos[perm], col[perm]
    ends, share = edge_ends(pos, voxel_size)
    ids, weights, flats = [], [], []
    for end, frac in zip(ends, share, strict=True):
        flat = voxel_flat_index(vbg, end, voxel_size, res)
        flats.append(flat)
        ids.append(gather_rows(vbg, "hyp_id", flat, 0).astype(np.int32) - 1)
        weights.append(gather_rows(vbg, "hyp_w", flat, 0.0).astype(np.float64) * frac[:, None])
    hyp_ids, hyp_weights = merge_hypotheses(ids[0], weights[0], ids[1], weights[1], k)
    # the anchor frame of the nearer end (both are usually fused by the same frames)
    nearer = np.where(share[0] >= share[1], flats[0], flats[1])
    anchors = gather_rows(vbg, "anchor", nearer, -1)[:, 0].astype(np.int32)
    return HypothesisMesh(
        vertices=np.ascontiguousarray(pos), colors=np.ascontiguousarray(col), faces=faces,
        hyp_ids=hyp_ids, hyp_weights=hyp_weights, anchors=anchors,
    )  # fmt: skip


def edge_ends(
    points: Annotated[np.ndarray, "(V, 3) float world metres, on grid edges"], voxel_size: float
) -> tuple[
    tuple[Annotated[np.ndarray, "(V, 3) float64 metres"], Annotated[np.ndarray, "(V, 3) float64 metres"]],
    tuple[Annotated[np.ndarray, "(V,) float64 in [0, 1]"], Annotated[np.ndarray, "(V,) float64 in [0, 1]"]],
]:
    """The two voxel centres of the grid edge each vertex lies on, and each end's interpolation
    share (1 - t, t), t being the vertex's position along the edge from the first end.

    The edge runs along the axis where the vertex is farthest from a voxel centre (the other two
    coordinates are voxel-centre coordinates, up to float32 rounding); a vertex exactly on a
    voxel centre gets that voxel with share 1 and its neighbour with share 0."""
    g = np.asarray(points, np.float64) / voxel_size
    near = np.rint(g)
    axis = np.argmax(np.abs(g - near), axis=1)
    rows = np.arange(len(g))
    lo = near.copy()
    lo[rows, axis] = np.floor(g[rows, axis])
    hi = lo.copy()
    hi[rows, axis] += 1.0
    t = np.clip(g[rows, axis] - lo[rows, axis], 0.0, 1.0)
    return (lo * voxel_size, hi * voxel_size), (1.0 - t, t)


def merge_hypotheses_numpy(ids_a: np.ndarray, w_a: np.ndarray, ids_b: np.ndarray, w_b: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`merge_hypotheses` in numpy (the rule as written, and the fallback without numba)."""
    ids_a = np.where(w_a > 0, ids_a, -1)
    ids_b = np.where(w_b > 0, ids_b, -1)
    w_a = np.where(ids_a >= 0, w_a, 0.0).astype(np.float64)
    w_b = np.where(ids_b >= 0, w_b, 0.0).astype(np.float64)
    same = (ids_b[:, :, None] == ids_a[:, None, :]) & (ids_b[:, :, None] >= 0)  # (V, Kb, Ka)
    w_a = w_a + np.einsum("vba,vb->va", same, w_b)
    ids_b = np.where(same.any(axis=2), -1, ids_b)
    ids = np.concatenate([ids_a, ids_b], axis=1)
    w = np.concatenate([w_a, np.where(ids_b >= 0, w_b, 0.0)], axis=1)
    order = np.argsort(np.where(ids >= 0, -w, np.inf), axis=1, kind="stable")[:, :k]
    ids = np.take_along_axis(ids, order, axis=1).astype(np.int32)
    w = np.take_along_axis(w, order, axis=1)
    return ids, np.where(ids >= 0, w, 0.0).astype(np.float32)


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _merge_rows(ids_a, w_a, ids_b, w_b, k, out_ids, out_w):  # pragma: no cover - compiled
        """``merge_hypotheses_numpy`` row by row: the same sums in the same order, the same
        stable order (weight descending, then slot), without the (V, Kb, Ka) temporaries."""
        ka, kb = ids_a.shape[1], ids_b.shape[1]
        ids = np.empty(ka + kb, np.int64)
        w = np.empty(ka + kb, np.float64)
        key = np.empty(ka + kb, np.float64)
        order = np.empty(ka + kb, np.int64)
        for v in range(ids_a.shape[0]):
            for i in range(ka):
                t = ids_a[v, i] if w_a[v, i] > 0 else -1
                ids[i] = t
                w[i] = np.float64(w_a[v, i]) if t >= 0 else 0.0
            for j in range(kb):
                t = ids_b[v, j] if w_b[v, j] > 0 else -1
                wb = np.float64(w_b[v, j]) if t >= 0 else 0.0
                matched = False
                if t >= 0:
                    for i in range(ka):
                        if ids[i] == t:
                            matched = True
                if matched:
                    ids[ka + j] = -1
                    w[ka + j] = 0.0
                else:
                    ids[ka + j] = t
                    w[ka + j] = wb
            for i in range(ka):  # a's weights plus the b weights of the same track (einsum's sum)
                if ids[i] >= 0:
                    extra = 0.0
                    for j in range(kb):
                        t = ids_b[v, j] if w_b[v, j] > 0 else -1
                        if t >= 0 and t == ids[i]:
                            extra += np.float64(w_b[v, j])
                    w[i] = w[i] + extra
            n = ka + kb
            for m in range(n):
                key[m] = -w[m] if ids[m] >= 0 else np.inf
                order[m] = m
            for m in range(1, n):  # stable insertion sort: a few slots a row
                o = order[m]
                x = key[o]
                p = m - 1
                while p >= 0 and key[order[p]] > x:
                    order[p + 1] = order[p]
                    p -= 1
                order[p + 1] = o
            for m in range(k):
                o = order[m]
                out_ids[v, m] = ids[o]
                out_w[v, m] = np.float32(w[o]) if ids[o] >= 0 else np.float32(0.0)


def merge_hypotheses(
    ids_a: Annotated[np.ndarray, "(V, K) int32 track id, -1 = empty"],
    w_a: Annotated[np.ndarray, "(V, K) float"],
    ids_b: Annotated[np.ndarray, "(V, K) int32 track id, -1 = empty"],
    w_b: Annotated[np.ndarray, "(V, K) float"],
    k: int,
) -> tuple[Annotated[np.ndarray, "(V, k) int32"], Annotated[np.ndarray, "(V, k) float32"]]:
    """Per row, the union of two hypothesis sets (each track at most once per set), weights of a
    track in both added, entries of zero weight dropped, the ``k`` heaviest kept in descending
    weight (ties: the first set's slots, in slot order, then the second's); ``k`` is at most
    the two sets' slots together. A numba kernel where numba is installed (4x faster at a
    mesh's 70k vertices), equal to :func:`merge_hypotheses_numpy` bit for bit."""
    if numba is None:
        return merge_hypotheses_numpy(ids_a, w_a, ids_b, w_b, k)
    n, k = len(ids_a), min(int(k), ids_a.shape[1] + ids_b.shape[1])
    out_ids, out_w = np.empty((n, k), np.int32), np.empty((n, k), np.float32)
    _merge_rows(np.ascontiguousarray(ids_a), np.ascontiguousarray(w_a, np.float64), np.ascontiguousarray(ids_b),
                np.ascontiguousarray(w_b, np.float64), k, out_ids, out_w)  # fmt: skip
    return out_ids, out_w


def _o3c() -> Any:
    from shared.o3d import import_open3d

    return import_open3d().core

