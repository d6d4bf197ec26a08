"""Per-voxel source-track hypotheses: the confidence of eq. 6 and the vote of eq. 5 (III-C).

The vote is pixel-driven. Each pixel with a valid depth is back-projected to its surface point
and lands in the voxel nearest to that point, ``round(p / voxel_size)`` (Open3D places voxel
centres at integer multiples of the voxel size). Only that surface voxel votes, not the other
voxels of the truncation band along the ray: mesh vertices sit on the zero crossing and take
their hypotheses from the two voxels of the grid edge they lie on (:mod:`services.fusion.volume.mesh`),
so the surface voxels are the ones the segments read, and one voxel per pixel keeps the vote
O(pixels).

A voxel usually covers many pixels (about 50 for a 3 cm voxel seen from 2 m at 640x480), while
eq. 5 adds one TSDF observation weight per frame, and Open3D's ``integrate`` gives every
observation the weight w_TSDF = 1. So in each frame a voxel v hit by n_v valid pixels, n_{v,tau}
of them inside the mask of track tau, receives::

    l_{v,tau} += w_TSDF * gamma_t(tau) * n_{v,tau} / n_v        (w_TSDF = 1)

which is the voxel-driven update of eq. 5 (project the voxel, read the mask there) averaged over
the voxel's footprint in the image. This is a deviation from the paper (docs/method.md, F2),
which adds ``w_TSDF * gamma`` once per voxel that projects into the mask. Pixels outside every mask count in n_v, as a voxel that
projects outside all masks gets no update, so weight does not grow with image resolution or
with how close the camera is.

Slots (III-C): a track already in the voxel adds to its weight. Then the tracks new to the voxel,
strongest first (ties by lower track id), each take the first empty slot or, if all K are full,
replace the slot of lowest weight (the first such slot on ties); its track's weight is reported
as displaced so the segment updater can still count it. Should that lowest slot hold a newcomer
placed earlier in the same frame, the (weaker) newcomer is dropped instead, and its increment
reported as displaced: newcomers of one frame never push each other out, nor does the weaker of
two push out an established hypothesis that the stronger one spared.

Two implementations with the same rules and arithmetic (float64 increment rounded once to
float32, float32 accumulation): a numba kernel over Open3D's zero-copy numpy views for CPU, and
vectorised torch for any device (used on CUDA through DLPack, and on CPU when numba is missing).
Stored track codes are ``track_id + 1`` so that the zero-filled memory of a fresh block reads as
"empty slot".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated

import numpy as np

if TYPE_CHECKING:
    import torch

try:
    import numba
except ImportError:  # the torch path covers every device; numba only makes CPU fast
    numba = None

# what both vote backends' pixel pass reads of a frame
FrameDepth = Annotated[np.ndarray, "(H, W) float32 metres, 0 = invalid"]
FrameTracks = Annotated[np.ndarray, "(H, W) int32 source track per pixel, -1 = none"]

MAX_TRACKS_PER_VOXEL = 8
"""Distinct tracks one voxel can receive in a single frame; more are dropped and counted (a
3 cm voxel meeting more than a few mask borders in one image does not happen in practice)."""


def confidence(keyframe: bool, frames_since_keyframe: int, alpha_p: float, beta_p: float) -> float:
    """gamma_t(tau) of eq. 6: 1 for a keyframe mask, alpha_p / (1 + beta_p * Delta_t) for a
    propagated mask, Delta_t being the frames since tau's latest keyframe detection."""
    if keyframe:
        return 1.0
    if frames_since_keyframe < 0:
        raise ValueError(f"frames_since_keyframe must be >= 0, got {frames_since_keyframe}")
    return float(alpha_p / (1.0 + beta_p * frames_since_keyframe))


