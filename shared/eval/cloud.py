"""Point-cloud helpers shared by the metrics: voxel downsampling with an instance vote (on
Open3D's voxel grid), nearest-neighbour transfer of predicted instances onto ground-truth
points, and OpenLex3D's two mask alignments."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from scipy.spatial import cKDTree

Alignment = Literal["per_mask", "global"]
ALIGNMENTS: tuple[str, ...] = ("per_mask", "global")
"""OpenLex3D's mask alignment modes (``masks.alignment_mode`` of its ``eval_query.yaml``)."""


# ---------------------------------------------------------------------------- precision


def exact_in_float32(points: Annotated[np.ndarray, "(M, 3) float"]) -> bool:
    """Is every coordinate a float32 value (as in a float32 PCD read into float64)?"""
    p = np.asarray(points)
    if p.dtype == np.float32:
        return True
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.array_equal(p.astype(np.float32).astype(p.dtype), p))


def cloud_file_dtype(path: str | Path) -> np.dtype | None:
    """The dtype Open3D's tensor reader gives the positions of a .pcd or .ply file, read from
    its header (float32 or float64); None when the header does not say (then the caller
    infers it from the values, see :func:`positions_dtype`)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError:
        return None
    text = head.decode("latin-1")
    if path.suffix == ".pcd":
        fields = re.search(r"^FIELDS\s+(.+)$", text, flags=re.MULTILINE)
        sizes = re.search(r"^SIZE\s+(.+)$", text, flags=re.MULTILINE)
        types = re.search(r"^TYPE\s+(.+)$", text, flags=re.MULTILINE)
        if not (fields and sizes and types):
            return None
        names, size, kind = fields.group(1).split(), sizes.group(1).split(), types.group(1).split()
        if "x" not in names or len(size) != len(names) or len(kind) != len(names):
            return None
        i = names.index("x")
        return {("F", "4"): np.dtype(np.float32), ("F", "8"): np.dtype(np.float64)}.get((kind[i], size[i]))
    if path.suffix == ".ply":
        m = re.search(r"^property\s+(\w+)\s+x\s*$", text.split("end_header")[0], flags=re.MULTILINE)
        if m is None:
            return None
        return {"float": np.dtype(np.float32), "float32": np.dtype(np.float32),
                "double": np.dtype(np.float64), "float64": np.dtype(np.float64)}.get(m.group(1))  # fmt: skip
    return None


def positions_dtype(points: Annotated[np.ndarray, "(M, 3) float"], stored: np.dtype | None = None) -> np.dtype:
    """The precision Open3D computes a cloud's voxel grid in: that of the stored positions
    when known, else float32 when every coordinate is a float32 value, else float64."""
    if stored is not None:
        return np.dtype(stored)
    return np.dtype(np.float32) if exact_in_float32(points) else np.dtype(np.float64)


# ---------------------------------------------------------------------------- downsampling


def voxel_cells(
    points: Annotated[np.ndarray, "(M, 3) float"],
    voxel: float,
    dtype: np.dtype | None = None,
) -> Annotated[np.ndarray, "(M, 3) int64"]:
    """Open3D's voxel of each point (``t.geometry.PointCloud.voxel_down_sample``, which
    OpenLex3D calls): ``floor(p / voxel)`` with ``p`` and ``voxel`` in the positions' own
    precision (``dtype``, see :func:`positions_dtype`). The precision matters: float32
    0.35 (0.3499999940...) / float32 0.05 rounds to 7.0, its float64 quotient is 6.99999988."""
    dt = positions_dtype(points) if dtype is None else np.dtype(dtype)
    p = np.asarray(points).astype(dt, copy=False)
    return np.floor(p / dt.type(voxel)).astype(np.int64)


def voxel_downsample(
    points: Annotated[np.ndarray, "(M, 3) float"],
    instance: Annotated[np.ndarray, "(M,) int"],
    voxel: float,
    *,
    dtype: np.dtype | None = None,
) -> tuple[Annotated[np.ndarray, "(V, 3) float64 centroids"], Annotated[np.ndarray, "(V,) int64"]]:
    """One point per occupied voxel of size ``voxel`` (the cells of :func:`voxel_cells`): the
    centroid of the voxel's points, rounded to float32 as Open3D keeps it, carrying the
    instance most of them belong to (ties: the lowest instance number)."""
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    points = np.asarray(points, np.float64)
    keys = voxel_cells(points, voxel, dtype)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]  # one int64 per cell
    _, vox = np.unique(flat, return_inverse=True)
    vox = vox.reshape(-1)
    n_vox = int(vox.max()) + 1
    counts = np.bincount(vox, minlength=n_vox).astype(np.float64)
    centroids = np.stack([np.bincount(vox, weights=points[:, d], minlength=n_vox) for d in range(3)], axis=1)
    centroids /= counts[:, None]
    # Open3D averages in float32 whatever the cloud's dtype; rounding the exact mean to
    # float32 lands within a float32 step of its result (its summation order is its own).
    centroids = centroids.astype(np.float32).astype(np.float64)
    inst = np.asarray(instance, np.int64)
    n_inst = int(inst.max()) + 1
    pair, pair_counts = np.unique(vox * n_inst + inst, return_counts=True)
    p_vox, p_inst = pair // n_inst, pair % n_inst
    # Sort by voxel, then by descending count, then by instance; the first row per voxel wins.
    order = np.lexsort((p_inst, -pair_counts, p_vox))
    p_vox, p_inst = p_vox[order], p_inst[order]
    first = np.ones(len(order), bool)
    first[1:] = p_vox[1:] != p_vox[:-1]
    majority = np.empty(n_vox, np.int64)
    majority[p_vox[first]] = p_inst[first]
    return centroids, majority


# ---------------------------------------------------------------------------- nearest points


def nearest(
    reference: Annotated[np.ndarray, "(M, 3) float"],
    queries: Annotated[np.ndarray, "(N, 3) float"],
) -> tuple[Annotated[np.ndarray, "(N,) float64 distance (inf if M = 0)"], Annotated[np.ndarray, "(N,) int64 (-1 if M = 0)"]]:
    """Each query point's nearest reference point."""
    if len(reference) == 0:
        return np.full(len(queries), np.inf), np.full(len(queries), -1, np.int64)
    if len(queries) == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    dist, idx = cKDTree(reference).query(queries, k=1, workers=-1)
    return np.asarray(dist, np.float64), np.asarray(idx, np.int64)


