"""Voxel blocks moved rigidly, each voxel with the motion of its own anchor frame.

A pose correction (:mod:`services.fusion.poses`) gives a rigid motion per frame; every voxel
moves with its anchor, the mean frame fused into it (``HypothesisTSDF.integrate``). A voxel
keeps its signed distance, weight, colour and hypotheses (a rigid motion preserves distances
to the surface):

- it lands on the grid point nearest to where its content is: its centre plus its ``offset``
  attribute, the sub-voxel remainder of earlier moves (int8, :data:`OFFSET_SCALE`), which this
  move updates, so roundings do not add up over many corrections;
- its signed distance is carried from its moved centre to that grid point along its gradient
  (finite differences inside the block): without it a whole wall would shift by the rounding;
- its votes go to the voxel nearest to the moved surface point (:data:`HYPOTHESIS_ATTRS`), where
  a pixel would have voted, and votes landing together add up track by track;
- of two voxels landing on one grid point the heavier stays, and a grid point left empty
  between two filled neighbours (a rotation's rounding) is filled from them.

Everything works on whole blocks as dense arrays (B, res, res, res, C), with the block's
voxels in Open3D's order, index ``(z * res + y) * res + x``. With numba (the fusion extra has
it) the work is a few passes over the grid's own memory (:func:`_move_blocks_fused`);
without it numpy does the same step by step, slower.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from services.fusion.poses import Motion

try:
    import numba

    # OpenMP or numba's own pool for the one parallel kernel: an older TBB on the system (as
    # here) is only a warning away otherwise
    if numba.config.THREADING_LAYER == "default":
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
except ImportError:  # numpy does the same, slower
    numba = None

Blocks = dict[str, Annotated[np.ndarray, "(B, res, res, res, C)"]]

OFFSET_SCALE = 200.0
"""``offset`` attribute units per voxel: where a moved voxel's content sits relative to its
grid point, as int8 in [-127, 127] (half a voxel is 100). Each move lands a voxel on the grid
point nearest to where its content really is, so roundings do not add up: without it, six
moves shifted an object's outline by 1.5 voxels on average."""

MAX_VOTE_SHIFT = 2.0
"""Voxels: a vote is moved onto the surface when the surface is at most this far from it."""

HYPOTHESIS_ATTRS = ("hyp_id", "hyp_w")
"""Attributes that follow the surface, not the voxel centre: a pixel votes in the voxel
nearest to its surface point (:mod:`services.fusion.hypotheses`), so a moved vote goes to the
voxel nearest to the moved surface point. Moved with the voxel centre, votes would drift off
the surface by up to half a voxel with every correction, and after a few the mesh would find
none (measured: 55% of vertices kept their winning track after six shifts; with this, 99%)."""

LUT_CELLS = 1 << 26
"""Largest bounding box of target blocks indexed by a dense table (256 MB of int32); a map
spread wider than that is indexed by sorting instead."""


@dataclass
class MoveCounts:
    voxels_moved: int = 0
    gaps_filled: int = 0


def filled_mask(attrs: Blocks, n: int) -> Annotated[np.ndarray, "(B, n) bool"]:
    """Voxels holding anything: a TSDF weight or a hypothesis."""
    b = len(attrs["weight"])
    hw = attrs["hyp_w"].reshape(b, n, attrs["hyp_w"].shape[-1])
    return (attrs["weight"].reshape(b, n) > 0) | (hw > 0).any(axis=2)


