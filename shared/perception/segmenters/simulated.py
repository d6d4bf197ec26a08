"""Ground-truth instance masks through a FastSAM-like noise model (synthetic scenes only).

The noise (``SimulatedSegmenterConfig.noise``) is what a learned class-agnostic segmenter does wrong:
boundaries off by a pixel or two, objects cut in two or fused with a neighbour, small objects
missed and a few masks of nothing. Draws are seeded from ``(cfg.seed, frame_index)``, so a
keyframe always gets the same masks; with every noise knob at zero the ground truth comes back
exactly (after the area filter).

The ground truth comes from an :class:`~shared.datasets.ground_truth.InstanceSource` given at
construction (by default the sequence folder of ``keyframe_vl.segmenter.ground_truth``), read
by the keyframe's frame index: no message carries it.
"""

from __future__ import annotations

import logging
import math
from typing import Annotated

import numpy as np
from scipy import ndimage

from shared.datasets.ground_truth import GroundTruthError, InstanceSource, SequenceGroundTruth
from shared.perception import KeyframeImage, Masks
from shared.perception.segmenters.base import check_image, finalize
from shared.perception.segmenters.simulated_config import (
    SimulatedSegmenterConfig,
    SimulatedSegmenterNoise,
)

log = logging.getLogger(__name__)

_JITTER_SMOOTH_PX = 3.0
"""Correlation length of the local part of the boundary jitter: wiggles, not pixel salt."""
_SPURIOUS_MAX_FRAC = 0.03
"""Largest spurious blob, as a share of the image."""

Mask = Annotated[np.ndarray, "(H, W) bool"]


def _rng(seed: int, frame_index: int) -> np.random.Generator:
    # SeedSequence wants non-negative entries; the modulo keeps negative ints distinct and valid.
    return np.random.default_rng(np.random.SeedSequence([seed % 2**64, frame_index % 2**64]))


def _touching_pairs(gt: Annotated[np.ndarray, "(H, W) int"]) -> set[tuple[int, int]]:
    """Unordered pairs of object ids that share a 4-neighbour edge."""
    pairs = []
    for a, b in ((gt[:, :-1], gt[:, 1:]), (gt[:-1, :], gt[1:, :])):
        sel = (a != b) & (a >= 0) & (b >= 0)
        lo = np.minimum(a[sel], b[sel])
        hi = np.maximum(a[sel], b[sel])
        pairs.append(np.stack([lo, hi], axis=1))
    both = np.unique(np.concatenate(pairs), axis=0) if pairs else np.zeros((0, 2), int)
    return {(int(p), int(q)) for p, q in both}


def _merge_groups(
    ids: list[int], touching: set[tuple[int, int]], prob: float, rng: np.random.Generator
) -> list[list[int]]:
    """Each object, visited in random order, fuses with prob ``prob`` with one touching object
    that is still on its own; every object ends in exactly one group."""
    if prob <= 0:
        return [[i] for i in ids]
    free = set(ids)
    groups: list[list[int]] = []
    for i in (ids[j] for j in rng.permutation(len(ids))):
        if i not in free:
            continue
        free.discard(i)
        partners = sorted(j for j in free if (min(i, j), max(i, j)) in touching)
        if partners and rng.random() < prob:
            j = partners[int(rng.integers(len(partners)))]
            free.discard(j)
            groups.append([i, j])
        else:
            groups.append([i])
    return groups


def _split(mask: Mask) -> tuple[Mask, Mask]:
    """Cut a mask in two across its principal (longest) axis, through its centroid."""
    ys, xs = np.nonzero(mask)
    pts = np.stack([xs, ys], axis=1).astype(np.float64)
    centred = pts - pts.mean(axis=0)
    cov = centred.T @ centred
    _, vecs = np.linalg.eigh(cov)
    side = centred @ vecs[:, -1] > 0
    a = np.zeros_like(mask)
    b = np.zeros_like(mask)
    a[ys[side], xs[side]] = True
    b[ys[~side], xs[~side]] = True
    return a, b


