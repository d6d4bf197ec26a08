"""Point-cloud helpers shared by the metrics: voxel downsampling with an instance vote, and
nearest-neighbour transfer of predicted instances onto ground-truth points."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from scipy.spatial import cKDTree


def voxel_downsample(
    points: Annotated[np.ndarray, "(M, 3) float"],
    instance: Annotated[np.ndarray, "(M,) int"],
    voxel: float,
) -> tuple[Annotated[np.ndarray, "(V, 3) float64 centroids"], Annotated[np.ndarray, "(V,) int64"]]:
    """One point per occupied voxel of size ``voxel`` (grid cells ``floor(p / voxel)``): the
    centroid of the voxel's points, carrying the instance most of them belong to (ties: the
    lowest instance number)."""
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    keys = np.floor(np.asarray(points, np.float64) / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]  # one int64 per cell
    _, vox = np.unique(flat, return_inverse=True)
    vox = vox.reshape(-1)
    n_vox = int(vox.max()) + 1
    counts = np.bincount(vox, minlength=n_vox).astype(np.float64)
    centroids = np.stack([np.bincount(vox, weights=points[:, d], minlength=n_vox) for d in range(3)], axis=1)
    centroids /= counts[:, None]
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
    """The instance of each ground-truth point's nearest predicted point, if nearer than
    ``radius`` (OpenLex3D's "global" mask alignment)."""
    dist, idx = nearest(pred_points, gt_points)
    out = np.full(len(gt_points), -1, np.int64)
    ok = dist < radius
    out[ok] = np.asarray(pred_instance, np.int64)[idx[ok]]
    return out


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
