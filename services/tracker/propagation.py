"""Source-track label propagation between keyframes (paper III-B, eq. 1).

For every patch p of frame t, eq. 1 looks at the reference patches q within a (2R+1)^2 window
around p in each reference frame r (the last keyframe plus up to ``context_frames`` recent
frames), keeps the top-k (q, r) by cosine similarity of the dense features, turns those
similarities into weights with a softmax at temperature tau, and mixes the references'
distributions over track slots: ``Y_t(p) = sum a_pqr Y_r(q)``.

Slot convention: channel 0 of every label tensor is "no track" (background); channels 1..C-1
are the active source tracks in the order the tracker keeps them. Propagation treats slot 0 like
any other slot, so background is carried and distributions keep summing to one. Deviation from
the paper (docs/method.md, T5), whose distributions range over the active tracks only: without
the background channel, pixels no keyframe mask covered would be forced onto a track.

Implementation ("row windows"): the maps are oriented so rows run along the short side (the
grid is transposed when wider than tall). Query row y is compared, in one batched matmul over
all rows, with reference rows y-R..y+R in full: with the reference map padded by R zero rows,
those 2R+1 rows are one contiguous (2R+1)*W x D block, and consecutive query rows' blocks are
W*D apart, so ``as_strided`` presents them to ``bmm`` without any copy. A mask then drops
pairs more than R columns apart (and the padding rows). Per reference the top-k is taken first,
then the top-k of the union: exact, since the global top-k is contained in the per-reference
ones. Work per patch is (2R+1)*W against the ideal (2R+1)^2: 1.8x at 720p (45 x 79 grid, R=12)
and 1.2x at 480p, against 5.7x for a full-frame comparison. On CPU references go one per
matmul; on CUDA all of them share one matmul (launch overhead dominates there) with float16
similarities. Measured at 720p with 8 references (D = 384): 1.0-1.5 s on a loaded 2-core CPU,
75 ms on 16 cores, 1.4 ms on an H100; square query tiles (T x T against the (T+2R)^2 region:
less arithmetic, but gathering the regions cost more than the matmul) took 3-6 s on the same
2-core CPU, and loops of small per-row-offset matmuls 2 s.

On the CPU, up to ``NUMBA_MAX_DIM`` channels, a numba kernel (:mod:`services.tracker.
propagation_numba`) replaces all of this: per patch, the top-k over its own window directly,
without the similarity tensor, the mask or ``topk``, and with the same float32 cosines (fused
multiply-adds in channel order, as MKL's matmul). At 1200x680 with classical features (48 x
85, D = 20, 7 references) it took 41 ms a frame against 137 ms for the path above on one
thread, 21 against 107 on two (the shared 2-core machine); the tracker's session went from
about 105 to 67 ms a frame. The torch path stays the reference and CUDA's.
"""

from __future__ import annotations

import functools
import logging
import time
from collections import deque
from collections.abc import Sequence
from typing import Annotated, Literal

import numpy as np
import torch
import torch.nn.functional as F

from shared.config.tracker import PropagationConfig

log = logging.getLogger(__name__)

FeatureMap = Annotated[torch.Tensor, "(h, w, D) float, unit L2 norm per patch"]
LabelMap = Annotated[torch.Tensor, "(h, w, C) float32, distribution over track slots, slot 0 = no track"]

DEFAULT_CHUNK_BYTES = 512 * 2**20
"""Working memory for similarities and masks; rows are processed in chunks under this."""


NUMBA_MAX_DIM = 128
"""Feature channels up to which the CPU uses the numba kernel by default. Measured on the
shared 2-core machine at 48 x 85 with 8 references, torch path against kernel, p50 per frame:
D = 20 153 / 43 ms on one thread, 124 / 22 on two; D = 384 471 / 694 and 296 / 343 (MKL's
matmul wins at DINOv3's D); in a busier run on one thread D = 64 435 / 188 and D = 128
507 / 343."""


def _numba_applies(feats: torch.Tensor, use_numba: bool | None) -> bool:
    """Whether ``propagate_labels`` takes the numba kernel (see its docstring)."""
    if use_numba is False or feats.device.type != "cpu" or feats.dtype != torch.float32:
        return False
    from services.tracker import propagation_numba

    if propagation_numba.numba is None:
        return False
    return bool(use_numba) or feats.shape[-1] <= NUMBA_MAX_DIM


