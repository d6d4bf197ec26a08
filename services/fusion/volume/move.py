"""Voxel blocks moved rigidly, each voxel with the motion of its own anchor frame.

A pose correction (:mod:`services.fusion.corrections.poses`) gives a rigid motion per frame; every voxel
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
it) the work is a few passes over the grid's own memory (:func:`_move_blocks_fused`, kernels in
:mod:`services.fusion.volume.move_numba`); without it numpy does the same step by step, slower.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from services.fusion.corrections.poses import Motion
from services.fusion.volume import move_numba as kernels
from services.fusion.volume.move_numba import numba  # None without it: numpy does the same, slower

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
nearest to its surface point (:mod:`services.fusion.volume.hypotheses`), so a moved vote goes to the
voxel nearest to the moved surface point. Moved with the voxel centre, votes would drift off
the surface by up to half a voxel with every correction, and after a few the mesh would find
none (measured: 55% of vertices kept their winning track after six shifts; with this, 99%)."""

LUT_CELLS = 1 << 26
"""Largest bounding box of target blocks indexed by a dense table (256 MB of int32); a map
spread wider than that is indexed by sorting instead."""


@dataclass
class MoveCounts:
    """What :func:`move_blocks` did to the voxels."""

    voxels_moved: int = 0
    gaps_filled: int = 0
    """Empty voxels between two filled neighbours after the move, filled from them."""


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
    target, target_h, tsdf, off, filled, moved = kernels.targets(
        np.ascontiguousarray(keys, np.int64), idx, flat["tsdf"][:, :, 0], flat["weight"][:, :, 0], flat["hyp_w"], flat["anchor"][:, :, 0],
        flat["offset"], lut, lo, np.ascontiguousarray(motion.deltas, np.float64), res, float(voxel_size), OFFSET_SCALE, MAX_VOTE_SHIFT,
    )  # fmt: skip
    bmin, bmax = kernels.bounds_filled(target, target_h, filled, res)
    ext = bmax - bmin + 1
    if int(np.prod(ext)) > LUT_CELLS:
        return None, None, None
    out_keys, tsdf_o, weight_o, color_o, anchor_o, off_o, id_o, w_o = kernels.rasterise(
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
        return kernels.gradient(np.ascontiguousarray(tsdf[..., 0] if tsdf.ndim == 5 else tsdf, np.float32), np.ascontiguousarray(filled))
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


def _merge_votes(cell, ids, ws, cells, cell_w, winner):
    """Per grid point, the votes of every voxel landing there added track by track; a track
    that finds all K slots taken replaces the lightest if it weighs more (the slot rule of
    eq. 5). Without numba, the votes of the voxel with the most weight."""
    k = ids.shape[1]
    if numba is not None:
        return kernels.merge_votes(cell, np.ascontiguousarray(ids, np.int32), np.ascontiguousarray(ws, np.float32), cells, k)
    out_id = np.zeros((cells, k), np.int32)
    out_w = np.zeros((cells, k), np.float32)
    out_id[cell_w], out_w[cell_w] = ids[winner], ws[winner]
    return out_id, out_w


def _move(vox, row, deltas, tsdf, grad, off, voxel_size):
    if numba is not None:
        return kernels.move_voxels(vox, row, deltas, tsdf, np.ascontiguousarray(grad), np.ascontiguousarray(off), voxel_size, MAX_VOTE_SHIFT)
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
        lo, hi = kernels.block_bounds(target, res)
        ext = hi - lo + 1
        if int(np.prod(ext)) <= LUT_CELLS:
            keys, cells = kernels.voxel_cells(target, res, lo, ext)
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
            best = kernels.winners(cell, weight, len(keys) * n)
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


def _fill_gaps(out: Blocks, res: int) -> int:
    """Empty grid points between two filled ones along x, y or z inside a block: the mean
    signed distance of the two, the lower weight, the rest from the heavier. In place."""
    b = len(out["weight"])
    if b == 0:
        return 0
    n = res**3
    if numba is not None and all(a.flags.c_contiguous for a in out.values()):
        flat = [out[name].reshape(b, n, -1) for name in ("tsdf", "weight", "color", "hyp_id", "hyp_w", "anchor", "offset")]
        return int(kernels.fill_gaps(*flat, res))
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
