"""Class-agnostic 3D instance quality of a map against the ground-truth objects.

Predicted instances (the rows of ``index.npy``) are transferred onto the ground-truth points:
each ground-truth point takes the instance of its nearest predicted point within
``align_radius`` (0.03 m), the nearest-point (``global``) alignment of OpenLex3D retrieval,
not its default ``per_mask``. All IoUs are counted on
ground-truth points.

- Ground truth: every object present in ``labels.npy`` with at least one synonym in
  ``gt_categories.json`` and not structure (wall, floor, ceiling, doorframe, ledge, window
  ledge). Points of other objects, and unlabelled points, are *void*.
- Predictions: every instance that covers at least one ground-truth point (instances that
  cover none are counted in ``n_pred_unaligned`` and otherwise ignored, as OpenLex3D does).
  A prediction's confidence is its number of points in ``point_cloud.pcd`` (the format has
  no scores; larger segments rank first). An unmatched prediction with more than the IoU
  threshold of its points on void is ignored rather than a false positive (ScanNet).
- ``ap``, ``ap50``, ``ap25``: ScanNet's greedy AP (:mod:`shared.eval.ap`), one class, ``ap``
  averaging IoU 0.50:0.05:0.90.
- ``segments_per_object``: each prediction is *assigned* to the scored object holding most of
  its transferred points; the assignment *counts* when the prediction overlaps that object
  with IoU >= 0.25 or has more than half of its transferred points on it. The figure is the
  number of counting assignments divided by the number of objects with at least one (1 for a
  clean map; 2 when every object is split in two; it grows with duplicates and fragments).
  ``objects_with_segments`` is that number of objects and ``object_recall_25`` its share of
  all scored objects.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from shared.eval.ap import MatchTable, ap_summary
from shared.eval.cloud import contingency, transfer_instances
from shared.eval.gt import EXCLUDED_LABELS, GroundTruth, load_gt
from shared.eval.prediction import Prediction, load_prediction

log = logging.getLogger(__name__)

ALIGN_RADIUS = 0.03
"""Ground-truth point to predicted point transfer radius (m)."""
SEGMENT_IOU = 0.25
"""IoU with its object at which a segment counts for ``segments_per_object``."""


def evaluate_instances(
    pred: Prediction,
    gt: GroundTruth,
    *,
    align_radius: float = ALIGN_RADIUS,
    excluded: Sequence[str] = EXCLUDED_LABELS,
) -> dict[str, Any]:
    """Instance AP and segments per object on loaded inputs (see the module docstring)."""
    object_ids = gt.evaluated_object_ids(excluded)
    n_obj, k = len(object_ids), pred.n_instances
    row = gt.object_rows(object_ids)

    aligned = transfer_instances(pred.points, pred.index, gt.points, align_radius)
    inter = contingency(aligned, k, row, n_obj)  # (K, O)
    size = np.bincount(aligned[aligned >= 0], minlength=k)  # transferred GT points per instance
    void = size - inter.sum(axis=1)
    obj_size = np.bincount(row[row >= 0], minlength=n_obj)
    confidence = np.bincount(pred.index, minlength=k).astype(np.float64)

    live = np.flatnonzero(size > 0)
    table = MatchTable(
        gt_group=np.zeros(n_obj, np.int64),
        gt_size=obj_size,
        pred_group=np.zeros(len(live), np.int64),
        pred_size=size[live],
        pred_score=confidence[live],
        intersection=inter[live].T,
        pred_void=void[live] / size[live],
    )
    out: dict[str, Any] = dict(ap_summary(table))

    segs = None
    with_segments = 0
    if n_obj and len(live):
        li = inter[live].astype(np.float64)
        owner = li.argmax(axis=1)
        on_owner = li[np.arange(len(live)), owner]
        iou = on_owner / (obj_size[owner] + size[live] - on_owner)
        counts = (on_owner > 0) & ((iou >= SEGMENT_IOU) | (on_owner > 0.5 * size[live]))
        per_object = np.bincount(owner[counts], minlength=n_obj)
        with_segments = int((per_object > 0).sum())
        if with_segments:
            segs = float(per_object.sum() / with_segments)
    out["segments_per_object"] = segs
    out["objects_with_segments"] = with_segments
    out["object_recall_25"] = with_segments / n_obj if n_obj else None
    out["n_gt_objects"] = n_obj
    out["n_pred_instances"] = k
    out["n_pred_unaligned"] = int(k - len(live))
    return out


def eval_instances(pred_dir: str | Path, gt_dir: str | Path, *, align_radius: float = ALIGN_RADIUS) -> dict[str, Any]:
    """Class-agnostic instance scores of the map in ``pred_dir`` (OpenLex3D prediction format)
    against ``gt_dir``: ``ap``, ``ap50``, ``ap25``, ``segments_per_object`` and counts."""
    t0 = time.perf_counter()
    gt = load_gt(gt_dir)
    pred = load_prediction(pred_dir)
    out = evaluate_instances(pred, gt, align_radius=align_radius)
    out["seconds"] = round(time.perf_counter() - t0, 3)
    log.info(
        "instances: AP %s, AP50 %s, AP25 %s, segments/object %s",
        *(("n/a" if out[key] is None else f"{out[key]:.3f}") for key in ("ap", "ap50", "ap25", "segments_per_object")),
    )
    return out
