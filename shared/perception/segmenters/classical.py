"""Class-agnostic RGB-D segmentation without learned weights.

The image is reduced by an integer factor to at least ``graph_width`` pixels across,
and a 4- or 8-neighbour pixel graph gets edge weights from three cues:

- colour: CIE Lab distance of the blurred image, which follows perceived colour steps;
- depth: the step in inverse depth that the neighbouring steps along the same line do not
  explain, relative to depth. Inverse depth is affine across a plane in the image, so floors
  seen at grazing angles (large but steady steps) cost nothing while an object's silhouette
  against what lies behind it does;
- normals: the angle between the surface normals of the two back-projected pixels, which
  separates touching surfaces at a crease (a box on the floor) where depth is continuous.

Felzenszwalb-Huttenlocher merging (:mod:`.graph`) turns the graph into regions, small ones join
their most similar neighbour, and each region becomes one mask scored by how much its boundary
stands out against its inside.
"""

from __future__ import annotations

import functools
import logging
import math
from typing import Annotated

import numpy as np
from scipy import ndimage

from shared.geometry import Intrinsics
from shared.perception import KeyframeImage, Masks
from shared.perception.segmenters.base import check_image, finalize_labels
from shared.perception.segmenters.classical_config import ClassicalSegmenterConfig
from shared.perception.segmenters.graph import (
    Edges,
    absorb_small,
    boundary_contrast,
    felzenszwalb,
)

log = logging.getLogger(__name__)

_K_AREA_UNIT = 1e-3
"""``k`` is given per thousandth of the image, so one setting fits any graph resolution."""

Grid = Annotated[np.ndarray, "(h, w) float"]


def rgb_to_lab(rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]) -> Annotated[np.ndarray, "(H, W, 3) float32 L*a*b*"]:
    """sRGB (D65) to CIE L*a*b*."""
    c = rgb.astype(np.float32) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array(
        [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]],
        np.float32,
    )
    xyz = lin @ m.T / np.array([0.95047, 1.0, 1.08883], np.float32)
    eps = 216 / 24389
    f = np.where(xyz > eps, np.cbrt(xyz), (24389 / 27 * xyz + 16) / 116)
    lab = np.empty_like(f)
    lab[..., 0] = 116 * f[..., 1] - 16
    lab[..., 1] = 500 * (f[..., 0] - f[..., 1])
    lab[..., 2] = 200 * (f[..., 1] - f[..., 2])
    return lab


