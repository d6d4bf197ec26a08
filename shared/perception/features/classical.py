"""Hand-made per-patch descriptors on the DINOv3 patch grid: no learned weights.

The stand-in for DINOv3 when no weights are present (synthetic scenes, CI, small robots). Per
patch of the resized frame (same resize rule and grid as the ViT), three blocks:

* colour (6): CIELAB mean (L centred on 50) and standard deviation;
* texture (10): a 9-bin unsigned gradient-orientation histogram of L (HOG-like, soft binning,
  magnitude-weighted), normalised by its norm plus a floor so flat patches stay near zero
  instead of amplifying noise, and centred so isotropic texture cancels; plus gradient energy;
* depth (4): log of the patch's mean depth over the frame's median patch depth, relative depth
  spread, and the x/y components of the surface normal from the depth gradient (focal length
  assumed 0.6 x width: the normal only has to be consistent between frames, not metric). Zero
  when the frame has no depth or the patch too few valid readings.

Each block is scaled to about unit range, its norm capped at 1 so no block dominates, weighted,
and the concatenation is L2-normalised. Blocks are signed (centred) wherever a constant offset
would make all patches look alike to a cosine.

Whole-image numpy, single-threaded on purpose: these are many small element-wise passes, and
torch's intra-op thread pool made them 10-30x slower on a loaded 2-core machine (measured),
while one thread meets the budget (about 15 ms at 320x240, 50 ms at 640x480).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from PIL import Image

from shared.perception.features import classical_numba
from shared.perception.features.base import PatchGridMixin

N_BINS = 9
COLOUR_DIM, TEXTURE_DIM, DEPTH_DIM = 6, N_BINS + 1, 4
BLOCK_WEIGHTS = (1.0, 0.3, 0.8)
"""Colour, texture, depth. Colour separates most indoor objects; depth splits same-coloured
surfaces at different distances or orientations; texture mostly breaks ties. Chosen with the
chroma and spread scales below on two synthetic sequences (``trackgraph synth --preset small``,
seeds 3 and 7): mean IoU of masks propagated 23 frames from ground-truth keyframes went from
0.60 / 0.47 (texture 0.6, chroma / 40, spread / 20) to 0.64 / 0.49; without the depth block
0.62 / 0.46, and copying the keyframe's labels unchanged gives 0.33 / 0.28."""
GRAD_FLOOR = 2.0
"""L units per pixel: below this a patch's orientation histogram counts as noise."""
FOCAL_FRACTION = 0.6
MIN_DEPTH_COVER = 0.25
"""A patch needs this fraction of valid depth pixels for a depth block."""

_WHITE = np.array([0.950456, 1.0, 1.088754])
_RGB_TO_XYZ = (
    np.array([[0.412453, 0.357580, 0.180423], [0.212671, 0.715160, 0.072169], [0.019334, 0.119193, 0.950227]])
    / _WHITE[:, None]
).astype(np.float32)
_LINEAR_LUT = np.where(
    np.arange(256) / 255.0 <= 0.04045,
    np.arange(256) / 255.0 / 12.92,
    ((np.arange(256) / 255.0 + 0.055) / 1.055) ** 2.4,
).astype(np.float32)


def _pool_sum(x: np.ndarray, p: int) -> np.ndarray:
    """Sum over non-overlapping p x p patches of (..., H, W) with H, W multiples of p."""
    *lead, height, width = x.shape
    s = x.reshape(*lead, height, width // p, p).sum(-1)
    return s.reshape(*lead, height // p, p, width // p).sum(-2)


def _cap_norm(block: np.ndarray) -> np.ndarray:
    norm = np.sqrt((block * block).sum(0, keepdims=True))
    return block / np.maximum(norm, 1.0)


_F_LUT_SIZE = 16384
_F_LUT_MAX = 1.1
"""XYZ/white is at most ~1.09 for sRGB input; a 16k-entry table keeps L within 0.05 units."""
_t = np.linspace(0.0, _F_LUT_MAX, _F_LUT_SIZE)
_F_LUT = np.where(_t > 0.008856, np.cbrt(_t), 7.787 * _t + 16.0 / 116.0).astype(np.float32)
del _t


_NUMBA_TABLES = (_LINEAR_LUT, (_RGB_TO_XYZ * np.float32((_F_LUT_SIZE - 1) / _F_LUT_MAX)).astype(np.float32), _F_LUT)
"""The tables of :func:`_lab` for the numba kernels (the XYZ rows scaled as it scales them)."""


def _lab(rgb: np.ndarray) -> np.ndarray:
    """(3, H, W) float32 CIELAB (D65) of an (H, W, 3) uint8 sRGB image."""
    lin = _LINEAR_LUT[rgb]
    r, g, b = lin[..., 0], lin[..., 1], lin[..., 2]
    scale = np.float32((_F_LUT_SIZE - 1) / _F_LUT_MAX)
    f = []
    for row in _RGB_TO_XYZ:
        # Table lookup instead of np.cbrt: the cube root was a third of this backend's time.
        t = (row[0] * scale) * r + (row[1] * scale) * g + (row[2] * scale) * b
        f.append(_F_LUT[np.minimum((t + np.float32(0.5)).astype(np.int32), _F_LUT_SIZE - 1)])
    fx, fy, fz = f
    return np.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]).astype(np.float32)