@dataclass
class FrameGeometry:
    """Everything the vote needs to map a pixel to a voxel of this frame's blocks.

    A pixel (u, v) with depth z has the camera point (xs[u] z, ys[v] z, z) and the voxel
    floor((R p + t) * inv_voxel + 0.5); both backends evaluate exactly these float64 products
    in the same order, so they pick the same voxel for every pixel.
    """

    R: Annotated[np.ndarray, "(3, 3) float64 world-from-camera rotation"]
    t: Annotated[np.ndarray, "(3,) float64 camera centre in world"]
    xs: Annotated[np.ndarray, "(W,) float64 (u - cx) / fx"]
    ys: Annotated[np.ndarray, "(H,) float64 (v - cy) / fy"]
    inv_voxel: float
    res: int
    shift: int
    """log2(res) when res is a power of two, else -1."""
    bmin: Annotated[np.ndarray, "(3,) int64 lowest block key of the frame"]
    bext: Annotated[np.ndarray, "(3,) int64 extent of the frame's block-key box"]
    lut: Annotated[np.ndarray, "(prod(bext),) int32 frame block index, -1 = not in frame"]


@dataclass
class VoteResult:
    pixels_voted: int = 0
    """Masked pixels with valid depth whose surface voxel is in the grid."""
    voxels_voted: int = 0
    """Voxels that received at least one track vote."""
    new_hypotheses: int = 0
    replaced: int = 0
    """New hypotheses that took a full voxel's lowest slot."""
    dropped: int = 0
    """Newcomers that found the lowest slot taken by a stronger newcomer of the same frame."""
    overflow: int = 0
    """(voxel, track) pairs dropped beyond MAX_TRACKS_PER_VOXEL (numba backend; torch keeps
    them all)."""
    displaced: dict[int, float] = field(default_factory=dict)
    """Track id -> weight it lost to slot replacement in this frame."""


def gamma_table(
    gamma: dict[int, float],
) -> tuple[Annotated[np.ndarray, "(T,) int64 sorted ids"], Annotated[np.ndarray, "(T,) float64"]]:
    ids = np.array(sorted(int(k) for k in gamma), dtype=np.int64)
    if len(ids) and (ids[0] < 0 or ids[-1] >= np.iinfo(np.int32).max):
        raise ValueError(f"track ids must be in [0, 2^31 - 2], got {ids[0]}..{ids[-1]}")
    vals = np.array([float(gamma[int(k)]) for k in ids], dtype=np.float64)
    if not np.all(np.isfinite(vals)) or np.any(vals < 0):
        raise ValueError("gamma values must be finite and >= 0")
    return ids, vals


def _unknown_tracks_error(track_ids: np.ndarray, gid: np.ndarray) -> ValueError:
    seen = np.unique(track_ids[track_ids >= 0])
    missing = seen[~np.isin(seen, gid)]
    return ValueError(f"gamma has no confidence for track ids {missing[:20].tolist()}")


def _sum_displaced(ids: np.ndarray, weights: np.ndarray) -> dict[int, float]:
    if len(ids) == 0:
        return {}
    uniq, inv = np.unique(ids, return_inverse=True)
    sums = np.bincount(inv, weights=weights.astype(np.float64), minlength=len(uniq))
    return {int(k): float(v) for k, v in zip(uniq, sums, strict=True)}


# --------------------------------------------------------------------------------------------
# numba (CPU)