def _factor(w: int, graph_width: int) -> int:
    """Integer reduction keeping at least ``graph_width`` pixels across. Integer, so the graph
    samples the image on a regular grid: inverse depth stays affine across planes there, which
    the depth cue relies on (uneven spacing reads as steps on every slanted surface)."""
    return max(1, w // graph_width)


def _reduce_rgb(rgb: np.ndarray, f: int, gh: int, gw: int) -> np.ndarray:
    """Mean colour of each f x f block (an anti-aliased reduction)."""
    if f == 1:
        return rgb
    blocks = rgb[: gh * f, : gw * f].reshape(gh, f, gw, f, 3).astype(np.float32)
    return np.round(blocks.mean(axis=(1, 3))).astype(np.uint8)


def _reduced_intrinsics(K: Intrinsics, f: int, gh: int, gw: int) -> Intrinsics:
    """Camera of the pixels ``(f * j + f // 2, f * i + f // 2)`` that the reduced depth samples."""
    o = f // 2
    return Intrinsics(fx=K.fx / f, fy=K.fy / f, cx=(K.cx - o) / f, cy=(K.cy - o) / f, width=gw, height=gh)


def _shifted(padded: np.ndarray, pad: int, h: int, w: int, dy: int, dx: int) -> np.ndarray:
    """``out[y, x] = original[y + dy, x + dx]`` for the unpadded grid (padding fills outside)."""
    return padded[pad + dy : pad + dy + h, pad + dx : pad + dx + w]


def _points(depth: Grid, K: Intrinsics) -> Annotated[np.ndarray, "(h, w, 3) float camera frame"]:
    h, w = depth.shape
    u = (np.arange(w) - K.cx) / K.fx
    v = (np.arange(h) - K.cy) / K.fy
    return np.stack([u[None, :] * depth, v[:, None] * depth, depth], axis=-1)


def _tangent(pad: np.ndarray, h: int, w: int, dy: int, dx: int) -> np.ndarray:
    """Edge-aware difference along (dy, dx) of points padded by 2: the forward or backward step,
    whichever continues straighter into the next one. A pixel on a crease or beside a
    silhouette then takes the tangent of one surface, not an average of two, so the normal
    flips across one edge instead of bending over several (each cheap enough to merge)."""
    at = lambda k: _shifted(pad, 2, h, w, k * dy, k * dx)  # noqa: E731
    p0, f1, f2, b1, b2 = at(0), at(1), at(2), at(-1), at(-2)
    fwd, bwd = f1 - p0, p0 - b1
    bend_f = np.linalg.norm((f2 - f1) - fwd, axis=-1)
    bend_b = np.linalg.norm((b1 - b2) - bwd, axis=-1)
    # NaN (outside the image or no depth) never wins the comparison.
    use_fwd = np.nan_to_num(bend_f, nan=np.inf) <= np.nan_to_num(bend_b, nan=np.inf)
    return np.where(use_fwd[..., None], fwd, bwd)


def _normals(pts: np.ndarray, depth: Grid) -> Annotated[np.ndarray, "(h, w, 3) float, zero where unknown"]:
    """Unit normals facing the camera from edge-aware tangents of the back-projected points."""
    h, w = depth.shape
    pad = np.pad(np.where((depth > 0)[..., None], pts, np.nan), ((2, 2), (2, 2), (0, 0)), constant_values=np.nan)
    n = np.cross(_tangent(pad, h, w, 0, 1), _tangent(pad, h, w, 1, 0))
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = np.isfinite(norm[..., 0]) & (norm[..., 0] > 0)
    n = np.where(ok[..., None], n / np.where(ok[..., None], norm, 1.0), 0.0)
    # x right, y down, z forward: d/du x d/dv points away from the camera; flip it towards it.
    return -n


def _along(arr: np.ndarray, k: int, pad: int, span: tuple[int, int, int, int], step: tuple[int, int]) -> np.ndarray:
    """For edges whose first pixels fill rows y0:y1 and columns x0:x1 (``span``) and run along
    ``step``, the k-th pixel from each first pixel, out of an array padded by ``pad``."""
    (y0, y1, x0, x1), (dy, dx) = span, step
    return arr[pad + y0 + k * dy : pad + y1 + k * dy, pad + x0 + k * dx : pad + x1 + k * dx]


def _directions(connectivity: int) -> list[tuple[int, int]]:
    return [(0, 1), (1, 0)] if connectivity == 4 else [(0, 1), (1, 0), (1, 1), (1, -1)]


def edge_weights(
    lab: Annotated[np.ndarray, "(h, w, 3) float"],
    depth: Grid | None,
    K: Intrinsics | None,
    cfg: ClassicalSegmenterConfig,
) -> Edges:
    """The weighted pixel graph of one (already reduced) image."""
    h, w = lab.shape[:2]
    node = np.arange(h * w).reshape(h, w)
    pad = 2
    f32 = np.float32

    def padded(a: np.ndarray, value: float) -> np.ndarray:
        widths = ((pad, pad), (pad, pad)) + (((0, 0),) if a.ndim == 3 else ())
        return np.pad(a.astype(f32), widths, mode="constant", constant_values=value)

    lab_p = padded(lab * np.array([cfg.lightness_weight, 1.0, 1.0], dtype=f32), 0.0)
    use_depth = depth is not None and bool((depth > 0).any()) and (cfg.depth_weight > 0 or cfg.normal_weight > 0)
    use_normals = use_depth and K is not None and cfg.normal_weight > 0
    if use_depth:
        inv_p = padded(np.where(depth > 0, 1.0 / np.where(depth > 0, depth, 1.0), np.nan), np.nan)
    if use_normals:
        pts = _points(depth, K)
        nrm = _normals(pts, depth)
        nrm_p, pts_p = padded(nrm, 0.0), padded(pts, 0.0)
        known_p = np.pad((np.abs(nrm).sum(-1) > 0), pad, mode="constant")

    a_all, b_all, w_all = [], [], []
    for dy, dx in _directions(cfg.connectivity):
        y0, y1 = 0, h - dy
        x0, x1 = max(0, -dx), w - max(0, dx)

        at = functools.partial(_along, pad=pad, span=(y0, y1, x0, x1), step=(dy, dx))
        weight = (cfg.colour_weight / 100.0) * np.linalg.norm(at(lab_p, 1) - at(lab_p, 0), axis=-1)
        if use_depth:
            prev, p, q, nxt = (at(inv_p, k) for k in (-1, 0, 1, 2))
            step = q - p
            with np.errstate(invalid="ignore"):
                unexplained = np.fmin(np.abs(step - (p - prev)), np.abs(step - (nxt - q)))
                unexplained = np.where(np.isnan(unexplained), np.abs(step), unexplained)
                rel = unexplained / np.fmin(p, q)
            weight += f32(cfg.depth_weight) * np.nan_to_num(rel, nan=0.0)
        if use_normals:
            n_p, n_q = at(nrm_p, 0), at(nrm_p, 1)
            cos = np.clip(np.einsum("ijk,ijk->ij", n_p, n_q), -1.0, 1.0)
            angle = np.where(at(known_p, 0) & at(known_p, 1), np.arccos(cos), f32(0))
            # Local convexity (as in LCCP): the crease is convex when the normals open away
            # from each other along the line joining the points, (n_p - n_q) . (x_p - x_q) > 0.
            convex = np.einsum("ijk,ijk->ij", n_p - n_q, at(pts_p, 0) - at(pts_p, 1)) > 0
            weight += f32(cfg.normal_weight) * np.where(convex, f32(cfg.convex_factor), f32(1)) * angle
        a_all.append(node[y0:y1, x0:x1].reshape(-1))
        b_all.append(node[y0 + dy : y1 + dy, x0 + dx : x1 + dx].reshape(-1))
        w_all.append(weight.reshape(-1))
    return Edges.sorted(np.concatenate(a_all), np.concatenate(b_all), np.concatenate(w_all))


def segment_labels(
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
    depth_m: Annotated[np.ndarray, "(H, W) float metres, 0 = none"] | None,
    intrinsics: Intrinsics | None,
    cfg: ClassicalSegmenterConfig,
) -> tuple[Annotated[np.ndarray, "(H, W) int64 region"], Annotated[np.ndarray, "(R,) float32 score"]]:
    """A full-resolution partition of the image into regions and a score per region."""
    h, w = rgb.shape[:2]
    f = _factor(w, cfg.graph_width)
    gh, gw = max(h // f, 1), w // f
    lab = rgb_to_lab(_reduce_rgb(rgb, f, gh, gw))
    if cfg.smooth_sigma > 0:
        lab = ndimage.gaussian_filter(lab, (cfg.smooth_sigma, cfg.smooth_sigma, 0), mode="nearest")
    depth = None
    K = None
    if depth_m is not None:
        if depth_m.shape != (h, w):
            raise ValueError(f"depth is {depth_m.shape} but the image is {(h, w)}")
        # Point samples, not block means: a mean across a silhouette invents depths in between.
        o = f // 2
        depth = np.asarray(depth_m[o::f, o::f][:gh, :gw], dtype=np.float64)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
        if intrinsics is not None:
            if (intrinsics.width, intrinsics.height) != (w, h):
                raise ValueError(f"intrinsics are for {intrinsics.width}x{intrinsics.height}, the image is {w}x{h}")
            K = _reduced_intrinsics(intrinsics, f, gh, gw)
    edges = edge_weights(lab, depth, K, cfg)
    n = gh * gw
    k_nodes = cfg.k * _K_AREA_UNIT * n
    part = felzenszwalb(n, edges, k_nodes)
    part = absorb_small(
        part,
        edges,
        int(math.ceil(cfg.min_region_frac * n)),
        cfg.min_region_width,
        edges_per_node=2 if cfg.connectivity == 4 else 6,
    )
    contrast = boundary_contrast(part, edges)
    score = contrast / (contrast + part.internal + 1e-6)
    labels = part.label.reshape(gh, gw)
    if (gh, gw) != (h, w):
        # Pixels past the last whole block (when f does not divide the size) take its label.
        labels = labels[np.ix_(np.minimum(np.arange(h) // f, gh - 1), np.minimum(np.arange(w) // f, gw - 1))]
    return labels, score.astype(np.float32)


class ClassicalSegmenter:
    """Graph-based RGB-D segmentation; uses depth and intrinsics when the keyframe has them."""

    name = "classical"

    def __init__(self, cfg: ClassicalSegmenterConfig) -> None:
        self.cfg = cfg

    def segment(self, image: KeyframeImage) -> Masks:
        check_image(image.rgb)
        labels, scores = segment_labels(image.rgb, image.depth_m, image.intrinsics, self.cfg)
        masks = finalize_labels(labels, scores, self.cfg)
        log.debug("frame %d: %d regions, %d masks", image.frame_index, len(scores), len(masks))
        return masks