def move_blocks(
    keys: Annotated[np.ndarray, "(B, 3) int block keys"],
    attrs: Blocks,
    motion: Motion,
    res: int,
    voxel_size: float,
    layout: dict[str, tuple[Any, int]],
    rows: Annotated[np.ndarray, "(B,) int64"] | None = None,
) -> tuple[Annotated[np.ndarray, "(B', 3) int32"], Blocks, MoveCounts]:
    """The blocks' voxels moved by their anchors' motions (voxels whose anchor did not move
    stay), rasterised back into blocks. With ``rows``, ``attrs`` are whole attribute arrays
    (a grid's zero-copy views) and block ``b`` is their row ``rows[b]``."""
    b, n = len(keys), res**3
    if b == 0:
        return np.zeros((0, 3), np.int32), {k: np.zeros((0, res, res, res, c), d) for k, (d, c) in layout.items()}, MoveCounts()
    if numba is not None and set(layout) == FUSED_LAYOUT:
        idx = np.arange(b, dtype=np.int64) if rows is None else np.asarray(rows, np.int64)
        out_keys, out, counts = _move_blocks_fused(keys, attrs, idx, motion, res, voxel_size, layout)
        if out_keys is not None:
            if motion.rotates():
                counts.gaps_filled = _fill_gaps(out, res)
            return out_keys.astype(np.int32), out, counts
    if rows is not None:
        attrs = {name: a[rows] for name, a in attrs.items()}
    filled = filled_mask(attrs, n)
    rows = _delta_rows(motion, attrs["anchor"].reshape(b, n))
    # distances are defined where something was fused (a voxel with votes only has none)
    grad = _gradient(attrs["tsdf"].reshape(b, res, res, res), (attrs["weight"] > 0).reshape(b, res, res, res))
    src = np.flatnonzero(filled.reshape(-1))  # flat voxel index b * n + loc; one take per attribute
    blk, loc = src // n, src % n
    local = np.stack([loc % res, (loc // res) % res, loc // (res * res)], axis=1)
    vox = np.asarray(keys, np.int64)[blk] * res + local
    row = rows.reshape(-1)[src]
    tsdf = attrs["tsdf"].reshape(-1)[src].astype(np.float64)
    g = grad.reshape(-1, 3)[src]
    off = attrs["offset"].reshape(-1, 3)[src].astype(np.float64) / OFFSET_SCALE
    target, target_h, tsdf, off = _move(vox, row, np.ascontiguousarray(motion.deltas, np.float64), tsdf, g, off, float(voxel_size))
    off = np.clip(np.rint(off * OFFSET_SCALE), -127, 127).astype(np.int8)
    counts = MoveCounts(voxels_moved=int((row >= 0).sum()))
    weight = attrs["weight"].reshape(-1)[src].astype(np.float64)
    hyp_w = attrs["hyp_w"].reshape(b * n, -1)[src]
    hyp_weight = hyp_w.sum(axis=1, dtype=np.float64)
    voting = np.flatnonzero(hyp_weight > 0)
    out_keys, (cell, winner), (cell_h, winner_h), cell_all_h = _cells([target, target_h[voting]], [weight, hyp_weight[voting]], res)
    winner_h = voting[winner_h]
    out = {}
    for name, (dtype, ch) in layout.items():
        if name in HYPOTHESIS_ATTRS:
            continue
        arr = np.zeros((len(out_keys) * n, ch), dtype)
        if name == "tsdf":
            arr[cell] = tsdf[winner][:, None].astype(dtype)
        elif name == "offset":
            arr[cell] = off[winner]
        else:
            arr[cell] = attrs[name].reshape(b * n, ch)[src[winner]]
        out[name] = arr.reshape(len(out_keys), res, res, res, ch)
    k = attrs["hyp_id"].shape[-1]
    ids, ws = _merge_votes(cell_all_h, attrs["hyp_id"].reshape(b * n, k)[src[voting]], hyp_w[voting], len(out_keys) * n, cell_h, winner_h)
    out["hyp_id"] = ids.reshape(len(out_keys), res, res, res, k)
    out["hyp_w"] = ws.reshape(len(out_keys), res, res, res, k)
    if motion.rotates():
        counts.gaps_filled = _fill_gaps(out, res)
    return out_keys.astype(np.int32), out, counts


FUSED_LAYOUT = {"tsdf", "weight", "color", "hyp_id", "hyp_w", "anchor", "offset"}
"""The grid layout the one-pass numba kernel is written for (``HypothesisTSDF``'s)."""


def _move_blocks_fused(keys, attrs, idx, motion, res, voxel_size, layout):
    """:func:`move_blocks` in numba passes over the blocks' own arrays: no per-voxel copies
    of every attribute in between (three times faster on the 900-frame demo map). Returns
    ``(None, None, None)`` when the blocks spread over too large a box for its lookup table."""
    n = res**3
    k = attrs["hyp_id"].shape[-1]
    flat = {name: np.ascontiguousarray(attrs[name]).reshape(len(attrs[name]), n, -1) for name in layout}
    anchors = flat["anchor"][idx, :, 0]
    lo, hi = int(anchors.min(initial=0)), int(anchors.max(initial=0))
    lut = motion.rows(lo, hi)
    target, target_h, tsdf, off, filled, moved = _targets_numba(
        np.ascontiguousarray(keys, np.int64), idx, flat["tsdf"][:, :, 0], flat["weight"][:, :, 0], flat["hyp_w"], flat["anchor"][:, :, 0],
        flat["offset"], lut, lo, np.ascontiguousarray(motion.deltas, np.float64), res, float(voxel_size), OFFSET_SCALE, MAX_VOTE_SHIFT,
    )  # fmt: skip
    bmin, bmax = _bounds_filled_numba(target, target_h, filled, res)
    ext = bmax - bmin + 1
    if int(np.prod(ext)) > LUT_CELLS:
        return None, None, None
    out_keys, tsdf_o, weight_o, color_o, anchor_o, off_o, id_o, w_o = _rasterise_numba(
        target, target_h, filled, tsdf, off, idx, flat["weight"][:, :, 0], flat["color"], flat["anchor"][:, :, 0], flat["hyp_id"], flat["hyp_w"],
        res, bmin, ext, k,
    )  # fmt: skip
    m = len(out_keys)
    shape = (m, res, res, res)
    out = {
        "tsdf": tsdf_o.reshape(*shape, 1), "weight": weight_o.reshape(*shape, 1), "color": color_o.reshape(*shape, 3),
        "anchor": anchor_o.reshape(*shape, 1), "offset": off_o.reshape(*shape, 3), "hyp_id": id_o.reshape(*shape, k),
        "hyp_w": w_o.reshape(*shape, k),
    }  # fmt: skip
    return out_keys, out, MoveCounts(voxels_moved=int(moved))


def moving_voxels(motion: Motion, anchors: Annotated[np.ndarray, "(B, n) int"]) -> Annotated[np.ndarray, "(B, n) bool"]:
    """Which voxels' anchors move."""
    return _delta_rows(motion, anchors) >= 0


def _delta_rows(motion: Motion, anchors: Annotated[np.ndarray, "(B, n) int"]) -> Annotated[np.ndarray, "(B, n) int64, -1 = stays"]:
    """The row of ``motion.deltas`` each voxel moves by, through a table over the frame range."""
    lo, hi = int(anchors.min(initial=0)), int(anchors.max(initial=0))
    return motion.rows(lo, hi)[anchors - lo]


def _gradient(
    tsdf: Annotated[np.ndarray, "(B, z, y, x)"], filled: Annotated[np.ndarray, "(B, z, y, x) bool"]
) -> Annotated[np.ndarray, "(B, z, y, x, 3) float64 per voxel along x, y, z"]:
    """Finite differences of the signed distance inside each block: central where both
    neighbours hold a value, one-sided where one does, 0 where neither."""
    if numba is not None:
        return _gradient_numba(np.ascontiguousarray(tsdf[..., 0] if tsdf.ndim == 5 else tsdf, np.float32), np.ascontiguousarray(filled))
    t = tsdf.astype(np.float64)
    out = np.zeros((*t.shape, 3))
    for k, axis in enumerate((3, 2, 1)):  # x, y, z
        fwd = np.zeros_like(t)
        bwd = np.zeros_like(t)
        has_f = np.zeros(t.shape, bool)
        has_b = np.zeros(t.shape, bool)
        hi = [slice(None)] * 4
        lo = [slice(None)] * 4
        hi[axis], lo[axis] = slice(1, None), slice(None, -1)
        hi, lo = tuple(hi), tuple(lo)
        fwd[lo] = t[hi] - t[lo]
        has_f[lo] = filled[hi]
        bwd[hi] = t[hi] - t[lo]
        has_b[hi] = filled[lo]
        out[..., k] = np.where(has_f & has_b, (fwd + bwd) / 2, np.where(has_f, fwd, np.where(has_b, bwd, 0.0)))
    return out


def _surface_offset(at, grad, tsdf):
    """Per voxel, ``s`` such that ``content - s * grad`` is the nearest surface point, from the
    distance ``at`` the content's position (voxel units; 0 where the stored distance is
    truncated or the gradient vanishes)."""
    g2 = np.einsum("ni,ni->n", grad, grad)
    ok = (np.abs(tsdf) < 1.0) & (g2 > 1e-6)
    s = np.where(ok, at / np.where(ok, g2, 1.0), 0.0)
    return np.where(s * s * g2 > MAX_VOTE_SHIFT**2, 0.0, s)


def _move_numpy(vox, row, deltas, tsdf, grad, off, voxel_size):
    target = vox.copy()
    target_h = vox.copy()
    tsdf = tsdf.copy()
    off = off.copy()
    moving = np.flatnonzero(row >= 0)
    if len(moving) == 0:
        return target, target_h, tsdf, off
    content = vox + off  # voxel units: where each voxel's content sits
    at = tsdf + np.einsum("ni,ni->n", grad, off)  # the distance there
    surface = content - _surface_offset(at, grad, tsdf)[:, None] * grad
    # by delta row, so each group is one matrix product
    order = moving[np.argsort(row[moving], kind="stable")]
    bounds = np.flatnonzero(np.diff(row[order])) + 1
    for part in np.split(order, bounds):
        D = deltas[row[part[0]]]
        q = ((vox[part] * voxel_size) @ D[:3, :3].T + D[:3, 3]) / voxel_size  # the grid point, moved
        qc = ((content[part] * voxel_size) @ D[:3, :3].T + D[:3, 3]) / voxel_size  # the content, moved
        g = np.floor(qc + 0.5)
        target[part] = g.astype(np.int64)
        off[part] = qc - g
        tsdf[part] += np.einsum("ni,ni->n", grad[part] @ D[:3, :3].T, g - q)
        qs = (surface[part] * voxel_size) @ D[:3, :3].T + D[:3, 3]
        target_h[part] = np.floor(qs / voxel_size + 0.5).astype(np.int64)
    np.clip(tsdf, -1.0, 1.0, out=tsdf)
    return target, target_h, tsdf, off


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _move_numba(vox, row, deltas, tsdf, grad, off, voxel_size):  # pragma: no cover - compiled
        n = vox.shape[0]
        target = vox.copy()
        target_h = vox.copy()
        out = tsdf.copy()
        off_out = off.copy()
        for i in range(n):
            r = row[i]
            if r < 0:
                continue
            g2 = grad[i, 0] * grad[i, 0] + grad[i, 1] * grad[i, 1] + grad[i, 2] * grad[i, 2]
            # the distance at the content's position, not at the grid point
            at = tsdf[i] + grad[i, 0] * off[i, 0] + grad[i, 1] * off[i, 1] + grad[i, 2] * off[i, 2]
            s = at / g2 if abs(tsdf[i]) < 1.0 and g2 > 1e-6 else 0.0
            # a vote sits within a voxel or two of the surface; a flat gradient is no evidence of farther
            if s * s * g2 > MAX_VOTE_SHIFT * MAX_VOTE_SHIFT:
                s = 0.0
            p0 = vox[i, 0] * voxel_size
            p1 = vox[i, 1] * voxel_size
            p2 = vox[i, 2] * voxel_size
            c0 = (vox[i, 0] + off[i, 0]) * voxel_size
            c1 = (vox[i, 1] + off[i, 1]) * voxel_size
            c2 = (vox[i, 2] + off[i, 2]) * voxel_size
            s0 = c0 - s * grad[i, 0] * voxel_size
            s1 = c1 - s * grad[i, 1] * voxel_size
            s2 = c2 - s * grad[i, 2] * voxel_size
            d = 0.0
            for a in range(3):
                q = (deltas[r, a, 0] * p0 + deltas[r, a, 1] * p1 + deltas[r, a, 2] * p2 + deltas[r, a, 3]) / voxel_size
                qc = (deltas[r, a, 0] * c0 + deltas[r, a, 1] * c1 + deltas[r, a, 2] * c2 + deltas[r, a, 3]) / voxel_size
                g = np.floor(qc + 0.5)
                target[i, a] = np.int64(g)
                off_out[i, a] = qc - g
                turned = deltas[r, a, 0] * grad[i, 0] + deltas[r, a, 1] * grad[i, 1] + deltas[r, a, 2] * grad[i, 2]
                d += turned * (g - q)
                qs = (deltas[r, a, 0] * s0 + deltas[r, a, 1] * s1 + deltas[r, a, 2] * s2 + deltas[r, a, 3]) / voxel_size
                target_h[i, a] = np.int64(np.floor(qs + 0.5))
            v = out[i] + d
            out[i] = min(1.0, max(-1.0, v))
        return target, target_h, out, off_out

    @numba.njit(cache=True, nogil=True)
    def _winners_numba(cell, weight, cells):  # pragma: no cover - compiled
        best = np.full(cells, -1, np.int64)
        for i in range(cell.shape[0]):
            c = cell[i]
            if best[c] < 0 or weight[i] > weight[best[c]]:
                best[c] = i
        return best


def _merge_votes(cell, ids, ws, cells, cell_w, winner):
    """Per grid point, the votes of every voxel landing there added track by track; a track
    that finds all K slots taken replaces the lightest if it weighs more (the slot rule of
    eq. 5). Without numba, the votes of the voxel with the most weight."""
    k = ids.shape[1]
    if numba is not None:
        return _merge_votes_numba(cell, np.ascontiguousarray(ids, np.int32), np.ascontiguousarray(ws, np.float32), cells, k)
    out_id = np.zeros((cells, k), np.int32)
    out_w = np.zeros((cells, k), np.float32)
    out_id[cell_w], out_w[cell_w] = ids[winner], ws[winner]
    return out_id, out_w


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _merge_votes_numba(cell, ids, ws, cells, k):  # pragma: no cover - compiled
        out_id = np.zeros((cells, k), np.int32)
        out_w = np.zeros((cells, k), np.float32)
        for i in range(cell.shape[0]):
            _add_votes(out_id, out_w, cell[i], ids[i], ws[i], k)
        return out_id, out_w

    @numba.njit(cache=True, nogil=True)
    def _add_votes(out_id, out_w, c, ids, ws, k):  # pragma: no cover - compiled
        """One voxel's votes into grid point ``c``: a track's weight adds to its slot, a new
        track takes an empty or the lightest slot if it weighs more (eq. 5's slot rule)."""
        for j in range(k):
            t = ids[j]
            w = ws[j]
            if t == 0 or w <= 0:
                continue
            slot = -1
            low = 0
            for s in range(k):
                if out_id[c, s] == t:
                    slot = s
                    break
                if out_w[c, s] < out_w[c, low]:
                    low = s
            if slot >= 0:
                out_w[c, slot] += w
            elif out_w[c, low] < w:
                out_id[c, low] = t
                out_w[c, low] = w


def _move(vox, row, deltas, tsdf, grad, off, voxel_size):
    if numba is not None:
        return _move_numba(vox, row, deltas, tsdf, np.ascontiguousarray(grad), np.ascontiguousarray(off), voxel_size)
    return _move_numpy(vox, row, deltas, tsdf, grad, off, voxel_size)


def _cells(
    targets: list[Annotated[np.ndarray, "(N, 3) int64 voxel coordinates"]], weights: list[Annotated[np.ndarray, "(N,)"]], res: int
) -> tuple[np.ndarray, ...]:
    """The target blocks of all ``targets``, then per target set the flat cell (block *
    res^3 + index) of each occupied grid point and the heaviest voxel landing there."""
    n = res**3
    bounds = np.cumsum([0] + [len(t) for t in targets])
    target = np.concatenate(targets)
    if numba is not None:
        lo, hi = _bounds_numba(target, res)
        ext = hi - lo + 1
        if int(np.prod(ext)) <= LUT_CELLS:
            keys, cells = _cells_numba(target, res, lo, ext)
            return _winning(keys, cells, bounds, weights, n)
    blocks = np.floor_divide(target, res)
    bmin = blocks.min(axis=0)
    ext = blocks.max(axis=0) - bmin + 1
    off = blocks - bmin
    flat_b = (off[:, 0] * ext[1] + off[:, 1]) * ext[2] + off[:, 2]
    if int(np.prod(ext)) <= LUT_CELLS:
        present = np.zeros(int(np.prod(ext)), bool)
        present[flat_b] = True
        used = np.flatnonzero(present)
        lut = np.full(len(present), -1, np.int64)
        lut[used] = np.arange(len(used))
        bidx = lut[flat_b]
    else:
        used, bidx = np.unique(flat_b, return_inverse=True)
        bidx = bidx.reshape(-1)
    keys = np.stack([used // (ext[1] * ext[2]), (used // ext[2]) % ext[1], used % ext[2]], axis=1) + bmin
    local = target - blocks * res
    cells = bidx * n + (local[:, 2] * res + local[:, 1]) * res + local[:, 0]
    return _winning(keys, cells, bounds, weights, n)


def _winning(keys, cells, bounds, weights, n):
    out = [keys]
    for k, weight in enumerate(weights):
        cell = cells[bounds[k] : bounds[k + 1]]
        if numba is not None:
            best = _winners_numba(cell, weight, len(keys) * n)
        else:
            order = np.lexsort((-weight, cell))
            first = np.ones(len(order), bool)
            first[1:] = cell[order][1:] != cell[order][:-1]
            best = np.full(len(keys) * n, -1, np.int64)
            best[cell[order][first]] = order[first]
        occupied = np.flatnonzero(best >= 0)
        out.append((occupied, best[occupied]))
    out.append(cells[bounds[-2] :])
    return tuple(out)


if numba is not None:

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _targets_numba(keys, idx, tsdf, weight, hyp_w, anchor, offset, lut, lo, deltas, res, voxel_size, scale, max_shift):  # pragma: no cover - compiled
        """Per voxel: filled or not, where its content and its votes land, its carried signed
        distance and its new sub-voxel offset (see :func:`_move_numba`). Block ``b`` is row
        ``idx[b]`` of the attribute arrays."""
        nb, n = idx.shape[0], tsdf.shape[1]
        kk = hyp_w.shape[2]
        target = np.zeros((nb, n, 3), np.int64)
        target_h = np.zeros((nb, n, 3), np.int64)
        out_t = np.zeros((nb, n), np.float32)
        out_off = np.zeros((nb, n, 3), np.int8)
        filled = np.zeros((nb, n), np.bool_)
        moved = 0
        r2 = res * res
        for b in numba.prange(nb):  # voxels are independent here: one block per thread at a time
            i = idx[b]
            for v in range(n):
                f = weight[i, v] > 0
                if not f:
                    for j in range(kk):
                        if hyp_w[i, v, j] > 0:
                            f = True
                            break
                if not f:
                    continue
                filled[b, v] = True
                x, y, z = v % res, (v // res) % res, v // r2
                p = (keys[b, 0] * res + x, keys[b, 1] * res + y, keys[b, 2] * res + z)
                out_t[b, v] = tsdf[i, v]
                a = anchor[i, v] - lo
                row = lut[a] if 0 <= a < lut.shape[0] else -1
                if row < 0:
                    for c in range(3):
                        target[b, v, c] = p[c]
                        target_h[b, v, c] = p[c]
                        out_off[b, v, c] = offset[i, v, c]
                    continue
                moved += 1
                # gradient inside the block (central, one-sided at the edges and next to holes)
                g = np.zeros(3)
                here = tsdf[i, v]
                for c in range(3 if weight[i, v] > 0 else 0):  # no distance where nothing was fused
                    step = 1 if c == 0 else (res if c == 1 else r2)
                    coord = x if c == 0 else (y if c == 1 else z)
                    hp = coord + 1 < res and (weight[i, v + step] > 0)
                    hm = coord > 0 and (weight[i, v - step] > 0)
                    if hp and hm:
                        g[c] = (tsdf[i, v + step] - tsdf[i, v - step]) / 2
                    elif hp:
                        g[c] = tsdf[i, v + step] - here
                    elif hm:
                        g[c] = here - tsdf[i, v - step]
                o = np.empty(3)
                for c in range(3):
                    o[c] = offset[i, v, c] / scale
                g2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
                at = here + g[0] * o[0] + g[1] * o[1] + g[2] * o[2]
                s = at / g2 if abs(here) < 1.0 and g2 > 1e-6 else 0.0
                if s * s * g2 > max_shift * max_shift:
                    s = 0.0
                d = 0.0
                for c in range(3):
                    q = 0.0
                    qc = 0.0
                    qs = 0.0
                    turned = 0.0
                    for e in range(3):
                        q += deltas[row, c, e] * p[e] * voxel_size
                        qc += deltas[row, c, e] * (p[e] + o[e]) * voxel_size
                        qs += deltas[row, c, e] * (p[e] + o[e] - s * g[e]) * voxel_size
                        turned += deltas[row, c, e] * g[e]
                    q = (q + deltas[row, c, 3]) / voxel_size
                    qc = (qc + deltas[row, c, 3]) / voxel_size
                    qs = (qs + deltas[row, c, 3]) / voxel_size
                    gc = np.floor(qc + 0.5)
                    target[b, v, c] = np.int64(gc)
                    target_h[b, v, c] = np.int64(np.floor(qs + 0.5))
                    out_off[b, v, c] = np.int8(min(127.0, max(-127.0, np.floor((qc - gc) * scale + 0.5))))
                    d += turned * (gc - q)
                out_t[b, v] = min(1.0, max(-1.0, here + d))
        return target, target_h, out_t, out_off, filled, moved

    @numba.njit(cache=True, nogil=True)
    def _rasterise_numba(target, target_h, filled, tsdf, off, idx, weight, color, anchor, hyp_id, hyp_w, res, bmin, ext, k):  # pragma: no cover - compiled
        """Moved voxels into whole blocks: the heaviest voxel per grid point for the distance,
        weight, colour, anchor and offset; the votes of all voxels landing on a grid point
        added track by track (the slot rule when K are taken)."""
        nb, n = filled.shape[0], filled.shape[1]
        size = ext[0] * ext[1] * ext[2]
        lut = np.full(size, -1, np.int64)
        for b in range(nb):
            for v in range(n):
                if not filled[b, v]:
                    continue
                votes = False
                for j in range(k):
                    if hyp_w[idx[b], v, j] > 0:
                        votes = True
                for which in range(2 if votes else 1):
                    t = target[b, v] if which == 0 else target_h[b, v]
                    f = ((t[0] // res - bmin[0]) * ext[1] + (t[1] // res - bmin[1])) * ext[2] + (t[2] // res - bmin[2])
                    lut[f] = 0
        keys = _number_blocks(lut, bmin, ext)
        count = len(keys)
        cells = count * n
        best_b = np.full(cells, -1, np.int64)
        best_v = np.zeros(cells, np.int64)
        id_o = np.zeros((cells, k), np.int32)
        w_o = np.zeros((cells, k), np.float32)
        for b in range(nb):
            for v in range(n):
                if not filled[b, v]:
                    continue
                t = target[b, v]
                f = ((t[0] // res - bmin[0]) * ext[1] + (t[1] // res - bmin[1])) * ext[2] + (t[2] // res - bmin[2])
                c = lut[f] * n + ((t[2] % res) * res + (t[1] % res)) * res + (t[0] % res)
                if best_b[c] < 0 or weight[idx[b], v] > weight[idx[best_b[c]], best_v[c]]:
                    best_b[c] = b
                    best_v[c] = v
                t = target_h[b, v]
                f = ((t[0] // res - bmin[0]) * ext[1] + (t[1] // res - bmin[1])) * ext[2] + (t[2] // res - bmin[2])
                c = lut[f] * n + ((t[2] % res) * res + (t[1] % res)) * res + (t[0] % res)
                _add_votes(id_o, w_o, c, hyp_id[idx[b], v], hyp_w[idx[b], v], k)
        tsdf_o = np.zeros(cells, np.float32)
        weight_o = np.zeros(cells, np.float32)
        color_o = np.zeros((cells, 3), np.float32)
        anchor_o = np.zeros(cells, np.int32)
        off_o = np.zeros((cells, 3), np.int8)
        for c in range(cells):
            b = best_b[c]
            if b < 0:
                continue
            v = best_v[c]
            tsdf_o[c] = tsdf[b, v]
            weight_o[c] = weight[idx[b], v]
            anchor_o[c] = anchor[idx[b], v]
            for e in range(3):
                color_o[c, e] = color[idx[b], v, e]
                off_o[c, e] = off[b, v, e]
        return keys, tsdf_o, weight_o, color_o, anchor_o, off_o, id_o, w_o

    @numba.njit(cache=True, nogil=True)
    def _fill_gaps_numba(tsdf, weight, color, hyp_id, hyp_w, anchor, offset, res):  # pragma: no cover - compiled
        """:func:`_fill_gaps` voxel by voxel (x, then y, then z, as the numpy passes)."""
        nb, n = weight.shape[0], weight.shape[1]
        r2 = res * res
        total = 0
        filled = np.zeros((nb, n), np.bool_)
        for b in range(nb):
            for v in range(n):
                f = weight[b, v, 0] > 0
                for j in range(hyp_w.shape[2]):
                    f = f or hyp_w[b, v, j] > 0
                filled[b, v] = f
        for axis in range(3):
            step = 1 if axis == 0 else (res if axis == 1 else r2)
            gaps = []
            for b in range(nb):
                for v in range(n):
                    coord = v % res if axis == 0 else ((v // res) % res if axis == 1 else v // r2)
                    if coord == 0 or coord == res - 1 or filled[b, v]:
                        continue
                    a, c = v - step, v + step
                    if filled[b, a] and filled[b, c]:
                        gaps.append((b, v, a, c))
            for b, v, a, c in gaps:
                heavy = a if weight[b, a, 0] >= weight[b, c, 0] else c
                for e in range(3):
                    color[b, v, e] = color[b, heavy, e]
                    offset[b, v, e] = offset[b, heavy, e]
                for j in range(hyp_id.shape[2]):
                    hyp_id[b, v, j] = hyp_id[b, heavy, j]
                    hyp_w[b, v, j] = hyp_w[b, heavy, j]
                anchor[b, v, 0] = anchor[b, heavy, 0]
                tsdf[b, v, 0] = (np.float64(tsdf[b, a, 0]) + tsdf[b, c, 0]) / 2
                weight[b, v, 0] = min(weight[b, a, 0], weight[b, c, 0])
                filled[b, v] = True
                total += 1
        return total

    @numba.njit(cache=True, nogil=True)
    def _gradient_numba(t, filled):  # pragma: no cover - compiled
        nb, r = t.shape[0], t.shape[1]
        out = np.zeros((nb, r, r, r, 3))
        for b in range(nb):
            for z in range(r):
                for y in range(r):
                    for x in range(r):
                        if not filled[b, z, y, x]:
                            continue
                        here = t[b, z, y, x]
                        for k in range(3):
                            # neighbours along x (k=0), y (k=1), z (k=2)
                            hp = hm = False
                            vp = vm = 0.0
                            if k == 0:
                                if x + 1 < r and filled[b, z, y, x + 1]:
                                    hp, vp = True, t[b, z, y, x + 1]
                                if x > 0 and filled[b, z, y, x - 1]:
                                    hm, vm = True, t[b, z, y, x - 1]
                            elif k == 1:
                                if y + 1 < r and filled[b, z, y + 1, x]:
                                    hp, vp = True, t[b, z, y + 1, x]
                                if y > 0 and filled[b, z, y - 1, x]:
                                    hm, vm = True, t[b, z, y - 1, x]
                            else:
                                if z + 1 < r and filled[b, z + 1, y, x]:
                                    hp, vp = True, t[b, z + 1, y, x]
                                if z > 0 and filled[b, z - 1, y, x]:
                                    hm, vm = True, t[b, z - 1, y, x]
                            if hp and hm:
                                out[b, z, y, x, k] = (vp - vm) / 2
                            elif hp:
                                out[b, z, y, x, k] = vp - here
                            elif hm:
                                out[b, z, y, x, k] = here - vm
        return out

    @numba.njit(cache=True, nogil=True)
    def _bounds_filled_numba(target, target_h, filled, res):  # pragma: no cover - compiled
        lo = np.zeros(3, np.int64)
        hi = np.zeros(3, np.int64)
        first = True
        for b in range(filled.shape[0]):
            for v in range(filled.shape[1]):
                if not filled[b, v]:
                    continue
                for a in range(3):
                    for t in (target[b, v, a] // res, target_h[b, v, a] // res):
                        if first or t < lo[a]:
                            lo[a] = t
                        if first or t > hi[a]:
                            hi[a] = t
                first = False
        return lo, hi

    @numba.njit(cache=True, nogil=True)
    def _number_blocks(lut, lo, ext):  # pragma: no cover - compiled
        """The blocks marked 0 in the table over the box ``lo`` + ``ext`` numbered in table
        order (in place: each entry becomes its block's index, -1 stays), and their keys."""
        count = 0
        for f in range(lut.shape[0]):
            if lut[f] == 0:
                lut[f] = count
                count += 1
        keys = np.empty((count, 3), np.int64)
        for f in range(lut.shape[0]):
            j = lut[f]
            if j >= 0:
                keys[j, 0] = f // (ext[1] * ext[2]) + lo[0]
                keys[j, 1] = (f // ext[2]) % ext[1] + lo[1]
                keys[j, 2] = f % ext[2] + lo[2]
        return keys

    @numba.njit(cache=True, nogil=True)
    def _bounds_numba(target, res):  # pragma: no cover - compiled
        lo = np.full(3, np.iinfo(np.int64).max, np.int64)
        hi = np.full(3, np.iinfo(np.int64).min, np.int64)
        for i in range(target.shape[0]):
            for a in range(3):
                v = target[i, a] // res
                lo[a] = min(lo[a], v)
                hi[a] = max(hi[a], v)
        return lo, hi

    @numba.njit(cache=True, nogil=True)
    def _cells_numba(target, res, lo, ext):  # pragma: no cover - compiled
        """Block keys in first-seen order... sorted by flat table index, and each voxel's cell."""
        m = target.shape[0]
        size = ext[0] * ext[1] * ext[2]
        lut = np.full(size, -1, np.int64)
        flat = np.empty(m, np.int64)
        for i in range(m):
            b0 = target[i, 0] // res - lo[0]
            b1 = target[i, 1] // res - lo[1]
            b2 = target[i, 2] // res - lo[2]
            f = (b0 * ext[1] + b1) * ext[2] + b2
            flat[i] = f
            lut[f] = 0
        keys = _number_blocks(lut, lo, ext)
        n = res * res * res
        cells = np.empty(m, np.int64)
        for i in range(m):
            l0 = target[i, 0] - (target[i, 0] // res) * res
            l1 = target[i, 1] - (target[i, 1] // res) * res
            l2 = target[i, 2] - (target[i, 2] // res) * res
            cells[i] = lut[flat[i]] * n + (l2 * res + l1) * res + l0
        return keys, cells


def _fill_gaps(out: Blocks, res: int) -> int:
    """Empty grid points between two filled ones along x, y or z inside a block: the mean
    signed distance of the two, the lower weight, the rest from the heavier. In place."""
    b = len(out["weight"])
    if b == 0:
        return 0
    n = res**3
    if numba is not None and all(a.flags.c_contiguous for a in out.values()):
        flat = [out[name].reshape(b, n, -1) for name in ("tsdf", "weight", "color", "hyp_id", "hyp_w", "anchor", "offset")]
        return int(_fill_gaps_numba(*flat, res))
    filled = filled_mask(out, n).reshape(b, res, res, res)
    flat = {k: v.reshape(b, n, v.shape[-1]) for k, v in out.items()}
    idx = np.arange(b * n).reshape(b, res, res, res)
    total = 0
    for axis in (3, 2, 1):
        lo = [slice(None)] * 4
        mid = [slice(None)] * 4
        hi = [slice(None)] * 4
        lo[axis], mid[axis], hi[axis] = slice(None, -2), slice(1, -1), slice(2, None)
        lo, mid, hi = tuple(lo), tuple(mid), tuple(hi)
        gap = ~filled[mid] & filled[lo] & filled[hi]
        if not gap.any():
            continue
        g, a, c = idx[mid][gap], idx[lo][gap], idx[hi][gap]
        wa = out["weight"].reshape(-1)[a]
        wc = out["weight"].reshape(-1)[c]
        heavy = np.where(wa >= wc, a, c)
        for arr in flat.values():
            rows = arr.reshape(b * n, arr.shape[-1])
            rows[g] = rows[heavy]
        t = out["tsdf"].reshape(-1)
        t[g] = (t[a].astype(np.float64) + t[c]) / 2
        w = out["weight"].reshape(-1)
        w[g] = np.minimum(wa, wc)
        filled[mid] |= gap
        total += len(g)
    return total


_WARM = False


def warm_up() -> None:
    """Load (or compile) the numba kernels once per process, on one small block: the first
    pose correction of a map would otherwise pay for it (about a second here)."""
    global _WARM
    if _WARM or numba is None:
        return
    res, k = 2, 2
    layout = {"tsdf": (np.float32, 1), "weight": (np.float32, 1), "color": (np.float32, 3), "hyp_id": (np.int32, k),
              "hyp_w": (np.float32, k), "anchor": (np.int32, 1), "offset": (np.int8, 3)}  # fmt: skip
    attrs = {name: np.zeros((1, res, res, res, c), d) for name, (d, c) in layout.items()}
    attrs["weight"][:] = 1.0
    attrs["hyp_w"][..., 0] = 1.0
    attrs["hyp_id"][..., 0] = 1
    turn = np.eye(4)
    turn[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    move_blocks(np.zeros((1, 3), np.int32), attrs, Motion(np.zeros(1, np.int64), turn[None], fused=np.zeros(1, np.int64)), res, 0.1, layout)
    _gradient(attrs["tsdf"][..., 0], attrs["weight"][..., 0] > 0)
    _WARM = True