if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _pixel_pass(
        depth,
        tracks,
        gid,
        R,
        t,
        xs,
        ys,
        inv_vs,
        res,
        shift,
        bmin,
        bext,
        lut,
        scratch,
        tv,
        tn,
        tk,
        ttr,
        tcnt,
    ):
        """Group the frame's pixels by surface voxel, counting valid pixels and per-track pixels.

        Touched voxel s (0 <= s < nt) is frame-local voxel tv[s], hit by tn[s] valid pixels, of
        which tcnt[s, q] belong to track index ttr[s, q] (q < tk[s]). ``scratch`` (frame-local
        voxel -> s) is all -1 and ``tn``, ``tk`` all 0 on entry; the caller resets the first nt
        entries afterwards (reusing the buffers saves allocating and faulting ~25 MB a frame).
        With a power-of-two block resolution (``shift`` >= 0) shifts and masks replace the
        integer divisions, which dominate otherwise.
        """
        H, W = depth.shape
        J = MAX_TRACKS_PER_VOXEL
        nt = 0
        voted = 0
        overflow = 0
        unknown = 0
        T = gid.shape[0]
        r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
        r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
        r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
        t0, t1, t2 = t[0], t[1], t[2]
        b0, b1, b2 = bmin[0], bmin[1], bmin[2]
        e0, e1, e2 = bext[0], bext[1], bext[2]
        mask = res - 1
        prev_loc = -1
        prev_s = 0
        prev_q = -1
        last_tid = -1
        last_c = -1
        for v in range(H):
            yv = ys[v]
            for u in range(W):
                d = depth[v, u]
                if not d > 0:
                    continue
                z = np.float64(d)
                x = xs[u] * z
                y = yv * z
                ix = np.int64(np.floor((r00 * x + r01 * y + r02 * z + t0) * inv_vs + 0.5))
                iy = np.int64(np.floor((r10 * x + r11 * y + r12 * z + t1) * inv_vs + 0.5))
                iz = np.int64(np.floor((r20 * x + r21 * y + r22 * z + t2) * inv_vs + 0.5))
                if shift >= 0:
                    bx, by, bz = ix >> shift, iy >> shift, iz >> shift
                    lx, ly, lz = ix & mask, iy & mask, iz & mask
                else:
                    bx, by, bz = ix // res, iy // res, iz // res
                    lx, ly, lz = ix - bx * res, iy - by * res, iz - bz * res
                ox = bx - b0
                oy = by - b1
                oz = bz - b2
                if ox < 0 or oy < 0 or oz < 0 or ox >= e0 or oy >= e1 or oz >= e2:
                    continue
                j = lut[(ox * e1 + oy) * e2 + oz]
                if j < 0:
                    continue
                loc = ((j * res + lz) * res + ly) * res + lx
                # neighbouring pixels mostly share voxel and track: skip the lookups then
                if loc != prev_loc:
                    s = scratch[loc]
                    if s < 0:
                        s = nt
                        scratch[loc] = nt
                        tv[nt] = loc
                        nt += 1
                    prev_loc = loc
                    prev_s = s
                    prev_q = -1
                else:
                    s = prev_s
                tn[s] += 1
                tid = tracks[v, u]
                if tid < 0:
                    continue
                if tid != last_tid:
                    lo = 0
                    hi = T
                    while lo < hi:
                        mid = (lo + hi) >> 1
                        if gid[mid] < tid:
                            lo = mid + 1
                        else:
                            hi = mid
                    last_tid = tid
                    last_c = lo if lo < T and gid[lo] == tid else -1
                c = last_c
                if c < 0:
                    unknown += 1
                    continue
                voted += 1
                if prev_q >= 0 and ttr[s, prev_q] == c:
                    tcnt[s, prev_q] += 1
                    continue
                found = False
                for q in range(tk[s]):
                    if ttr[s, q] == c:
                        tcnt[s, q] += 1
                        prev_q = q
                        found = True
                        break
                if not found:
                    if tk[s] < J:
                        ttr[s, tk[s]] = c
                        tcnt[s, tk[s]] = 1
                        prev_q = tk[s]
                        tk[s] += 1
                    else:
                        overflow += 1
        return nt, voted, overflow, unknown

    @numba.njit(cache=True, nogil=True)
    def _slot_pass(tv, tn, tk, ttr, tcnt, nt, gid, gval, bufs, res, hyp_id, hyp_w):
        """Apply eq. 5 and the slot rule to every touched voxel, in place on the grid."""
        res3 = res * res * res
        K = hyp_id.shape[1]
        J = MAX_TRACKS_PER_VOXEL
        total = 0
        for s in range(nt):
            total += tk[s]
        disp_id = np.empty(total, np.int64)
        disp_w = np.empty(total, np.float32)
        ndisp = 0
        n_new = 0
        n_repl = 0
        n_vox = 0
        new_c = np.empty(J, np.int64)
        new_inc = np.empty(J, np.float32)
        for s in range(nt):
            if tk[s] == 0:
                continue
            n_vox += 1
            loc = tv[s]
            j = loc // res3
            f = bufs[j] * res3 + (loc - j * res3)
            n = tn[s]
            m = 0
            for q in range(tk[s]):
                c = ttr[s, q]
                inc = np.float32(gval[c] * tcnt[s, q] / n)
                code = gid[c] + 1
                matched = False
                for k in range(K):
                    if hyp_id[f, k] == code:
                        hyp_w[f, k] = hyp_w[f, k] + inc
                        matched = True
                        break
                if not matched:
                    # insertion sort: strongest first, then lower track id
                    p = m
                    while p > 0 and (
                        new_inc[p - 1] < inc
                        or (new_inc[p - 1] == inc and gid[new_c[p - 1]] > gid[c])
                    ):
                        new_inc[p] = new_inc[p - 1]
                        new_c[p] = new_c[p - 1]
                        p -= 1
                    new_inc[p] = inc
                    new_c[p] = c
                    m += 1
            placed = 0
            for q in range(m):
                best = -1
                for k in range(K):
                    if hyp_id[f, k] == 0:
                        best = k
                        break
                if best < 0:
                    best = 0
                    for k in range(1, K):
                        if hyp_w[f, k] < hyp_w[f, best]:
                            best = k
                    if placed & (1 << best):
                        # the lowest slot went to a stronger newcomer of this frame
                        disp_id[ndisp] = gid[new_c[q]]
                        disp_w[ndisp] = new_inc[q]
                        ndisp += 1
                        continue
                    disp_id[ndisp] = hyp_id[f, best] - 1
                    disp_w[ndisp] = hyp_w[f, best]
                    ndisp += 1
                    n_repl += 1
                hyp_id[f, best] = gid[new_c[q]] + 1
                hyp_w[f, best] = new_inc[q]
                placed |= 1 << best
                n_new += 1
        return disp_id[:ndisp], disp_w[:ndisp], n_new, n_repl, n_vox


