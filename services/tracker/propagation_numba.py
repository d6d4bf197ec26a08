"""The numba kernel of :func:`services.tracker.propagation.propagate_labels` on the CPU.

Eq. 1 patch by patch, without the torch path's detour: for each query patch p it walks the
(2R+1)^2 window around p in every reference (clipped to the map), keeps the k best (q, r) by
cosine in a small sorted list, and mixes their label distributions with the softmax weights.
No (rows, cols, (2R+1) * cols) similarity tensor, no ``masked_fill_`` of the out-of-window
columns, no ``topk`` over a thousand candidates per patch: at 1200x680 with classical features
(48 x 85 grid, D = 20, R = 12, k = 5, 7 references) the torch path spent its time in ``bmm``
(37%), ``topk`` (33%) and ``masked_fill_`` (18%), and this kernel does half the dot products
(the window instead of 2R + 1 full rows).

Work goes by pairs of a query row and a reference row within R of it: their (2R+1) x w band
of cosines is computed channel by channel over whole rows (contiguous loops that vectorise;
references stored (h, D, w) and zero-padded by R columns on both sides), then merged into each
patch's list. Each cosine is summed over the channels in order with fused multiply-adds, as
MKL's sgemm does, so it equals the torch path's ``bmm`` bit for bit (checked on the tracker's
features); softmax and mix differ from torch's in the last bits. The one real difference is
between exactly equal cosines at the k-th place (identical features, e.g. flat synthetic
surfaces): the kernel keeps the candidate met first (references in order, then rows, then
columns), torch's ``topk`` whichever its heap leaves.

The global top-k is taken directly over all references; the torch path's per-reference top-k
followed by the top-k of their union selects the same set, since the global top-k is contained
in the per-reference ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import numpy as np

try:
    import numba

    if numba.config.THREADING_LAYER == "default":
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
except ImportError:  # the torch path does the same, slower
    numba = None


ROW_BLOCK = 4
"""Query rows per parallel task: they share each reference row while it is in cache (at D = 384
a reference row is 170 kB, and the 8 x 25 rows of one query row's windows 33 MB)."""

if numba is not None:

    @numba.njit(cache=True, nogil=True, fastmath={"contract"})
    def _row_sims(q_row, ref_row, span, sims):  # pragma: no cover - compiled
        """``sims[j, x] = q_row[:, x] . ref_row[:, x + j]`` for the (D, w) query row and the
        (D, w + 2R) padded reference row: channel by channel over whole rows, long contiguous
        loops that vectorise, each sum taken over the channels in order with fused
        multiply-adds, as MKL's sgemm does (bit-equal to the torch path's ``bmm``), four
        channels per pass so ``sims`` is loaded and stored a quarter as often."""
        dim, w = q_row.shape
        sims[:] = 0
        d = 0
        while d + 4 <= dim:
            q0, q1, q2, q3 = q_row[d], q_row[d + 1], q_row[d + 2], q_row[d + 3]
            r0, r1, r2, r3 = ref_row[d], ref_row[d + 1], ref_row[d + 2], ref_row[d + 3]
            for j in range(span):
                s_j = sims[j]
                for x in range(w):
                    s_j[x] = (((s_j[x] + q0[x] * r0[x + j]) + q1[x] * r1[x + j]) + q2[x] * r2[x + j]) + q3[x] * r3[x + j]
            d += 4
        while d < dim:
            q0, r0 = q_row[d], ref_row[d]
            for j in range(span):
                s_j = sims[j]
                for x in range(w):
                    s_j[x] += q0[x] * r0[x + j]
            d += 1

    @numba.njit(cache=True, nogil=True)
    def _select(sims, radius, r, yy, row_max, best, src):  # pragma: no cover - compiled
        """Merge the candidates of reference ``r``, row ``yy`` into each patch's sorted k best
        (``best`` (w, k) descending, -inf where empty; ``src`` (w, k, 3) their reference, row,
        column). Ties keep the candidate met first."""
        span, w = sims.shape
        k = best.shape[1]
        # A vectorised pass finds the patches where some candidate beats the k-th best
        # (padding columns count 0: at worst a scan below that inserts nothing).
        row_max[:] = -np.inf
        for j in range(span):
            s_j = sims[j]
            for x in range(w):
                row_max[x] = max(row_max[x], s_j[x])
        for x in range(w):
            kth = best[x, k - 1]
            if not row_max[x] > kth:
                continue
            b = best[x]
            for j in range(max(0, radius - x), min(span, w + radius - x)):
                s = sims[j, x]
                if s > kth:
                    i = k - 1
                    while i > 0 and b[i - 1] < s:
                        b[i] = b[i - 1]
                        src[x, i, 0] = src[x, i - 1, 0]
                        src[x, i, 1] = src[x, i - 1, 1]
                        src[x, i, 2] = src[x, i - 1, 2]
                        i -= 1
                    b[i] = s
                    src[x, i, 0] = r
                    src[x, i, 1] = yy
                    src[x, i, 2] = x - radius + j
                    kth = b[k - 1]

    @numba.njit(cache=True, nogil=True, fastmath={"contract"})
    def _mix(best, src, labels, temperature, weights, out_row):  # pragma: no cover - compiled
        """Softmax of ``best / temperature`` (the maximum subtracted and the sum's reciprocal
        multiplied, as torch does; empty places weigh 0), then the weighted sum of the
        chosen distributions, best first, into ``out_row`` (w, C)."""
        w, k = best.shape
        n_slots = labels.shape[3]
        temp = np.float32(temperature)
        for x in range(w):
            top = best[x, 0] / temp
            total = np.float32(0.0)
            for i in range(k):
                e = np.float32(np.exp(best[x, i] / temp - top)) if best[x, i] > -np.inf else np.float32(0.0)
                weights[i] = e
                total += e
            out_row[x] = 0
            if not total > 0:  # NaN cosines only: no weight anywhere (torch's nan_to_num)
                continue
            scale = np.float32(1.0) / total
            for i in range(k):
                if weights[i] > 0:
                    a = weights[i] * scale
                    lab = labels[src[x, i, 0], src[x, i, 1], src[x, i, 2]]
                    for c in range(n_slots):
                        out_row[x, c] += a * lab[c]

    @numba.njit(cache=True, nogil=True, parallel=True)
    def window_topk_mix(query_t, refs_p, labels, radius, k, temperature, out):  # pragma: no cover - compiled
        """``out[y, x]``: eq. 1 at patch (y, x) of ``query_t`` (h, D, w), over the references
        ``refs_p`` (n, h, D, w + 2R), columns zero-padded by R on both sides, with
        distributions ``labels`` (n, h, w, C)."""
        h, _, w = query_t.shape
        n_refs = refs_p.shape[0]
        span = 2 * radius + 1
        n_blocks = (h + ROW_BLOCK - 1) // ROW_BLOCK
        for blk in numba.prange(n_blocks):
            y0, y1 = blk * ROW_BLOCK, min(h, (blk + 1) * ROW_BLOCK)
            sims = np.empty((span, w), np.float32)  # sims[j, x]: patch x against column x - R + j
            row_max = np.empty(w, np.float32)
            best = np.full((y1 - y0, w, k), -np.inf, np.float32)
            src = np.zeros((y1 - y0, w, k, 3), np.int64)
            weights = np.empty(k, np.float32)
            for r in range(n_refs):
                for yy in range(max(0, y0 - radius), min(h, y1 + radius)):
                    for y in range(max(y0, yy - radius), min(y1, yy + radius + 1)):
                        _row_sims(query_t[y], refs_p[r, yy], span, sims)
                        _select(sims, radius, r, yy, row_max, best[y - y0], src[y - y0])
            for y in range(y0, y1):
                _mix(best[y - y0], src[y - y0], labels, temperature, weights, out[y])


def propagate_numba(
    query: Annotated[np.ndarray, "(h, w, D) float32"],
    ref_feats: Sequence[Annotated[np.ndarray, "(h, w, D) float32"]],
    ref_labels: Sequence[Annotated[np.ndarray, "(h, w, C) float32"]],
    radius: int,
    topk: int,
    temperature: float,
) -> Annotated[np.ndarray, "(h, w, C) float32"]:
    """Eq. 1 over the references with :func:`window_topk_mix` (numba must be installed)."""
    if numba is None:
        raise RuntimeError("propagate_numba needs numba")
    h, w, dim = query.shape
    # The kernel's inner loops run along rows: make them the long side (the window is square).
    transpose = h > w
    if transpose:
        h, w = w, h
    n_refs = len(ref_feats)
    refs_p = np.zeros((n_refs, h, dim, w + 2 * radius), np.float32)
    labels = np.empty((n_refs, h, w, ref_labels[0].shape[-1]), np.float32)
    for i, (rf, ry) in enumerate(zip(ref_feats, ref_labels, strict=True)):
        refs_p[i, :, :, radius : radius + w] = (rf.transpose(1, 2, 0) if transpose else rf.transpose(0, 2, 1))
        labels[i] = ry.swapaxes(0, 1) if transpose else ry
    query_t = np.ascontiguousarray(query.transpose(1, 2, 0) if transpose else query.transpose(0, 2, 1), dtype=np.float32)
    out = np.empty((h, w, labels.shape[-1]), np.float32)
    window_topk_mix(query_t, refs_p, labels, int(radius), int(topk), float(temperature), out)
    return np.ascontiguousarray(out.swapaxes(0, 1)) if transpose else out