@functools.lru_cache(maxsize=16)
def _window_plan(rows: int, cols: int, cols_p: int, radius: int, group: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """For each virtual row (see ``propagate_labels``) and candidate (dy, x') of its block:
    whether the candidate is outside the window or the map, and its flat index (row * cols +
    column, clamped) in the stacked references of the group. Depends on shapes only."""
    per_ref = rows + 2 * radius
    span = 2 * radius + 1
    n_virtual = group * per_ref - 2 * radius
    dev = torch.device(device)
    v = torch.arange(n_virtual, device=dev)
    v_row, v_ref = v % per_ref, v // per_ref
    ref_rows = v_row[:, None] + torch.arange(span, device=dev)[None, :] - radius  # (n_virtual, span)
    row_ok = (ref_rows >= 0) & (ref_rows < rows)
    xs = torch.arange(cols_p, device=dev)
    col_ok = ((xs[:, None] - xs[None, :]).abs() <= radius) & (xs[None, :] < cols)  # (query x, x')
    outside = ~(col_ok[None, :, None, :] & row_ok[:, None, :, None]).reshape(n_virtual, cols_p, span * cols_p)
    flat = ref_rows.clamp(0, rows - 1)[:, :, None] * cols + xs.clamp(max=cols - 1)[None, None, :]
    cand = (flat + (v_ref * rows * cols)[:, None, None]).reshape(n_virtual, span * cols_p)
    return outside, cand


def propagate_labels(
    feats: FeatureMap,
    refs: Sequence[tuple[FeatureMap, LabelMap]],
    *,
    window_radius: int = 12,
    topk: int = 5,
    temperature: float = 0.2,
    precision: Literal["auto", "float32"] = "auto",
    batch_refs: bool | None = None,
    chunk_bytes: int = DEFAULT_CHUNK_BYTES,
    use_numba: bool | None = None,
) -> LabelMap:
    """Eq. 1: the distribution over track slots of every patch of the current frame.

    ``refs`` are (features, labels) pairs of the reference frames (the keyframe and the
    recent frames), all on the current frame's grid. Returns float32 on ``feats.device``.
    ``precision="auto"`` computes similarities in float16 on CUDA (tensor cores; cosines then
    carry ~5e-4 absolute error, ~0.3% on the softmax weights at tau = 0.2, which can swap
    near-tied k-th and (k+1)-th candidates) and in the features' dtype elsewhere;
    ``"float32"`` forces full precision. ``batch_refs`` compares all references in one matmul
    (the default on CUDA) instead of one reference at a time.

    On the CPU, float32 features of at most ``NUMBA_MAX_DIM`` channels go to the numba kernel
    of :mod:`services.tracker.propagation_numba` when numba is installed (``use_numba=None``,
    the default); it gives the torch path's result to float32 round-off (ties between equal
    similarities aside). ``use_numba=False`` forces the torch path, ``True`` the kernel for
    any D; ``batch_refs`` and ``chunk_bytes`` only concern the torch path.
    """
    if not refs:
        raise ValueError("label propagation needs at least one reference frame")
    if feats.ndim != 3:
        raise ValueError(f"feats must be (h, w, D), got {tuple(feats.shape)}")
    h, w, dim = feats.shape
    n_slots = refs[0][1].shape[-1]
    for i, (rf, ry) in enumerate(refs):
        if tuple(rf.shape) != (h, w, dim) or tuple(ry.shape) != (h, w, n_slots):
            raise ValueError(
                f"reference {i}: features {tuple(rf.shape)} and labels {tuple(ry.shape)} do not match "
                f"the frame's ({h}, {w}, {dim}) grid with {n_slots} slots"
            )
    device = feats.device
    if _numba_applies(feats, use_numba):
        from services.tracker import propagation_numba

        out = propagation_numba.propagate_numba(
            feats.detach().numpy(),
            [rf.detach().to(device="cpu", dtype=torch.float32).numpy() for rf, _ in refs],
            [ry.detach().to(device="cpu", dtype=torch.float32).numpy() for _, ry in refs],
            window_radius,
            topk,
            temperature,
        )
        return torch.from_numpy(out)
    cuda = device.type == "cuda"
    dtype = torch.float16 if cuda and precision == "auto" else (torch.float32 if precision == "float32" else feats.dtype)
    transpose = w > h

    def orient(t: torch.Tensor) -> torch.Tensor:
        return t.transpose(-3, -2) if transpose else t

    rows, cols = (w, h) if transpose else (h, w)
    batch = cuda if batch_refs is None else batch_refs
    # Tensor-core matmuls want dimensions in multiples of 8; padded columns are masked out.
    cols_p = -(-cols // 8) * 8 if batch else cols
    radius = window_radius
    span = 2 * radius + 1
    per_ref = rows + 2 * radius  # rows of one reference after padding
    n_refs = len(refs)

    query = F.pad(orient(feats).to(dtype), (0, 0, 0, cols_p - cols))
    stacked = torch.stack([rf.to(device) for rf, _ in refs]).to(dtype)
    padded = F.pad(orient(stacked), (0, 0, 0, cols_p - cols, radius, radius))  # (n, per_ref, cols_p, D)
    labels = orient(torch.stack([ry.to(device) for _, ry in refs]).float()).reshape(n_refs * rows * cols, n_slots)

    k_ref = min(topk, span * cols_p)
    k_all = min(topk, n_refs * k_ref)
    top_vals = torch.empty(n_refs, rows, cols, k_ref, device=device, dtype=torch.float32)
    top_src = torch.empty(n_refs, rows, cols, k_ref, device=device, dtype=torch.long)
    row_bytes = cols_p * span * cols_p * (2 * torch.finfo(dtype).bits // 8 + 1)  # sims, a copy, mask
    # On CPU the matmul dominates and references go one at a time (no wasted rows). On a GPU
    # launches dominate, so a group of references shares one bmm over "virtual rows": row v
    # of the group is row v % per_ref of reference v // per_ref, one uniform stride through
    # the stacked padded maps, so every comparison block is an as_strided view. The last
    # 2R rows of each reference's stretch are padding, computed and dropped.
    group = max(1, min(n_refs, chunk_bytes // (row_bytes * per_ref))) if batch else 1
    for g0 in range(0, n_refs, group):
        g = min(group, n_refs - g0)
        flat = padded[g0 : g0 + g].reshape(g * per_ref * cols_p, dim)
        n_virtual = g * per_ref - 2 * radius
        # One cached plan serves every group size up to 8 (its first rows are the smaller plans).
        outside, cand = _window_plan(rows, cols, cols_p, radius, max(g, 8) if g > 1 else 1, str(device))
        if g == 1:
            qflat, chunk = query, max(1, min(rows, chunk_bytes // row_bytes))
        else:
            qflat = F.pad(query, (0, 0, 0, 0, 0, 2 * radius)).expand(g, per_ref, cols_p, dim).reshape(g * per_ref, cols_p, dim)
            chunk = n_virtual
        for a in range(0, n_virtual, chunk):
            b = min(n_virtual, a + chunk)
            blocks = torch.as_strided(flat, (b - a, span * cols_p, dim), (cols_p * dim, dim, 1), flat.storage_offset() + a * cols_p * dim)
            sims = torch.bmm(qflat[a:b], blocks.transpose(1, 2))  # (b-a, cols_p, span*cols_p)
            sims.masked_fill_(outside[a:b], float("-inf"))
            val, loc = sims.topk(k_ref, dim=-1)
            src = cand[a:b].gather(1, loc.reshape(b - a, -1)).view(b - a, cols_p, k_ref) + g0 * rows * cols
            if g == 1:
                top_vals[g0, a:b] = val[:, :cols].float()
                top_src[g0, a:b] = src[:, :cols]
            else:
                top_vals[g0 : g0 + g] = F.pad(val, (0, 0, 0, 0, 0, 2 * radius)).view(g, per_ref, cols_p, k_ref)[:, :rows, :cols].float()
                top_src[g0 : g0 + g] = F.pad(src, (0, 0, 0, 0, 0, 2 * radius)).view(g, per_ref, cols_p, k_ref)[:, :rows, :cols]

    # Each reference's own top-k first, then the best of their union.
    top_vals = top_vals.permute(1, 2, 0, 3).reshape(rows, cols, n_refs * k_ref)
    top_src = top_src.permute(1, 2, 0, 3).reshape(rows, cols, n_refs * k_ref)
    best, pick = top_vals.topk(k_all, dim=-1)
    weights = torch.softmax(best / temperature, dim=-1).nan_to_num_(0.0)
    out = torch.einsum("yxk,yxkc->yxc", weights, labels[top_src.gather(2, pick)])
    return orient(out).contiguous()


def propagate_with_config(feats: FeatureMap, refs: Sequence[tuple[FeatureMap, LabelMap]], cfg: PropagationConfig) -> LabelMap:
    """``propagate_labels`` with the window, top-k and temperature of ``cfg``."""
    return propagate_labels(feats, refs, window_radius=cfg.window_radius, topk=cfg.topk, temperature=cfg.temperature)


class LabelPropagator:
    """The references of eq. 1 between keyframes: the keyframe plus the recent frames.

    ``reset`` at each keyframe with its (corrected) labels; ``step`` on every later frame
    propagates from the keyframe and up to ``cfg.context_frames`` most recent propagated
    frames, then remembers the result as a reference for the next frames.
    """

    def __init__(self, cfg: PropagationConfig | None = None):
        self.cfg = cfg or PropagationConfig()
        self._keyframe: tuple[torch.Tensor, torch.Tensor] | None = None
        self._recent: deque[tuple[torch.Tensor, torch.Tensor]] = deque(maxlen=max(self.cfg.context_frames, 1))

    @property
    def ready(self) -> bool:
        return self._keyframe is not None

    @property
    def num_slots(self) -> int:
        return 0 if self._keyframe is None else int(self._keyframe[1].shape[-1])

    def reset(self, feats: FeatureMap, labels: LabelMap) -> None:
        """New keyframe: its labels come from the keyframe masks, not from propagation."""
        if tuple(feats.shape[:2]) != tuple(labels.shape[:2]):
            raise ValueError(f"keyframe features {tuple(feats.shape)} and labels {tuple(labels.shape)} differ in grid")
        self._keyframe = (feats, labels.to(device=feats.device, dtype=torch.float32))
        self._recent.clear()

    def references(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        if self._keyframe is None:
            return []
        recent = list(self._recent) if self.cfg.context_frames > 0 else []
        return [self._keyframe, *recent]

    def step(self, feats: FeatureMap) -> LabelMap:
        if self._keyframe is None:
            raise RuntimeError("LabelPropagator.step before the first keyframe (call reset)")
        labels = propagate_with_config(feats, self.references(), self.cfg)
        if self.cfg.context_frames > 0:
            self._recent.append((feats, labels))
        return labels


def _linear_taps(out_len: int, in_len: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Source indices and weight of 1-D linear interpolation, as torch's bilinear
    (align_corners=False) computes them, so the upsample matches F.interpolate exactly."""
    scale = in_len / out_len
    src = ((torch.arange(out_len, device=device, dtype=torch.float32) + 0.5) * scale - 0.5).clamp(min=0)
    i0 = src.floor().long().clamp(max=in_len - 1)
    i1 = torch.where(i0 < in_len - 1, i0 + 1, i0)
    return i0, i1, src - i0


@functools.lru_cache(maxsize=16)
def _numpy_taps(out_len: int, in_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``_linear_taps`` on the CPU as numpy (i0, i1, f, 1 - f), for the numba kernels; kept
    per size (the arrays are never written)."""
    i0, i1, f = _linear_taps(out_len, in_len, torch.device("cpu"))
    return i0.numpy(), i1.numpy(), f.numpy(), (1 - f).numpy()


def upsample_labels(
    labels: LabelMap, height: int, width: int, chunk_rows: int = 64, *, use_numba: bool = True
) -> Annotated[torch.Tensor, "(H, W) int32 slot index, 0 = no track"]:
    """Pixel-wise argmax of the bilinearly upsampled distributions (paper: predicted masks).

    Returns slot indices, not track ids: 0 is "no track", s >= 1 the tracker's slot s.
    Equal to ``F.interpolate(..., mode="bilinear", align_corners=False).argmax`` without
    interpolating every channel of every pixel: a pixel whose four source patches have the
    same argmax c takes c (a convex combination of vectors that all peak first at c peaks
    first at c too), and only the others, along label boundaries, are interpolated, in row
    chunks so full-resolution C-channel maps are never held at once. At 720 x 1280 with 40
    keyframe-like slots (one CPU thread) this took 0.2 s against 0.5 s for interpolating
    every pixel, with identical output; at 240 x 320 the two are on par.

    On the CPU with numba installed, :mod:`services.tracker.upsample_numba` gives the same
    result cell by cell over the slots that carry mass (``use_numba=False`` forces torch).
    """
    h, w, n_slots = labels.shape
    device = labels.device
    y = labels.float()
    if use_numba and device.type == "cpu":
        from services.tracker import upsample_numba

        if upsample_numba.numba is not None:
            # numpy's argmax (the first maximum, as torch's): on the tracker's small grids
            # torch's thread pool cost more than the reduction itself.
            y_np = y.detach().contiguous().numpy()
            slots, _ = upsample_numba.upsample_numba(y_np, y_np.argmax(-1), _numpy_taps(height, h), _numpy_taps(width, w), height, width)
            return torch.from_numpy(slots)
    x0, x1, wx = _linear_taps(width, w, device)
    r0, r1, wr = _linear_taps(height, h, device)
    peak = y.argmax(-1)  # (h, w)
    out = torch.empty(height, width, dtype=torch.int32, device=device)
    for a in range(0, height, chunk_rows):
        b = min(height, a + chunk_rows)
        top, bottom = peak[r0[a:b]], peak[r1[a:b]]  # (n, w)
        c00, c01, c10, c11 = top[:, x0], top[:, x1], bottom[:, x0], bottom[:, x1]  # (n, W)
        block = c00.to(torch.int32)
        mixed = (c00 != c01) | (c00 != c10) | (c00 != c11)
        yy, xx = mixed.nonzero(as_tuple=True)
        if len(yy):
            ra, rb, xa, xb = r0[a:b][yy], r1[a:b][yy], x0[xx], x1[xx]
            fx = wx[xx, None]
            fy = wr[a:b][yy, None]
            # The same operation order as a horizontal then a vertical pass.
            upper = y[ra, xa] * (1 - fx) + y[ra, xb] * fx
            lower = y[rb, xa] * (1 - fx) + y[rb, xb] * fx
            block[yy, xx] = (upper * (1 - fy) + lower * fy).argmax(-1).to(torch.int32)
        out[a:b] = block
    return out


def upsample_ids(
    labels: LabelMap, height: int, width: int, slots: Sequence[int]
) -> tuple[Annotated[np.ndarray, "(H, W) int32 track id, -1 = none"], list[int]]:
    """:func:`upsample_labels` with each slot s >= 1 written as its track ``slots[s - 1]``
    (0 as -1), and the track ids present, ascending: on the CPU with numba in the kernel's
    one pass (the lookup and a count over 1200x680 pixels took another 4-8 ms)."""
    lut = np.asarray([-1, *slots], np.int32)
    h, w, n_slots = labels.shape
    if n_slots > len(lut):
        raise ValueError(f"{n_slots} label slots for {len(slots)} tracks")
    if labels.device.type == "cpu":
        from services.tracker import upsample_numba

        if upsample_numba.numba is not None:
            y_np = labels.float().detach().contiguous().numpy()
            ids, seen = upsample_numba.upsample_numba(y_np, y_np.argmax(-1), _numpy_taps(height, h), _numpy_taps(width, w),
                                                      height, width, lut[:n_slots])  # fmt: skip
            return ids, sorted({int(t) for t in lut[:n_slots][seen] if t >= 0})
    slot_img = upsample_labels(labels, height, width).cpu().numpy()
    present = np.bincount(slot_img.ravel(), minlength=n_slots)[:n_slots] > 0
    return lut[slot_img], sorted({int(t) for t in lut[:n_slots][present] if t >= 0})


def upsample_confidence(
    labels: LabelMap, height: int, width: int, *, use_numba: bool = True
) -> Annotated[np.ndarray, "(H, W) uint8, 255 = 1"]:
    """Per pixel, the probability of its most likely slot: the patch grid's maximum over the
    distribution, bilinearly upsampled like the labels, as 0-255. Where two tracks meet, or
    propagation found no clear reference, it is low.

    On the CPU with numba installed, :func:`services.tracker.upsample_numba.upsample_peak`
    does it in one pass with torch's arithmetic (equal bit for bit, tested; 1.6 against 5-7
    ms at 1200x680 on one thread); ``use_numba=False`` forces torch."""
    if use_numba and labels.device.type == "cpu":
        from services.tracker import upsample_numba

        if upsample_numba.numba is not None:
            out = np.empty((height, width), np.uint8)
            upsample_numba.upsample_peak(np.ascontiguousarray(labels.detach().float().numpy().max(-1)), out)
            return out
    peak = labels.float().max(-1).values[None, None]
    up = F.interpolate(peak, size=(height, width), mode="bilinear", align_corners=False)[0, 0]
    return (up.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def masks_to_soft(
    masks: Annotated[np.ndarray | torch.Tensor, "(N, H, W) bool, or (H, W) int slot image"] | Sequence[np.ndarray],
    h: int,
    w: int,
    num_slots: int | None = None,
    *,
    hard: bool = False,
    device: str | torch.device = "cpu",
) -> LabelMap:
    """Keyframe initialisation of ``Y``: per patch, the fraction of its pixels in each slot.

    ``masks`` is either a stack (or list) of N boolean masks, mask j going to slot j + 1 and
    earlier masks winning where they overlap (FastSAM sorts best first), or an integer slot
    image (0 or negative = no track). Pixels covered by no mask count for slot 0. Patch cells
    tile the image as ``floor(y * h / H)``, the same partition association uses. ``hard``
    turns each patch into the one-hot of its majority slot (the paper's example). Deviation
    from the paper (docs/method.md, T5): the tracker uses the soft form, so a patch on a mask
    border starts as the mix it is.
    """
    if isinstance(masks, torch.Tensor):
        masks = masks.detach().cpu().numpy()
    if isinstance(masks, (list, tuple)):
        masks = np.stack([np.asarray(m, dtype=bool) for m in masks]) if masks else None
        if masks is None:
            raise ValueError("an empty mask list has no image size; pass a (0, H, W) array")
    masks = np.asarray(masks)
    if masks.ndim == 3:
        if masks.dtype != bool:
            masks = masks.astype(bool)
        if masks.shape[0] == 0:
            slots = np.zeros(masks.shape[1:], np.int64)
        else:
            # argmax finds the first True: earlier masks win overlaps.
            slots = np.where(masks.any(0), masks.argmax(0) + 1, 0)
        needed = masks.shape[0] + 1
    elif masks.ndim == 2 and np.issubdtype(masks.dtype, np.integer):
        slots = np.maximum(masks.astype(np.int64), 0)
        needed = int(slots.max()) + 1
    else:
        raise ValueError(f"masks must be (N, H, W) bool or an (H, W) integer slot image, got {masks.dtype} {masks.shape}")
    n_slots = needed if num_slots is None else num_slots
    if n_slots < needed:
        raise ValueError(f"masks use {needed} slots but num_slots is {num_slots}")
    height, width = slots.shape
    cy = np.arange(height) * h // height
    cx = np.arange(width) * w // width
    cell = (cy[:, None] * w + cx[None, :]).reshape(-1)
    counts = np.bincount(cell * n_slots + slots.reshape(-1), minlength=h * w * n_slots)
    counts = counts.reshape(h, w, n_slots).astype(np.float32)
    if hard:
        counts = np.eye(n_slots, dtype=np.float32)[counts.argmax(-1)]
    total = counts.sum(-1, keepdims=True)
    soft = counts / np.maximum(total, 1e-12)
    return torch.from_numpy(soft).to(device)


def benchmark_propagation(
    h: int,
    w: int,
    dim: int,
    n_refs: int,
    n_slots: int,
    device: str = "cpu",
    *,
    repeats: int = 3,
    cfg: PropagationConfig | None = None,
    seed: int = 0,
) -> float:
    """Milliseconds per frame of ``propagate_labels`` on random unit features (after a warm-up)."""
    cfg = cfg or PropagationConfig()
    gen = torch.Generator().manual_seed(seed)

    def unit(*shape: int) -> torch.Tensor:
        return torch.nn.functional.normalize(torch.randn(*shape, generator=gen), dim=-1).to(device)

    feats = unit(h, w, dim)
    refs = [(unit(h, w, dim), torch.softmax(torch.randn(h, w, n_slots, generator=gen), -1).to(device)) for _ in range(n_refs)]

    def run() -> None:
        propagate_labels(feats, refs, window_radius=cfg.window_radius, topk=cfg.topk, temperature=cfg.temperature)
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize()

    run()
    start = time.perf_counter()
    for _ in range(repeats):
        run()
    ms = (time.perf_counter() - start) / repeats * 1e3
    log.info("propagation %dx%d D=%d refs=%d C=%d on %s: %.1f ms", h, w, dim, n_refs, n_slots, device, ms)
    return ms