def transfer_instances(
    pred_points: Annotated[np.ndarray, "(M, 3) float"],
    pred_instance: Annotated[np.ndarray, "(M,) int"],
    gt_points: Annotated[np.ndarray, "(N, 3) float"],
    radius: float,
) -> Annotated[np.ndarray, "(N,) int64, -1 = no predicted point within radius"]:
    """The instance of each ground-truth point's nearest predicted point, if nearer than the
    Euclidean ``radius`` (one instance per point; OpenLex3D's "global" alignment compares a
    squared distance instead, see :func:`align_instances`)."""
    dist, idx = nearest(pred_points, gt_points)
    out = np.full(len(gt_points), -1, np.int64)
    ok = dist < radius
    out[ok] = np.asarray(pred_instance, np.int64)[idx[ok]]
    return out


def _squared(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = a - b
    return np.einsum("ij,ij->i", d, d)


def check_alignment(mode: str, threshold: float) -> None:
    """Refuse an alignment mode other than :data:`ALIGNMENTS` or a threshold that is not a
    positive finite squared distance (ValueError naming what was expected)."""
    if mode not in ALIGNMENTS:
        raise ValueError(f"alignment must be one of {', '.join(ALIGNMENTS)} (got {mode!r})")
    try:
        ok = math.isfinite(float(threshold)) and float(threshold) > 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"alignment_threshold must be a positive squared distance in m² (got {threshold!r})")