def numba_available() -> bool:
    return numba is not None


class NumbaVote:
    """CPU vote over the grid's zero-copy numpy views, with per-frame buffers kept across frames."""

    def __init__(self) -> None:
        if numba is None:
            raise ImportError("numba is not installed; use the torch backend")
        self._scratch = np.full(0, -1, np.int32)
        self._tv = np.zeros(0, np.int32)
        self._tn = np.zeros(0, np.int32)
        self._tk = np.zeros(0, np.int32)
        self._ttr = np.zeros((0, MAX_TRACKS_PER_VOXEL), np.int32)
        self._tcnt = np.zeros((0, MAX_TRACKS_PER_VOXEL), np.int32)
        self._dirty = 0

    def _buffers(self, npix: int, need: int) -> None:
        if self._dirty:  # counts of the previous frame (also one whose integration failed)
            self._tn[: self._dirty] = 0
            self._tk[: self._dirty] = 0
            self._dirty = 0
        if need >= np.iinfo(np.int32).max:
            raise ValueError(f"frame touches too many voxels ({need}) for int32 indexing")
        if self._scratch.shape[0] < need:
            self._scratch = np.full(max(need, 2 * self._scratch.shape[0]), -1, np.int32)
        if self._tv.shape[0] < npix:
            J = MAX_TRACKS_PER_VOXEL
            self._tv = np.zeros(npix, np.int32)
            self._tn = np.zeros(npix, np.int32)
            self._tk = np.zeros(npix, np.int32)
            self._ttr = np.zeros((npix, J), np.int32)
            self._tcnt = np.zeros((npix, J), np.int32)

    def pixel_pass(
        self, depth: FrameDepth, track_ids: FrameTracks, gid: np.ndarray, geo: FrameGeometry, n_frame_blocks: int
    ) -> tuple[int, int, int]:
        """Returns (touched voxels, voted pixels, overflow); the touched-voxel buffers stay
        valid until the next call."""
        self._buffers(depth.size, n_frame_blocks * geo.res**3)
        nt, voted, overflow, unknown = _pixel_pass(
            depth, track_ids, gid, geo.R, geo.t, geo.xs, geo.ys, geo.inv_voxel, geo.res,
            geo.shift, geo.bmin, geo.bext, geo.lut, self._scratch,
            self._tv, self._tn, self._tk, self._ttr, self._tcnt,
        )  # fmt: skip
        self._dirty = nt
        # the scratch index is only valid within one frame
        self._scratch[self._tv[:nt]] = -1
        if unknown:
            raise _unknown_tracks_error(track_ids, gid)
        return nt, voted, overflow

    def slot_pass(
        self,
        passed: tuple[int, int, int],
        gid: np.ndarray,
        gval: np.ndarray,
        bufs: Annotated[np.ndarray, "(B,) int64 grid buffer index of each frame block"],
        res: int,
        hyp_id: Annotated[np.ndarray, "(capacity * res^3, K) int32 view"],
        hyp_w: Annotated[np.ndarray, "(capacity * res^3, K) float32 view"],
    ) -> VoteResult:
        nt, voted, overflow = passed
        disp_id, disp_w, n_new, n_repl, n_vox = _slot_pass(
            self._tv, self._tn, self._tk, self._ttr, self._tcnt, nt, gid, gval, bufs, res,
            hyp_id, hyp_w,
        )  # fmt: skip
        return VoteResult(
            pixels_voted=int(voted), voxels_voted=int(n_vox), new_hypotheses=int(n_new),
            replaced=int(n_repl), dropped=len(disp_id) - int(n_repl), overflow=int(overflow),
            displaced=_sum_displaced(disp_id, disp_w),
        )  # fmt: skip