def _jitter(mask: Mask, std: float, rng: np.random.Generator) -> Mask:
    """Move the boundary by a random signed distance: one shift for the whole mask plus a
    smooth local wiggle, each carrying half the variance of ``std``."""
    if std <= 0 or not mask.any():
        return mask
    limit = 4.0 * std
    pad = int(math.ceil(limit)) + 2
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    y0, y1 = max(int(ys.min()) - pad, 0), min(int(ys.max()) + pad + 1, h)
    x0, x1 = max(int(xs.min()) - pad, 0), min(int(xs.max()) + pad + 1, w)
    crop = mask[y0:y1, x0:x1]
    part = std / math.sqrt(2.0)
    local = ndimage.gaussian_filter(rng.standard_normal(crop.shape), _JITTER_SMOOTH_PX, mode="reflect")
    spread = float(local.std())
    local = local / spread * part if spread > 0 else np.zeros_like(local)
    shift = np.clip(rng.normal(0.0, part) + local, -limit, limit)
    # Signed distance from pixel centres to the boundary, which lies half a pixel out.
    inside = ndimage.distance_transform_edt(crop)
    outside = ndimage.distance_transform_edt(~crop)
    signed = np.where(crop, 0.5 - inside, outside - 0.5)
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = signed < shift
    return out


def _blob(h: int, w: int, min_area: float, rng: np.random.Generator) -> Mask:
    """A random ellipse somewhere in the image."""
    hi = max(_SPURIOUS_MAX_FRAC * h * w, min_area * 1.5)
    area = math.exp(rng.uniform(math.log(min_area), math.log(hi)))
    aspect = rng.uniform(0.5, 2.0)
    a = math.sqrt(area * aspect / math.pi)
    b = math.sqrt(area / (aspect * math.pi))
    cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    theta = rng.uniform(0, math.pi)
    yy, xx = np.mgrid[0:h, 0:w]
    dx, dy = xx - cx, yy - cy
    u = dx * math.cos(theta) + dy * math.sin(theta)
    v = -dx * math.sin(theta) + dy * math.cos(theta)
    return (u / a) ** 2 + (v / b) ** 2 <= 1.0


class SimulatedSegmenter:
    """Noisy ground-truth masks of the keyframe's frame, from its ground-truth source."""

    name = "simulated"

    def __init__(self, cfg: SimulatedSegmenterConfig, ground_truth: InstanceSource | None = None) -> None:
        self.cfg = cfg
        self.ground_truth = ground_truth if ground_truth is not None else SequenceGroundTruth(
            cfg.ground_truth, field="keyframe_vl.segmenter.ground_truth", user="simulated segmenter"
        )

    def segment(self, image: KeyframeImage) -> Masks:
        h, w = check_image(image.rgb)
        try:
            gt = np.asarray(self.ground_truth.frame_instances(image.frame_index))
        except GroundTruthError as exc:
            raise GroundTruthError(f"keyframe {image.frame_index}: the simulated segmenter has no ground truth: {exc}") from None
        if gt.shape != (h, w):
            raise GroundTruthError(
                f"keyframe {image.frame_index}: the ground-truth instances are {gt.shape[1]}x{gt.shape[0]} but the image is "
                f"{w}x{h}: is keyframe_vl.segmenter.ground_truth the sequence being replayed?"
            )
        noise: SimulatedSegmenterNoise = self.cfg.noise
        rng = _rng(self.cfg.seed, image.frame_index)

        ids, areas = np.unique(gt[gt >= 0], return_counts=True)
        miss_below = noise.miss_below_px if noise.miss_below_px is not None else noise.miss_below_frac * h * w
        seen = [int(i) for i, a in zip(ids, areas, strict=True) if a >= miss_below]
        touching = _touching_pairs(gt) if noise.merge_prob > 0 else set()
        groups = _merge_groups(seen, touching, noise.merge_prob, rng)

        masks: list[Mask] = []
        for group in groups:
            whole = gt == group[0] if len(group) == 1 else np.isin(gt, group)
            parts = list(_split(whole)) if noise.split_prob > 0 and rng.random() < noise.split_prob else [whole]
            masks.extend(_jitter(m, noise.boundary_jitter_px, rng) for m in parts)
        scores = list(rng.uniform(0.5, 1.0, len(masks)))

        n_spurious = int(rng.poisson(noise.spurious_per_frame)) if noise.spurious_per_frame > 0 else 0
        min_blob = float(max(self.cfg.min_area_px, 30))
        for _ in range(n_spurious):
            masks.append(_blob(h, w, min_blob, rng))
            scores.append(float(rng.uniform(0.05, 0.5)))

        log.debug(
            "frame %d: %d objects, %d missed, %d masks (%d spurious)",
            image.frame_index, len(ids), len(ids) - len(seen), len(masks), n_spurious,
        )
        if not masks:
            return Masks.empty(h, w)
        return finalize(np.stack(masks), np.asarray(scores), self.cfg)
