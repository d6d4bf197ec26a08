"""Numba kernels of the renderer and of the ground truth's visibility test (CPU, one thread each).

Each kernel does what a numpy reference in this package does, to the same bytes (tested in
tests/shared/synth/test_synth_kernels.py), in one pass over the pixels or points instead of
a dozen whole-array temporaries:

- :func:`pinhole_rays`, :func:`shade_hits` and :func:`compose` are
  :meth:`shared.synth.render.Renderer.render_numpy` (textures' SOLID and NOISE materials and the
  grime on every surface; the other patterns stay in numpy, on the few pixels that show them);
- :func:`value_noise_kernel`, :func:`tiles` and :func:`checker` are
  :func:`shared.synth.textures.value_noise_numpy` and those patterns of
  :func:`shared.synth.textures.apply_patterns`;
- :func:`observed_points` is :func:`shared.synth.groundtruth.observed_in` over the points of
  the objects a frame shows;
- :func:`grid_points` and :func:`in_box` find the probes near each part for
  ``shared.synth.groundtruth._in_air`` (which then tests them with numpy, as before).

Bit-identity rests on doing the same IEEE operations in the same order and type: float32
arithmetic stays float32 (every constant is an ``np.float32``; numba would widen a float32
times a Python number to float64), and numba does not contract a multiply and an add into an
FMA without fastmath. The one exception is the visibility test's float64 projection, which
numpy does with a BLAS matrix product whose rounding depends on the CPU's kernel (FMA or not):
the kernel decides every point whose outcome no such rounding can change and hands the rare
rest (within 1e-6 px of a pixel edge, 1e-9 m of a depth threshold) back to numpy.

Kernels release the GIL (``nogil``) so the pipeline's frame threads overlap; none is parallel
on its own, as CI's two cores are shared.
"""

from __future__ import annotations

import numpy as np

from shared.synth.primitives import Pattern

try:
    import numba
except ImportError:  # the numpy references do the same, slower
    numba = None

ENABLED = numba is not None
"""Whether the renderer and the ground truth use the kernels (tests switch it off to get the
numpy references)."""
NOISE_PATTERN = int(Pattern.NOISE)
"""As a plain int, which the kernels take as a constant."""
PIXEL_MARGIN = 1e-6
"""Projections this close (pixels) to a pixel edge go back to numpy (see the module doc)."""
DEPTH_MARGIN = 1e-9
"""Depths this close (metres) to a visibility threshold go back to numpy."""