def align_instances(
    pred_points: Annotated[np.ndarray, "(M, 3) float"],
    pred_instance: Annotated[np.ndarray, "(M,) int, negative = none"],
    gt_points: Annotated[np.ndarray, "(N, 3) float"],
    threshold: float,
    mode: Alignment = "per_mask",
) -> tuple[Annotated[np.ndarray, "(P,) int64 ground-truth point"], Annotated[np.ndarray, "(P,) int64 instance"]]:
    """OpenLex3D's mask alignment (``core/align_masks.py``): the (ground-truth point,
    predicted instance) pairs it assigns, each pair once.

    ``threshold`` is compared, strictly, with the *squared* Euclidean distance (FAISS
    ``IndexFlatL2`` returns squared distances), so 0.001 m² admits points nearer than
    sqrt(0.001) = 3.16 cm. Both clouds are rounded to float32 first, as OpenLex3D does.

    - ``per_mask``: a ground-truth point belongs to every instance that has a point within
      the threshold, so it may belong to several (neighbouring instances overlap).
    - ``global``: a ground-truth point belongs to the instance of its single nearest predicted
      point, if that is within the threshold.
    """
    check_alignment(mode, threshold)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(pred_points) == 0 or len(gt_points) == 0:
        return empty
    pred = np.asarray(pred_points, np.float32).astype(np.float64)
    gt = np.asarray(gt_points, np.float32).astype(np.float64)
    inst = np.asarray(pred_instance, np.int64)
    # cKDTree finds the neighbour; the decision is taken on its exact squared distance, so
    # its bound only needs to be a little wider than the threshold's radius.
    bound = math.sqrt(threshold) * (1.0 + 1e-6)
    if mode == "global":
        dist, idx = cKDTree(pred).query(gt, k=1, distance_upper_bound=bound, workers=-1)
        near = np.flatnonzero(np.isfinite(dist))
        near = near[_squared(gt[near], pred[idx[near]]) < threshold]
        owner = inst[idx[near]]
        keep = owner >= 0
        return near[keep].astype(np.int64), owner[keep]
    # per_mask: one search per instance, over the ground-truth points inside its padded box
    # (found through the x-sorted ground truth) rather than over all of them.
    by_x = np.argsort(gt[:, 0], kind="stable")
    xs = gt[by_x, 0]
    order = np.argsort(inst, kind="stable")
    ids, starts = np.unique(inst[order], return_index=True)
    ends = np.append(starts[1:], len(order))
    points_out, inst_out = [], []
    for iid, s, e in zip(ids, starts, ends, strict=True):
        if iid < 0:
            continue
        pts = pred[order[s:e]]
        lo, hi = pts.min(axis=0) - bound, pts.max(axis=0) + bound
        a, b = np.searchsorted(xs, lo[0], side="left"), np.searchsorted(xs, hi[0], side="right")
        cand = by_x[a:b]
        cand = cand[np.all((gt[cand] >= lo) & (gt[cand] <= hi), axis=1)]
        if len(cand) == 0:
            continue
        dist, idx = cKDTree(pts).query(gt[cand], k=1, distance_upper_bound=bound)
        ok = np.isfinite(dist)
        cand, idx = cand[ok], idx[ok]
        hit = np.sort(cand[_squared(gt[cand], pts[idx]) < threshold])
        points_out.append(hit)
        inst_out.append(np.full(len(hit), iid, np.int64))
    if not points_out:
        return empty
    return np.concatenate(points_out).astype(np.int64), np.concatenate(inst_out)


def contingency(
    a: Annotated[np.ndarray, "(N,) int, negative = none"],
    n_a: int,
    b: Annotated[np.ndarray, "(N,) int, negative = none"],
    n_b: int,
) -> Annotated[np.ndarray, "(n_a, n_b) int64"]:
    """Counts of points per (a, b) pair of non-negative labels."""
    ok = (a >= 0) & (b >= 0)
    flat = a[ok].astype(np.int64) * n_b + b[ok].astype(np.int64)
    return np.bincount(flat, minlength=n_a * n_b).reshape(n_a, n_b)
