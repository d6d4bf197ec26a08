"""3D footprints of source tracks: where a lost track should appear in a later keyframe.

A track's footprint is a sample of the world points under the keyframe masks assigned to it
(back-projected with each keyframe's depth, intrinsics and pose, merged over keyframes and
thinned on a voxel grid), i.e. the surface seen of the object so far. Projected into a later
keyframe, with a depth test against that keyframe's depth, it gives the pixels the object
would cover if it is still there: a predicted mask for tracks that propagation no longer
carries, compared with the detections under the same gates as propagated masks (eq. 3).
The deviation from the paper that this serves is described in ``services.tracker.core``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from scipy import ndimage

from shared.geometry import Intrinsics

MAX_POINTS = 1500
"""Points sampled from one mask: it is sampled on a regular pixel grid at this size."""
MAX_MERGED_POINTS = 4000
"""Points kept per track over all its keyframe masks (voxel-thinned beyond this)."""
MIN_VISIBLE = 8
"""A footprint with fewer points in view (and not occluded) predicts no mask."""
OCCLUSION_ABS_M = 0.05
OCCLUSION_REL = 0.05
"""A projected point counts as hidden when it lies more than ``abs + rel x observed depth``
behind the keyframe's depth at its pixel: the slack absorbs depth noise and the sampling of
slanted surfaces, not the thickness of occluders."""
MAX_CLOSING_PX = 32
"""Cap on the gap filling between projected samples (a footprint seen from very close)."""

Pose = Annotated[np.ndarray, "(4, 4) float64 camera-to-world"]


@dataclass(frozen=True)
class Footprint:
    """World points of one or more masks of a track and their sampling step."""

    points: Annotated[np.ndarray, "(N, 3) float32 world"]
    spacing_m: float
    """World distance between neighbouring samples at the points' median depth."""


def mask_footprint(
    mask: Annotated[np.ndarray, "(H, W) bool"],
    depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 = none"],
    K: Intrinsics,
    T_world_cam: Pose,
    max_points: int = MAX_POINTS,
    box: tuple[int, int, int, int] | None = None,
) -> Footprint | None:
    """The mask's pixels with a depth reading, sampled every s pixels in x and y so at most
    about ``max_points`` remain, in world coordinates. None without any valid depth.
    ``box`` (y0, y1, x0, x1): where the mask's pixels are, so only that part is read."""
    y0, y1, x0, x1 = (0, mask.shape[0], 0, mask.shape[1]) if box is None else box
    d = depth_m[y0:y1, x0:x1]
    valid = mask[y0:y1, x0:x1] & (d > 0) & np.isfinite(d)
    n = int(valid.sum())
    if n == 0:
        return None
    step = max(1, math.ceil(math.sqrt(n / max_points)))
    if step > 1:
        # every step-th row and column of the image (not of the box)
        grid = np.zeros_like(valid)
        grid[(-y0) % step :: step, (-x0) % step :: step] = True
        sampled = valid & grid
        # A thin mask can fall between the grid lines: keep it whole rather than lose it.
        if sampled.any():
            valid = sampled
    ys, xs = np.nonzero(valid)
    ys, xs = ys + y0, xs + x0
    z = depth_m[ys, xs].astype(np.float64)
    cam = np.stack([(xs - K.cx) / K.fx * z, (ys - K.cy) / K.fy * z, z], axis=1)
    world = cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    spacing = step * float(np.median(z)) / K.fx
    return Footprint(world.astype(np.float32), spacing)


def merge_footprints(old: Footprint | None, new: Footprint | None, max_points: int = MAX_MERGED_POINTS) -> Footprint | None:
    """The union of two footprints of one track (the surfaces seen from several keyframes),
    thinned on a voxel grid that doubles until at most ``max_points`` points remain."""
    if old is None or new is None:
        return new if old is None else old
    points = np.concatenate([new.points, old.points])
    spacing = max(old.spacing_m, new.spacing_m)
    if len(points) <= max_points:
        return Footprint(points, spacing)
    voxel = max(spacing, 1e-3)
    while True:
        keys = np.floor(points / voxel).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        if len(first) <= max_points:
            break
        voxel *= 2.0
    # The first occurrence favours the newest view, which comes first in ``points``.
    return Footprint(points[np.sort(first)], max(spacing, voxel))


def project_footprint(
    fp: Footprint,
    depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 = none"],
    K: Intrinsics,
    T_world_cam: Pose,
) -> Annotated[np.ndarray, "(H, W) bool"]:
    """The pixels the footprint covers in a view, hidden points removed; gaps between the
    projected samples are closed at the scale the sampling step has at the new distance."""
    H, W = depth_m.shape
    out = np.zeros((H, W), bool)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    cam = (fp.points.astype(np.float64) - t) @ R
    z = cam[:, 2]
    front = z > 1e-3
    if not front.any():
        return out
    cam, z = cam[front], z[front]
    u = np.floor(cam[:, 0] / z * K.fx + K.cx + 0.5).astype(np.int64)
    v = np.floor(cam[:, 1] / z * K.fy + K.cy + 0.5).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v, z = u[inside], v[inside], z[inside]
    if len(u) < MIN_VISIBLE:
        return out
    d = depth_m[v, u]
    slack = OCCLUSION_ABS_M + OCCLUSION_REL * d
    # Behind the observed surface: hidden. In front of it: the camera sees through the place
    # where the point was, so the object is not there any more (or never was); both are dropped.
    seen = (d <= 0) | (np.abs(z - d) <= slack)
    u, v, z = u[seen], v[seen], z[seen]
    if len(u) < MIN_VISIBLE:
        return out
    out[v, u] = True
    gap = fp.spacing_m * K.fx / float(np.median(z))
    # Closing with an odd square (it fills holes narrower than its side) as separable max and
    # min filters: the same result as ``binary_closing`` with a square, several times faster.
    size = 2 * math.ceil(min(MAX_CLOSING_PX, gap) / 2) + 1
    if gap > 1.0:
        pad = size + 1
        y0, y1 = max(int(v.min()) - pad, 0), min(int(v.max()) + pad + 1, H)
        x0, x1 = max(int(u.min()) - pad, 0), min(int(u.max()) + pad + 1, W)
        crop = np.pad(out[y0:y1, x0:x1], pad).view(np.uint8)
        grown = ndimage.maximum_filter1d(ndimage.maximum_filter1d(crop, size, axis=0), size, axis=1)
        closed = ndimage.minimum_filter1d(ndimage.minimum_filter1d(grown, size, axis=0), size, axis=1)
        out[y0:y1, x0:x1] = closed[pad:-pad, pad:-pad].astype(bool)
    return out


def support(
    track: Footprint,
    seen: Footprint,
    radius_m: float,
    trees: dict[int, Any] | None = None,
) -> float:
    """Share of the points of ``seen`` (a detection's footprint) that lie within ``radius_m``,
    or within 1.5 sampling steps of either footprint if that is larger, of a point of
    ``track``: the 3D overlap of eq. 8, between a detection and what a track was seen as.
    ``trees``: k-d trees of track footprints built so far (by ``id``), for a caller that
    tests one track against several detections."""
    from scipy.spatial import cKDTree

    if len(seen.points) == 0 or len(track.points) == 0:
        return 0.0
    r = max(radius_m, 1.5 * max(track.spacing_m, seen.spacing_m))
    tree = None if trees is None else trees.get(id(track))
    if tree is None:
        tree = cKDTree(track.points)
        if trees is not None:
            trees[id(track)] = tree
    dist, _ = tree.query(seen.points, k=1, distance_upper_bound=r)
    return float(np.isfinite(dist).mean())