# --------------------------------------------------------------------------------------------
# torch (any device)


class TorchVote:
    """Vectorised vote; every tensor lives on ``device`` (the grid's, shared through DLPack)."""

    def __init__(self, device: str | torch.device = "cpu") -> None:
        import torch

        self.torch = torch
        self.device = torch.device(device)

    def pixel_pass(
        self, depth: FrameDepth, track_ids: FrameTracks, gid: np.ndarray, geo: FrameGeometry, n_frame_blocks: int
    ) -> dict:
        """(voxel, track) pairs of this frame with their pixel counts, before the grid is
        touched, so an unknown track fails before anything is integrated."""
        th = self.torch
        dev = self.device
        d_all = th.from_numpy(np.ascontiguousarray(depth)).to(dev).reshape(-1)
        idx = th.nonzero(d_all > 0).squeeze(1)
        W = depth.shape[1]
        z = d_all[idx].double()
        xs = th.from_numpy(geo.xs).to(dev)
        ys = th.from_numpy(geo.ys).to(dev)
        x = xs[idx % W] * z
        y = ys[th.div(idx, W, rounding_mode="floor")] * z
        R = [[float(geo.R[i, k]) for k in range(3)] for i in range(3)]
        t = [float(c) for c in geo.t]
        ivox = [
            th.floor((R[i][0] * x + R[i][1] * y + R[i][2] * z + t[i]) * geo.inv_voxel + 0.5).long()
            for i in range(3)
        ]
        blk = [th.div(c, geo.res, rounding_mode="floor") for c in ivox]
        off = [blk[i] - int(geo.bmin[i]) for i in range(3)]
        ext = [int(e) for e in geo.bext]
        inside = (
            (off[0] >= 0) & (off[1] >= 0) & (off[2] >= 0)
            & (off[0] < ext[0]) & (off[1] < ext[1]) & (off[2] < ext[2])
        )  # fmt: skip
        lut = th.from_numpy(geo.lut).to(dev).long()
        j = th.full_like(idx, -1)
        j[inside] = lut[((off[0] * ext[1] + off[1]) * ext[2] + off[2])[inside]]
        keep = j >= 0
        res = geo.res
        loc = (
            j * res**3
            + ((ivox[2] - blk[2] * res) * res + (ivox[1] - blk[1] * res)) * res
            + (ivox[0] - blk[0] * res)
        )
        loc = loc[keep]
        tr = th.from_numpy(np.ascontiguousarray(track_ids)).to(dev).reshape(-1)[idx[keep]].long()
        gid_t = th.from_numpy(gid).to(dev)
        T = len(gid)
        masked = tr >= 0
        c = th.full_like(tr, -1)
        if T:
            pos = th.searchsorted(gid_t, tr[masked]).clamp_(max=T - 1)
            if not bool((gid_t[pos] == tr[masked]).all()):
                raise _unknown_tracks_error(track_ids, gid)
            c[masked] = pos
        elif bool(masked.any()):
            raise _unknown_tracks_error(track_ids, gid)
        pair = loc * (T + 1) + (c + 1)
        uniq, cnt = th.unique(pair, return_counts=True)
        vox = th.div(uniq, T + 1, rounding_mode="floor")
        cc = uniq - vox * (T + 1) - 1
        _, inv = th.unique_consecutive(vox, return_inverse=True)
        n_vox = th.zeros(int(inv.max()) + 1 if len(inv) else 0, dtype=th.long, device=dev)
        n_vox.index_add_(0, inv, cnt)
        tracked = cc >= 0
        return {
            "vox": vox[tracked], "c": cc[tracked], "cnt": cnt[tracked], "n": n_vox[inv][tracked],
            "voted": int(masked.sum()),
        }  # fmt: skip

    def slot_pass(
        self,
        passed: dict,
        gid: np.ndarray,
        gval: np.ndarray,
        bufs: Annotated[np.ndarray, "(B,) int64 grid buffer index of each frame block"],
        res: int,
        hyp_id: torch.Tensor,
        hyp_w: torch.Tensor,
    ) -> VoteResult:
        """``hyp_id`` (capacity * res^3, K) int32 and ``hyp_w`` float32 are views of the grid."""
        th = self.torch
        dev = self.device
        vox, c, cnt, n = passed["vox"], passed["c"], passed["cnt"], passed["n"]
        res3 = res**3
        if len(vox) == 0:
            return VoteResult(pixels_voted=passed["voted"])
        bufs_t = th.from_numpy(bufs).to(dev).long()
        gid_t = th.from_numpy(gid).to(dev)
        gval_t = th.from_numpy(gval).to(dev)
        jb = th.div(vox, res3, rounding_mode="floor")
        f = bufs_t[jb] * res3 + (vox - jb * res3)
        inc = (gval_t[c] * cnt.double() / n.double()).float()
        code = (gid_t[c] + 1).int()
        tgid = gid_t[c]
        # pairs come sorted by voxel from the pixel pass
        n_vox = int(th.unique_consecutive(vox).numel())

        rows = hyp_id[f]
        match = rows == code[:, None]
        matched = match.any(1)
        k = match.int().argmax(1)
        fm, km = f[matched], k[matched]
        hyp_w[fm, km] = hyp_w[fm, km] + inc[matched]

        new = ~matched
        f, inc, code, tgid = f[new], inc[new], code[new], tgid[new]
        if len(f) == 0:
            return VoteResult(pixels_voted=passed["voted"], voxels_voted=n_vox)
        # per voxel: strongest first, ties by lower track id (stable sorts, least key first)
        order = th.argsort(tgid, stable=True)
        order = order[th.argsort(-inc[order], stable=True)]
        order = order[th.argsort(f[order], stable=True)]
        f, inc, code, tgid = f[order], inc[order], code[order], tgid[order]
        _, group, counts = th.unique_consecutive(f, return_inverse=True, return_counts=True)
        starts = th.cumsum(counts, 0) - counts
        rank = th.arange(len(f), device=dev) - th.repeat_interleave(starts, counts)
        placed = th.zeros((len(counts), hyp_id.shape[1]), dtype=th.bool, device=dev)
        disp_ids, disp_ws = [], []
        n_new = n_repl = 0
        for r in range(int(rank.max()) + 1):
            sel = th.nonzero(rank == r).squeeze(1)
            fr, gr = f[sel], group[sel]
            rid, rw = hyp_id[fr], hyp_w[fr]
            score = th.where(rid == 0, th.full_like(rw, -float("inf")), rw)
            kk = th.argmin(score, 1)
            ar = th.arange(len(fr), device=dev)
            # the lowest slot went to a stronger newcomer of this frame: drop the weaker one
            drop = placed[gr, kk]
            disp_ids.append(tgid[sel][drop])
            disp_ws.append(inc[sel][drop])
            ok = ~drop
            fr, kk, gr, sel, ar = fr[ok], kk[ok], gr[ok], sel[ok], ar[ok]
            old_id, old_w = rid[ar, kk], rw[ar, kk]
            occupied = old_id != 0
            disp_ids.append(old_id[occupied].long() - 1)
            disp_ws.append(old_w[occupied])
            hyp_id[fr, kk] = code[sel]
            hyp_w[fr, kk] = inc[sel]
            placed[gr, kk] = True
            n_new += len(fr)
            n_repl += int(occupied.sum())
        d_id = th.cat(disp_ids).cpu().numpy()
        d_w = th.cat(disp_ws).cpu().numpy()
        return VoteResult(
            pixels_voted=passed["voted"], voxels_voted=n_vox, new_hypotheses=n_new,
            replaced=n_repl, dropped=len(d_id) - n_repl, displaced=_sum_displaced(d_id, d_w),
        )  # fmt: skip
