"""The numba kernels of :mod:`services.fusion.volume.move`: the per-voxel move, the one-pass
move of whole blocks (targets, then rasterisation), vote merging, gap filling and the block
bookkeeping they share. Each has a numpy counterpart in ``move`` that gives the same result;
``move`` picks these when numba is installed (the fusion extra has it).

Blocks are dense (B, res^3, C) arrays with the voxels in Open3D's order, index
``(z * res + y) * res + x``.
"""

from __future__ import annotations

import numpy as np

try:
    import numba

    # OpenMP or numba's own pool for the one parallel kernel: an older TBB on the system (as
    # here) is only a warning away otherwise
    if numba.config.THREADING_LAYER == "default":
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
except ImportError:  # numpy does the same, slower
    numba = None

if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def move_voxels(vox, row, deltas, tsdf, grad, off, voxel_size, max_shift):  # pragma: no cover - compiled
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
            if s * s * g2 > max_shift * max_shift:
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
    def winners(cell, weight, cells):  # pragma: no cover - compiled
        best = np.full(cells, -1, np.int64)
        for i in range(cell.shape[0]):
            c = cell[i]
            if best[c] < 0 or weight[i] > weight[best[c]]:
                best[c] = i
        return best



    @numba.njit(cache=True, nogil=True)
    def merge_votes(cell, ids, ws, cells, k):  # pragma: no cover - compiled
        out_id = np.zeros((cells, k), np.int32)
        out_w = np.zeros((cells, k), np.float32)
        for i in range(cell.shape[0]):
            add_votes(out_id, out_w, cell[i], ids[i], ws[i], k)
        return out_id, out_w

    @numba.njit(cache=True, nogil=True)
    def add_votes(out_id, out_w, c, ids, ws, k):  # pragma: no cover - compiled
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



    @numba.njit(cache=True, nogil=True, parallel=True)
    def targets(keys, idx, tsdf, weight, hyp_w, anchor, offset, lut, lo, deltas, res, voxel_size, scale, max_shift):  # pragma: no cover - compiled
        """Per voxel: filled or not, where its content and its votes land, its carried signed
        distance and its new sub-voxel offset (see :func:`move_voxels`). Block ``b`` is row
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
    def rasterise(target, target_h, filled, tsdf, off, idx, weight, color, anchor, hyp_id, hyp_w, res, bmin, ext, k):  # pragma: no cover - compiled
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
        keys = number_blocks(lut, bmin, ext)
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
                add_votes(id_o, w_o, c, hyp_id[idx[b], v], hyp_w[idx[b], v], k)
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
    def fill_gaps(tsdf, weight, color, hyp_id, hyp_w, anchor, offset, res):  # pragma: no cover - compiled
        """:func:`services.fusion.volume.move._fill_gaps` voxel by voxel (x, then y, then z, as the numpy passes)."""
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
    def gradient(t, filled):  # pragma: no cover - compiled
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
    def bounds_filled(target, target_h, filled, res):  # pragma: no cover - compiled
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
    def number_blocks(lut, lo, ext):  # pragma: no cover - compiled
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
    def block_bounds(target, res):  # pragma: no cover - compiled
        lo = np.full(3, np.iinfo(np.int64).max, np.int64)
        hi = np.full(3, np.iinfo(np.int64).min, np.int64)
        for i in range(target.shape[0]):
            for a in range(3):
                v = target[i, a] // res
                lo[a] = min(lo[a], v)
                hi[a] = max(hi[a], v)
        return lo, hi

    @numba.njit(cache=True, nogil=True)
    def voxel_cells(target, res, lo, ext):  # pragma: no cover - compiled
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
        keys = number_blocks(lut, lo, ext)
        n = res * res * res
        cells = np.empty(m, np.int64)
        for i in range(m):
            l0 = target[i, 0] - (target[i, 0] // res) * res
            l1 = target[i, 1] - (target[i, 1] // res) * res
            l2 = target[i, 2] - (target[i, 2] // res) * res
            cells[i] = lut[flat[i]] * n + (l2 * res + l1) * res + l0
        return keys, cells