def _shift_diffs(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences (half the neighbour difference), edges replicated."""
    padded = np.pad(a, 1, mode="edge")
    gx = (padded[1:-1, 2:] - padded[1:-1, :-2]) * 0.5
    gy = (padded[2:, 1:-1] - padded[:-2, 1:-1]) * 0.5
    return gx, gy


class ClassicalFeatures(PatchGridMixin):
    """Colour, gradient-orientation and depth statistics per patch (see the module doc)."""

    name = "classical"
    dim = COLOUR_DIM + TEXTURE_DIM + DEPTH_DIM
    appearance_dims = COLOUR_DIM + TEXTURE_DIM
    """The depth block (relative depth, camera-frame normal) tells neighbouring frames' patches
    apart but changes with the viewpoint, so mask prototypes leave it out: on the revisit
    preset, prototype cosines of one wall seen from two sides went as low as -0.6 with it, and
    IDF1 rose from 0.64 to 0.70 without it."""

    def __init__(self, short_side: int, patch_size: int, device: str | torch.device = "cpu", use_numba: bool | None = None):
        """``use_numba``: the per-pixel passes in numba kernels (the same features, 3x faster;
        :mod:`shared.perception.features.classical_numba`); None: where numba is installed."""
        self.short_side = short_side
        self.patch_size = patch_size
        self.device = torch.device(device)
        self.use_numba = classical_numba.available() if use_numba is None else bool(use_numba)
        if self.use_numba and not classical_numba.available():
            raise RuntimeError("use_numba needs numba (the fusion extra)")
        self._bin_base: dict[tuple[int, int], np.ndarray] = {}

    def _pixel_patch_base(self, height: int, width: int) -> np.ndarray:
        """Per pixel, the first histogram slot of its patch (patch index x N_BINS)."""
        key = (height, width)
        if key not in self._bin_base:
            p = self.patch_size
            ys = np.arange(height) // p
            xs = np.arange(width) // p
            self._bin_base[key] = ((ys[:, None] * (width // p) + xs[None, :]) * N_BINS).reshape(-1)
        return self._bin_base[key]

    def _colour(self, lab: np.ndarray) -> np.ndarray:
        return self._colour_of(_pool_sum(lab, self.patch_size), _pool_sum(lab * lab, self.patch_size))

    def _colour_of(self, total: np.ndarray, total_sq: np.ndarray) -> np.ndarray:
        """The colour block from each patch's CIELAB sums and sums of squares (3, h, w)."""
        area = float(self.patch_size**2)
        mean = total / area
        sq = total_sq / area
        std = np.sqrt(np.maximum(sq - mean * mean, 0.0))
        offset = np.array([50.0, 0.0, 0.0], np.float32)[:, None, None]
        # Chroma weighs more than lightness: shading changes L along a surface, not a and b.
        scale = np.array([50.0, 20.0, 20.0], np.float32)[:, None, None]
        return np.concatenate([(mean - offset) / scale, std / 40.0])

    def _texture(self, lightness: np.ndarray, h: int, w: int) -> np.ndarray:
        p = self.patch_size
        gx, gy = _shift_diffs(lightness)
        mag = np.sqrt(gx * gx + gy * gy).reshape(-1)
        # Unsigned orientation in [0, pi); np.mod is avoided, it is ~50x slower than a where.
        theta = np.arctan2(gy, gx).reshape(-1)
        theta = np.where(theta < 0, theta + np.float32(math.pi), theta)
        pos = theta * np.float32(N_BINS / math.pi) - np.float32(0.5)
        lower = np.floor(pos)
        frac = pos - lower
        b0 = lower.astype(np.int64)
        b0 = np.where(b0 < 0, N_BINS - 1, np.where(b0 >= N_BINS, b0 - N_BINS, b0))
        b1 = np.where(b0 == N_BINS - 1, 0, b0 + 1)
        base = self._pixel_patch_base(*lightness.shape)
        n = h * w * N_BINS
        hist = np.bincount(base + b0, weights=mag * (1.0 - frac), minlength=n)
        hist += np.bincount(base + b1, weights=mag * frac, minlength=n)
        return self._texture_of(hist.reshape(h, w, N_BINS), _pool_sum(mag.reshape(lightness.shape), p))

    def _texture_of(self, hist: np.ndarray, energy: np.ndarray) -> np.ndarray:
        """The texture block from each patch's soft orientation histogram of gradient
        magnitude ((h, w, bins) float64) and summed magnitude ((h, w) float32)."""
        p = self.patch_size
        hist = hist.astype(np.float32).transpose(2, 0, 1)
        # The floor is in the histogram's units: gradient magnitude summed over the patch.
        norm = np.sqrt((hist * hist).sum(0, keepdims=True) + (GRAD_FLOOR * p * p / 3.0) ** 2)
        hist = hist / norm
        hist = hist - hist.mean(0, keepdims=True)
        energy = np.tanh(energy / (p * p * 4.0 * GRAD_FLOOR))
        return np.concatenate([hist * 1.5, energy[None]])

    def _depth(self, depth: np.ndarray | None, h: int, w: int) -> np.ndarray:
        if depth is None:
            return np.zeros((DEPTH_DIM, h, w), np.float32)
        p = self.patch_size
        valid = (depth > 0) & np.isfinite(depth)
        z = np.where(valid, depth, 0.0).astype(np.float32)
        vf = valid.astype(np.float32)
        gx, gy = _shift_diffs(z)
        inv = 1.0 / np.maximum(z, 1e-6)
        # A central difference needs the pixel and its four neighbours to be valid.
        vp = np.pad(vf, 1, mode="edge")
        gvalid = vf * vp[1:-1, 2:] * vp[1:-1, :-2] * vp[2:, 1:-1] * vp[:-2, 1:-1]
        sums = (_pool_sum(vf, p), _pool_sum(z, p), _pool_sum(z * z, p), _pool_sum(gvalid, p),
                _pool_sum(gx * inv * gvalid, p), _pool_sum(gy * inv * gvalid, p))  # fmt: skip
        return self._depth_of(*sums, w)

    def _depth_of(self, count: np.ndarray, total: np.ndarray, total_sq: np.ndarray, gcount: np.ndarray,
                  gx_sum: np.ndarray, gy_sum: np.ndarray, w: int) -> np.ndarray:  # fmt: skip
        """The depth block from each patch's sums ((h, w) float32 each): valid readings, their
        sum and sum of squares, pixels with a valid central difference, and the depth
        gradient over depth summed over those (x, y)."""
        h = count.shape[0]
        p = self.patch_size
        area = float(p * p)
        has = count >= MIN_DEPTH_COVER * area
        if not has.any():
            return np.zeros((DEPTH_DIM, h, w), np.float32)
        safe = np.maximum(count, 1.0)
        mean = total / safe
        sq = total_sq / safe
        spread = np.sqrt(np.maximum(sq - mean * mean, 0.0)) / np.maximum(mean, 1e-6)
        rel = np.clip(np.log(np.maximum(mean, 1e-6) / np.median(mean[has])), -2.0, 2.0)
        gcount = np.maximum(gcount, 1.0)
        gxm = gx_sum / gcount
        gym = gy_sum / gcount
        focal = FOCAL_FRACTION * w * p
        nx, ny = -focal * gxm, -focal * gym
        nnorm = np.sqrt(nx * nx + ny * ny + 1.0)
        block = np.stack([rel, np.minimum(spread * 5.0, 1.0), nx / nnorm, ny / nnorm])
        return (block * has).astype(np.float32)

    def _resize(self, rgb: np.ndarray, depth: np.ndarray | None, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
        height, width = rgb.shape[:2]
        if (height, width) == size:
            return rgb, depth
        # PIL's bilinear resize widens its kernel when shrinking, i.e. it antialiases.
        rgb = np.asarray(Image.fromarray(rgb).resize((size[1], size[0]), Image.BILINEAR))
        if depth is not None:
            # Nearest keeps invalid (zero) readings from blending into valid ones.
            ys = ((np.arange(size[0]) + 0.5) * height / size[0]).astype(np.int64)
            xs = ((np.arange(size[1]) + 0.5) * width / size[1]).astype(np.int64)
            depth = depth[ys[:, None], xs[None, :]]
        return rgb, depth

    def features(self, rgb: np.ndarray, depth_m: np.ndarray | None, size: tuple[int, int]) -> torch.Tensor:
        h, w = size[0] // self.patch_size, size[1] // self.patch_size
        depth = None if depth_m is None else np.asarray(depth_m, dtype=np.float32)
        rgb, depth = self._resize(np.ascontiguousarray(rgb), depth, size)
        if self.use_numba:
            colour, hist0, hist1, energy, dsums = classical_numba.pixel_passes(rgb, depth, self.patch_size, N_BINS, _NUMBA_TABLES)
            blocks = [
                self._colour_of(colour[:3], colour[3:]),
                self._texture_of(hist0 + hist1, energy),
                np.zeros((DEPTH_DIM, h, w), np.float32) if dsums is None else self._depth_of(*dsums, w),
            ]
        else:
            lab = _lab(rgb)
            blocks = [self._colour(lab), self._texture(lab[0], h, w), self._depth(depth, h, w)]
        blocks = [_cap_norm(b) * weight for b, weight in zip(blocks, BLOCK_WEIGHTS, strict=True)]
        feats = np.concatenate(blocks).transpose(1, 2, 0)
        norm = np.sqrt((feats * feats).sum(-1, keepdims=True))
        feats = (feats / np.maximum(norm, 1e-12)).astype(np.float32)
        return torch.from_numpy(np.ascontiguousarray(feats)).to(self.device)
