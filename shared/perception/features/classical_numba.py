"""The per-pixel passes of :mod:`shared.perception.features.classical` as numba kernels.

The numpy backend makes a dozen whole-image passes (CIELAB, gradients, orientation bins,
patch sums, the depth statistics), 10 ms at Replica's 1200x680 resized to 425x240, a fifth of
the tracker's frame. Here two kernels do the per-pixel work and leave patch sums (CIELAB
and its square, the two soft orientation histograms, gradient energy, the depth sums), and
the per-patch formulas stay in numpy on those small arrays. Every sum is taken in numpy's
order and precision (a row of a patch, then its rows; the histograms in float64 in pixel
order, as ``np.bincount``), and the one transcendental per pixel, ``arctan2``, is numpy's own,
so the features equal the numpy backend's bit for bit (tested).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np

try:
    import numba
except ImportError:  # the numpy backend does the same, slower
    numba = None


def available() -> bool:
    return numba is not None


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def lab_and_gradient(rgb, lin_lut, m, f_lut, f_max_index, lab, gx, gy):  # pragma: no cover - compiled
        """``lab`` (3, H, W): CIELAB of ``rgb`` as ``classical._lab`` computes it (``m``: the
        RGB -> XYZ / white rows times the table scale); ``gx``, ``gy``: central differences
        of L, half the neighbour difference, edges replicated."""
        height, width = rgb.shape[0], rgb.shape[1]
        half = np.float32(0.5)
        for y in range(height):
            for x in range(width):
                r = lin_lut[rgb[y, x, 0]]
                g = lin_lut[rgb[y, x, 1]]
                b = lin_lut[rgb[y, x, 2]]
                fx = f_lut[min(np.int32(m[0, 0] * r + m[0, 1] * g + m[0, 2] * b + half), f_max_index)]
                fy = f_lut[min(np.int32(m[1, 0] * r + m[1, 1] * g + m[1, 2] * b + half), f_max_index)]
                fz = f_lut[min(np.int32(m[2, 0] * r + m[2, 1] * g + m[2, 2] * b + half), f_max_index)]
                lab[0, y, x] = np.float32(116.0) * fy - np.float32(16.0)
                lab[1, y, x] = np.float32(500.0) * (fx - fy)
                lab[2, y, x] = np.float32(200.0) * (fy - fz)
        light = lab[0]
        for y in range(height):
            up, down = max(y - 1, 0), min(y + 1, height - 1)
            for x in range(width):
                left, right = max(x - 1, 0), min(x + 1, width - 1)
                gx[y, x] = (light[y, right] - light[y, left]) * half
                gy[y, x] = (light[down, x] - light[up, x]) * half

    @numba.njit(cache=True, nogil=True)
    def patch_sums(lab, gx, gy, theta, p, n_bins, bin_scale, colour, hist0, hist1, energy):  # pragma: no cover - compiled
        """Per patch of side ``p``: sums of each CIELAB channel and of its square
        (``colour`` (6, h, w)), the soft orientation histogram's two halves ((h, w, bins)
        float64, in pixel order) and the summed gradient magnitude (``energy``)."""
        n_ch, h, w = colour.shape[0] // 2, colour.shape[1], colour.shape[2]
        pi = np.float32(np.pi)
        half = np.float32(0.5)
        one = np.float32(1.0)
        for i in range(h):
            for j in range(w):
                for c in range(n_ch):
                    s = np.float32(0.0)
                    s2 = np.float32(0.0)
                    for yy in range(p):
                        rs = np.float32(0.0)
                        rs2 = np.float32(0.0)
                        for xx in range(p):
                            v = lab[c, i * p + yy, j * p + xx]
                            rs += v
                            rs2 += v * v
                        s += rs
                        s2 += rs2
                    colour[c, i, j] = s
                    colour[n_ch + c, i, j] = s2
                e = np.float32(0.0)
                for yy in range(p):
                    y = i * p + yy
                    re = np.float32(0.0)
                    for xx in range(p):
                        x = j * p + xx
                        a, b = gx[y, x], gy[y, x]
                        mag = np.sqrt(a * a + b * b)
                        re += mag
                        t = theta[y, x]
                        if t < 0:
                            t = t + pi
                        pos = t * bin_scale - half
                        lower = np.floor(pos)
                        frac = pos - lower
                        b0 = np.int64(lower)
                        if b0 < 0:
                            b0 = n_bins - 1
                        elif b0 >= n_bins:
                            b0 -= n_bins
                        b1 = 0 if b0 == n_bins - 1 else b0 + 1
                        hist0[i, j, b0] += np.float64(mag * (one - frac))
                        hist1[i, j, b1] += np.float64(mag * frac)
                    e += re
                energy[i, j] = e

    @numba.njit(cache=True, nogil=True)
    def depth_sums(depth, p, out):  # pragma: no cover - compiled
        """Per patch: valid readings, their sum and sum of squares, pixels whose central
        difference has five valid readings, and the sums of the depth gradient over depth
        there (x, y) (``out`` (6, h, w)), as ``classical._depth`` forms them."""
        height, width = depth.shape
        h, w = out.shape[1], out.shape[2]
        half = np.float32(0.5)
        floor = np.float32(1e-6)
        one = np.float32(1.0)
        zero = np.float32(0.0)
        for i in range(h):
            for j in range(w):
                s = np.zeros(6, np.float32)
                for yy in range(p):
                    y = i * p + yy
                    up, down = max(y - 1, 0), min(y + 1, height - 1)
                    rs = np.zeros(6, np.float32)
                    for xx in range(p):
                        x = j * p + xx
                        left, right = max(x - 1, 0), min(x + 1, width - 1)
                        d = depth[y, x]
                        ok = d > 0 and np.isfinite(d)
                        z = d if ok else zero
                        vf = one if ok else zero
                        rs[0] += vf
                        rs[1] += z
                        rs[2] += z * z
                        gv = vf
                        for q in (depth[y, right], depth[y, left], depth[down, x], depth[up, x]):
                            gv = gv * (one if (q > 0 and np.isfinite(q)) else zero)
                        zr = depth[y, right] if depth[y, right] > 0 and np.isfinite(depth[y, right]) else zero
                        zl = depth[y, left] if depth[y, left] > 0 and np.isfinite(depth[y, left]) else zero
                        zd = depth[down, x] if depth[down, x] > 0 and np.isfinite(depth[down, x]) else zero
                        zu = depth[up, x] if depth[up, x] > 0 and np.isfinite(depth[up, x]) else zero
                        inv = one / max(z, floor)
                        rs[3] += gv
                        rs[4] += (zr - zl) * half * inv * gv
                        rs[5] += (zd - zu) * half * inv * gv
                    for k in range(6):
                        s[k] += rs[k]
                for k in range(6):
                    out[k, i, j] = s[k]


def pixel_passes(
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
    depth: Annotated[np.ndarray, "(H, W) float32 m"] | None,
    p: int,
    n_bins: int,
    tables: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> tuple[np.ndarray, ...]:
    """Patch sums for :meth:`ClassicalFeatures.features`: CIELAB and its square (6, h, w),
    the two histogram halves (h, w, n_bins) float64, summed gradient magnitude (h, w), and
    the depth sums (6, h, w) or None. ``tables``: linearisation LUT, scaled RGB -> XYZ rows,
    the cube-root LUT."""
    lin_lut, m, f_lut = tables
    height, width = rgb.shape[:2]
    h, w = height // p, width // p
    lab = np.empty((3, height, width), np.float32)
    gx = np.empty((height, width), np.float32)
    gy = np.empty((height, width), np.float32)
    lab_and_gradient(rgb, lin_lut, m, f_lut, np.int32(len(f_lut) - 1), lab, gx, gy)
    theta = np.arctan2(gy, gx)  # numpy's arctan2, as the numpy backend's
    colour = np.empty((6, h, w), np.float32)
    hist0 = np.zeros((h, w, n_bins), np.float64)
    hist1 = np.zeros((h, w, n_bins), np.float64)
    energy = np.empty((h, w), np.float32)
    patch_sums(lab, gx, gy, theta, p, n_bins, np.float32(n_bins / np.pi), colour, hist0, hist1, energy)
    sums = None
    if depth is not None:
        sums = np.empty((6, h, w), np.float32)
        depth_sums(np.ascontiguousarray(depth, np.float32), p, sums)
    return colour, hist0, hist1, energy, sums