if numba is not None:

    @numba.njit(cache=True, nogil=True, inline="always")
    def _noise(x, y, z, lattice):  # pragma: no cover - compiled
        """One point of :func:`shared.synth.textures.value_noise` (float32 in, float32 out)."""
        fx, fy, fz = np.floor(x), np.floor(y), np.floor(z)
        ax, ay, az = x - fx, y - fy, z - fz
        three, two = np.float32(3.0), np.float32(2.0)
        ux = ax * ax * (three - two * ax)
        uy = ay * ay * (three - two * ay)
        uz = az * az * (three - two * az)
        ix, iy, iz = np.int32(fx) & 63, np.int32(fy) & 63, np.int32(fz) & 63
        x0, y0, z0 = ix << 12, iy << 6, iz
        x1, y1, z1 = ((ix + 1) & 63) << 12, ((iy + 1) & 63) << 6, (iz + 1) & 63
        a = lattice[x0 + y0 + z0]
        c00 = a + (lattice[x1 + y0 + z0] - a) * ux
        a = lattice[x0 + y1 + z0]
        c10 = a + (lattice[x1 + y1 + z0] - a) * ux
        a = lattice[x0 + y0 + z1]
        c01 = a + (lattice[x1 + y0 + z1] - a) * ux
        a = lattice[x0 + y1 + z1]
        c11 = a + (lattice[x1 + y1 + z1] - a) * ux
        c0 = c00 + (c10 - c00) * uy
        c1 = c01 + (c11 - c01) * uy
        return c0 + (c1 - c0) * uz

    @numba.njit(cache=True, nogil=True)
    def value_noise_kernel(p, lattice, out):  # pragma: no cover - compiled
        """``out[i]``: value noise at ``p[i]`` ((N, 3) float32) on the flat 64^3 ``lattice``."""
        for i in range(p.shape[0]):
            out[i] = _noise(p[i, 0], p[i, 1], p[i, 2], lattice)

    @numba.njit(cache=True, nogil=True)
    def pinhole_rays(rot, origin, xc, yc, rays):  # pragma: no cover - compiled
        """``rays`` (H, W, 6) float32: ``origin`` then ``rot @ (xc[u], yc[v], 1)``, summed as
        ``Renderer.cast`` sums it."""
        h, w = yc.shape[0], xc.shape[0]
        for v in range(h):
            for u in range(w):
                for k in range(3):
                    rays[v, u, k] = origin[k]
                    rays[v, u, 3 + k] = rot[k, 0] * xc[u] + rot[k, 1] * yc[v] + rot[k, 2]

    @numba.njit(cache=True, nogil=True)
    def shade_hits(t_hit, geom, prim, normals, rays, geom_obj, tri_offset, tri_part,  # pragma: no cover - compiled
                   suns, sun_weights, ambient, bounce, lamps, lamp_strength, falloff2,
                   rot, trans, color, color2, pattern, scale, lattice, textures,
                   obj, part, local, light, base, shade, pat):
        """Hit pixels in raster order (flat (H*W, ...) inputs): object id, part, part-local
        point, light, the albedo before patterns and grime shade (SOLID and NOISE done; the
        other patterns are filled in by numpy), and the part's pattern. Returns the hit count."""
        zero, one = np.float32(0.0), np.float32(1.0)
        nine, spread = np.float32(9.0), np.float32(3.7)
        two, seventeen, half, third = np.float32(2.0), np.float32(17.0), np.float32(0.5), np.float32(1.5)
        grime0, grime1 = np.float32(0.93), np.float32(0.14)
        eps = np.float32(1e-12)
        o0, o1, o2 = rays[0, 0], rays[0, 1], rays[0, 2]
        n = 0
        for i in range(t_hit.shape[0]):
            z = t_hit[i]
            if not np.isfinite(z):
                continue
            g = np.int64(geom[i])
            obj[n] = geom_obj[g]
            pi = tri_part[tri_offset[g] + np.int64(prim[i])]
            part[n] = pi
            d0, d1, d2 = rays[i, 3], rays[i, 4], rays[i, 5]
            p0, p1, p2 = o0 + d0 * z, o1 + d1 * z, o2 + d2 * z
            n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
            flip = -one if n0 * d0 + n1 * d1 + n2 * d2 > zero else one
            n0, n1, n2 = n0 * flip, n1 * flip, n2 * flip
            lit = ambient
            for s in range(suns.shape[0]):
                c = n0 * suns[s, 0] + n1 * suns[s, 1] + n2 * suns[s, 2]
                lit += sun_weights[s] * (c if c >= zero else zero)
            c = -n2
            lit += bounce * (c if c >= zero else zero)
            for m in range(lamps.shape[0]):
                t0, t1, t2 = lamps[m, 0] - p0, lamps[m, 1] - p1, lamps[m, 2] - p2
                dist2 = t0 * t0 + t1 * t1 + t2 * t2
                dist2 = dist2 if dist2 >= eps else eps
                c = n0 * t0 + n1 * t1 + n2 * t2
                lam = (c if c >= zero else zero) / np.sqrt(dist2)
                lit += lamp_strength * lam / (one + dist2 / falloff2)
            light[n] = lit
            q0 = trans[pi, 0]
            q0 += rot[pi, 0, 0] * p0
            q0 += rot[pi, 0, 1] * p1
            q0 += rot[pi, 0, 2] * p2
            q1 = trans[pi, 1]
            q1 += rot[pi, 1, 0] * p0
            q1 += rot[pi, 1, 1] * p1
            q1 += rot[pi, 1, 2] * p2
            q2 = trans[pi, 2]
            q2 += rot[pi, 2, 0] * p0
            q2 += rot[pi, 2, 1] * p1
            q2 += rot[pi, 2, 2] * p2
            local[n, 0], local[n, 1], local[n, 2] = q0, q1, q2
            kind = pattern[pi]
            pat[n] = kind
            if not textures:
                for k in range(3):
                    base[n, k] = color[pi, k]
                n += 1
                continue
            sc = scale[pi]
            noisy = kind == NOISE_PATTERN
            ns = sc if noisy else nine
            off = zero if noisy else np.float32(pi) * spread
            g0, g1, g2 = q0 * ns + off, q1 * ns + off, q2 * ns + off
            t = _noise(g0, g1, g2, lattice)
            if noisy and sc >= np.float32(20.0):
                fine = _noise(g0 * two + seventeen, g1 * two + seventeen, g2 * two + seventeen, lattice)
                t = (t + half * fine) / third
            mix = t if noisy else zero
            for k in range(3):
                c1 = color[pi, k]
                base[n, k] = c1 + (color2[pi, k] - c1) * mix
            shade[n] = one if noisy else grime0 + grime1 * t
            n += 1
        return n

    @numba.njit(cache=True, nogil=True)
    def compose(t_hit, base, shade, light, obj, textures, noise, dy, dx, noise_std, depth_max, clip_depth,
                rgb, inst, depth):  # pragma: no cover - compiled
        """The frame from :func:`shade_hits`' outputs (``base`` with patterns filled in):
        ``rgb`` (H, W, 3) uint8 with the noise window at (dy, dx) (``noise_std`` 0: none),
        ``inst`` (H, W) int32 and ``depth`` (H, W) float32 (z on a hit, else 0; with
        ``clip_depth`` also 0 beyond ``depth_max``)."""
        h, w = inst.shape
        zero, one, full = np.float32(0.0), np.float32(1.0), np.float32(255.0)
        with_noise = noise_std != zero
        n = 0
        c = np.empty(3, np.float32)
        for v in range(h):
            for u in range(w):
                z = t_hit[v, u]
                if np.isfinite(z):
                    lit = light[n] * full
                    for k in range(3):
                        a = base[n, k]
                        if textures:
                            a = a * shade[n]
                            a = one if a > one else (zero if a < zero else a)
                        c[k] = a * lit
                    inst[v, u] = obj[n]
                    n += 1
                    d = z
                    if clip_depth and not (d > zero and d <= depth_max):
                        d = zero
                    depth[v, u] = d
                else:
                    c[0], c[1], c[2] = zero, zero, zero
                    inst[v, u] = -1
                    depth[v, u] = zero
                for k in range(3):
                    a = c[k]
                    if with_noise:
                        a += noise[dy + v, dx + u, k] * noise_std
                    a = np.rint(a)
                    rgb[v, u, k] = np.uint8(full if a > full else (zero if a < zero else a))

    @numba.njit(cache=True, nogil=True)
    def _outside_view(lo, hi, rot, trans, fx, fy, cx, cy, w, h):  # pragma: no cover - compiled
        """Whether every point of the box ``lo``-``hi`` is behind z = 0.04 or projects more than
        a pixel beyond one image edge (each test is linear, so its corners decide it)."""
        behind = left = right = above = below = True
        for corner in range(8):
            p0 = (hi[0] if corner & 1 else lo[0]) - trans[0]
            p1 = (hi[1] if corner & 2 else lo[1]) - trans[1]
            p2 = (hi[2] if corner & 4 else lo[2]) - trans[2]
            x = p0 * rot[0, 0] + p1 * rot[1, 0] + p2 * rot[2, 0]
            y = p0 * rot[0, 1] + p1 * rot[1, 1] + p2 * rot[2, 1]
            z = p0 * rot[0, 2] + p1 * rot[1, 2] + p2 * rot[2, 2]
            behind &= z < 0.04
            # x * fx / z + cx + 0.5 < -1 and > w + 1 (the same for y), times z > 0.
            left &= x * fx + (cx + 1.5) * z < 0
            right &= x * fx + (cx - 0.5 - w) * z > 0
            above &= y * fy + (cy + 1.5) * z < 0
            below &= y * fy + (cy - 0.5 - h) * z > 0
        return behind or left or right or above or below

    @numba.njit(cache=True, nogil=True)
    def observed_points(points, order, object_chunks, chunk_start, lo, hi, shown, depth, rot, trans,  # pragma: no cover - compiled
                        fx, fy, cx, cy, tol, seen, unsure):
        """:func:`shared.synth.groundtruth.observed_in` over the points of the objects in
        ``shown`` (chunked as :class:`shared.synth.groundtruth.PointChunks`): the indices it
        sees go to ``seen``, those too close to call (see the module doc) to ``unsure``.
        Returns both counts. A chunk whose box lies wholly behind z = 0.04 or a pixel beyond an
        image edge is skipped: observed_in drops all its points whatever the rounding."""
        h, w = depth.shape
        n_seen, n_unsure = 0, 0
        rel = np.float32(0.01)
        for o in shown:
            for c in range(object_chunks[o], object_chunks[o + 1]):
                if _outside_view(lo[c], hi[c], rot, trans, fx, fy, cx, cy, w, h):
                    continue
                for j in range(chunk_start[c], chunk_start[c + 1]):
                    idx = order[j]
                    q0 = np.float64(points[idx, 0]) - trans[0]
                    q1 = np.float64(points[idx, 1]) - trans[1]
                    q2 = np.float64(points[idx, 2]) - trans[2]
                    z = q0 * rot[0, 2] + q1 * rot[1, 2] + q2 * rot[2, 2]
                    if abs(z - 0.05) <= DEPTH_MARGIN:
                        unsure[n_unsure] = idx
                        n_unsure += 1
                        continue
                    if not z > 0.05:
                        continue
                    x = (q0 * rot[0, 0] + q1 * rot[1, 0] + q2 * rot[2, 0]) / z * fx + cx + 0.5
                    y = (q0 * rot[0, 1] + q1 * rot[1, 1] + q2 * rot[2, 1]) / z * fy + cy + 0.5
                    # Well outside the image whatever the rounding (and safe to convert below).
                    if not (x > -1.0 and x < w + 1.0 and y > -1.0 and y < h + 1.0):
                        continue
                    fu, fv = np.floor(x), np.floor(y)
                    if x - fu < PIXEL_MARGIN or fu + 1.0 - x < PIXEL_MARGIN or y - fv < PIXEL_MARGIN or fv + 1.0 - y < PIXEL_MARGIN:
                        unsure[n_unsure] = idx
                        n_unsure += 1
                        continue
                    u, v = np.int64(fu), np.int64(fv)
                    if u < 0 or u >= w or v < 0 or v >= h:
                        continue
                    d = depth[v, u]
                    if not d > 0:
                        continue
                    limit = np.float64(tol + rel * d)
                    gap = abs(z - np.float64(d))
                    if abs(gap - limit) <= DEPTH_MARGIN:
                        unsure[n_unsure] = idx
                        n_unsure += 1
                    elif gap < limit:
                        seen[n_seen] = idx
                        n_seen += 1
        return n_seen, n_unsure

    @numba.njit(cache=True, nogil=True, inline="always")
    def _cell(v, origin, size, n):  # pragma: no cover - compiled
        """The grid cell (0 to n - 1) of coordinate ``v``; monotone in ``v``."""
        c = np.floor((v - origin) / size)
        return 0 if c < 0 else (n - 1 if c > n - 1 else np.int64(c))

    @numba.njit(cache=True, nogil=True)
    def grid_points(points, origin, size, nx, ny, cell_start, members):  # pragma: no cover - compiled
        """Bucket ``points`` (N, 3) by an ``nx`` x ``ny`` grid of ``size`` cells in xy from
        ``origin``: cell k's point indices, increasing, are ``members[cell_start[k]:cell_start[k + 1]]``."""
        n = points.shape[0]
        cells = np.empty(n, np.int64)
        cell_start[:] = 0
        for i in range(n):
            k = _cell(points[i, 0], origin[0], size, nx) * ny + _cell(points[i, 1], origin[1], size, ny)
            cells[i] = k
            cell_start[k + 1] += 1
        for k in range(nx * ny):
            cell_start[k + 1] += cell_start[k]
        fill = cell_start[:-1].copy()
        for i in range(n):
            members[fill[cells[i]]] = i
            fill[cells[i]] += 1

    @numba.njit(cache=True, nogil=True)
    def in_box(points, cell_start, members, origin, size, nx, ny, lo, hi, out):  # pragma: no cover - compiled
        """``out[:count]``: the indices of the ``points`` in the closed box ``lo``-``hi`` (as
        ``np.all((p >= lo) & (p <= hi), axis=1)`` picks them), found through the grid of
        :func:`grid_points`, in no particular order. Returns the count."""
        count = 0
        for ix in range(_cell(lo[0], origin[0], size, nx), _cell(hi[0], origin[0], size, nx) + 1):
            for iy in range(_cell(lo[1], origin[1], size, ny), _cell(hi[1], origin[1], size, ny) + 1):
                k = ix * ny + iy
                for j in range(cell_start[k], cell_start[k + 1]):
                    idx = members[j]
                    inside = True
                    for d in range(3):
                        c = points[idx, d]
                        if not (c >= lo[d] and c <= hi[d]):
                            inside = False
                            break
                    if inside:
                        out[count] = idx
                        count += 1
        return count

    @numba.njit(cache=True, nogil=True, inline="always")
    def _grout(g, c, width):  # pragma: no cover - compiled
        """Whether a tile coordinate lies in the grout (numpy's float64 ``frac``, as there)."""
        frac = np.float64(g) - np.float64(c)
        rest = 1 - frac
        return (frac if frac <= rest else rest) < width

    @numba.njit(cache=True, nogil=True)
    def tiles(q, sc, a1, a2, lattice, out):  # pragma: no cover - compiled
        """The TILES pattern of :func:`shared.synth.textures.apply_patterns` at ``q`` (N, 3)."""
        width = 0.035
        base, spread = np.float32(0.92), np.float32(0.16)
        for i in range(q.shape[0]):
            s = sc[i]
            g0, g1, g2 = q[i, 0] * s, q[i, 1] * s, q[i, 2] * s
            c0, c1, c2 = np.int64(np.floor(g0)), np.int64(np.floor(g1)), np.int64(np.floor(g2))
            if _grout(g0, c0, width) or _grout(g1, c1, width):
                for k in range(3):
                    out[i, k] = a2[i, k]
            else:
                tint = base + spread * lattice[((c0 & 63) << 12) + ((c1 & 63) << 6) + (c2 & 63)]
                for k in range(3):
                    out[i, k] = a1[i, k] * tint

    @numba.njit(cache=True, nogil=True)
    def checker(q, sc, a1, a2, out):  # pragma: no cover - compiled
        """The CHECKER pattern of :func:`shared.synth.textures.apply_patterns` at ``q`` (N, 3)."""
        nudge = np.float32(1e-3)
        for i in range(q.shape[0]):
            s = sc[i]
            cells = np.int64(0)
            for k in range(3):
                cells += np.int64(np.floor(q[i, k] * s + nudge))
            t = np.float32(cells % 2)
            for k in range(3):
                out[i, k] = a1[i, k] + (a2[i, k] - a1[i, k]) * t
