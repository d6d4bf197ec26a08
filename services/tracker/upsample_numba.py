"""The numba kernel of :func:`services.tracker.propagation.upsample_labels` on the CPU.

It gives the same slot image as the torch path, bit for bit (tested), with less work:

- it goes cell by cell, a cell being the output pixels that share their four source patches
  (about 14 x 14 pixels at 1200x680 on a 48 x 84 grid). Where the four patches peak at the same
  slot, the whole cell takes it (a convex combination of distributions that all peak first at
  c peaks first at c);
- elsewhere it interpolates only the slots that carry mass in one of the four patches. A
  slot with none is exactly 0 everywhere in the cell, so it cannot beat a positive one, and
  the first maximum among the rest is the first maximum of all (slots are taken in order).
  Propagated distributions hold 3 slots on average (top-k mixing), out of 30 to 40.

The arithmetic is the torch path's, in float32 and in its order (a horizontal pass, then a
vertical one, with ``1 - f`` computed by the caller as torch does), so ties and roundings land
the same way.
"""

from __future__ import annotations

import numpy as np

try:
    import numba

    if numba.config.THREADING_LAYER == "default":
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
except ImportError:  # the torch path does the same, slower
    numba = None


if numba is not None:

    @numba.njit(cache=True, nogil=True, parallel=True)
    def upsample_cells(y, peak, r0, r1, fy, gy, row_start, x0, x1, fx, gx, col_start, lut, out, seen):  # pragma: no cover - compiled
        """``out[Y, X]``: ``lut`` of the argmax of the bilinear mix of ``y`` (h, w, C) at output
        pixel (Y, X), with row taps ``r0, r1`` weighted ``gy = 1 - fy, fy`` and column taps
        ``x0, x1`` weighted ``gx = 1 - fx, fx``. ``row_start[i]:row_start[i + 1]`` are the output
        rows whose first tap is source row i (taps are non-decreasing), the same for columns.
        ``seen[i, c]`` is set where argmax c lands in those rows (the slots present, without a
        second pass over the image)."""
        h, w, n_slots = y.shape
        for i in numba.prange(h):
            ya, yb = row_start[i], row_start[i + 1]
            if ya == yb:
                continue
            ra, rb = r0[ya], r1[ya]
            cand = np.empty(n_slots, np.int64)
            for j in range(w):
                xa, xb = col_start[j], col_start[j + 1]
                if xa == xb:
                    continue
                ca, cb = x0[xa], x1[xa]
                p = peak[ra, ca]
                if p == peak[ra, cb] and p == peak[rb, ca] and p == peak[rb, cb]:
                    v = lut[p]
                    for Y in range(ya, yb):
                        for X in range(xa, xb):
                            out[Y, X] = v
                    seen[i, p] = 1
                    continue
                n = 0
                for c in range(n_slots):
                    if y[ra, ca, c] != 0 or y[ra, cb, c] != 0 or y[rb, ca, c] != 0 or y[rb, cb, c] != 0:
                        cand[n] = c
                        n += 1
                for Y in range(ya, yb):
                    wy0, wy1 = gy[Y], fy[Y]
                    for X in range(xa, xb):
                        wx0, wx1 = gx[X], fx[X]
                        best = np.float32(0.0)
                        arg = 0
                        for t in range(n):
                            c = cand[t]
                            upper = y[ra, ca, c] * wx0 + y[ra, cb, c] * wx1
                            lower = y[rb, ca, c] * wx0 + y[rb, cb, c] * wx1
                            v = upper * wy0 + lower * wy1
                            if v > best:
                                best = v
                                arg = c
                        out[Y, X] = lut[arg]
                        seen[i, arg] = 1

    @numba.njit(cache=True, nogil=True, fastmath={"contract"})
    def bilinear_taps(out_len, in_len):  # pragma: no cover - compiled
        """Source indices ``i0, i1`` and weights ``1 - f, f`` of torch's bilinear upsampling
        (align_corners=False) as its CPU kernel computes them: the source coordinate with one
        fused multiply-add."""
        scale = np.float32(in_len) / np.float32(out_len)
        i0 = np.empty(out_len, np.int64)
        i1 = np.empty(out_len, np.int64)
        g = np.empty(out_len, np.float32)
        f = np.empty(out_len, np.float32)
        for o in range(out_len):
            real = max(scale * (np.float32(o) + np.float32(0.5)) - np.float32(0.5), np.float32(0.0))
            i = min(np.int64(np.floor(real)), in_len - 1)
            i0[o] = i
            i1[o] = i + 1 if i < in_len - 1 else i
            f[o] = min(max(real - np.float32(i), np.float32(0.0)), np.float32(1.0))
            g[o] = np.float32(1.0) - f[o]
        return i0, i1, g, f

    @numba.njit(cache=True, nogil=True, parallel=True, fastmath={"contract"})
    def upsample_peak(peak, out):  # pragma: no cover - compiled
        """``out[Y, X]``: ``peak`` (h, w) bilinearly upsampled to ``out``'s (H, W), clamped to
        [0, 1], as 0-255 (``uint8(v * 255 + 0.5)``). The interpolation is torch's, a pass
        along the width per source row then one along the height, each a fused multiply-add
        onto the second product."""
        height, width = out.shape
        r0, r1, gy, fy = bilinear_taps(height, peak.shape[0])
        x0, x1, gx, fx = bilinear_taps(width, peak.shape[1])
        for Y in numba.prange(height):
            ra, rb, wy0, wy1 = r0[Y], r1[Y], gy[Y], fy[Y]
            for X in range(width):
                ca, cb, wx0, wx1 = x0[X], x1[X], gx[X], fx[X]
                upper = peak[ra, ca] * wx0 + peak[ra, cb] * wx1
                lower = peak[rb, ca] * wx0 + peak[rb, cb] * wx1
                v = min(max(upper * wy0 + lower * wy1, np.float32(0.0)), np.float32(1.0))
                out[Y, X] = np.uint8(v * np.float32(255.0) + np.float32(0.5))


def upsample_numba(
    y: np.ndarray, peak: np.ndarray, rows: tuple[np.ndarray, ...], cols: tuple[np.ndarray, ...], height: int, width: int,
    lut: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W) int32`` slots, or ``lut[slot]`` with ``lut`` ((C,) int32, e.g. slot -> track
    id), and which slots it holds ((C,) bool); ``rows`` and ``cols`` are the taps (i0, i1, f,
    1 - f) of :func:`services.tracker.propagation._linear_taps`, as numpy arrays."""
    r0, r1, fy, gy = rows
    x0, x1, fx, gx = cols
    row_start = np.searchsorted(r0, np.arange(y.shape[0] + 1)).astype(np.int64)
    col_start = np.searchsorted(x0, np.arange(y.shape[1] + 1)).astype(np.int64)
    if lut is None:
        lut = np.arange(y.shape[2], dtype=np.int32)
    out = np.empty((height, width), np.int32)
    seen = np.zeros((y.shape[0], y.shape[2]), np.uint8)
    upsample_cells(y, peak, r0, r1, fy, gy, row_start, x0, x1, fx, gx, col_start, np.ascontiguousarray(lut, np.int32), out, seen)
    return out, seen.any(axis=0)
