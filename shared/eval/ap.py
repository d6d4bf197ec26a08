"""Class-agnostic average precision with ScanNet's greedy matching, as OpenLex3D computes it.

Ground-truth and predicted instances live in *groups* (one group per retrieval query; a single
group for instance segmentation); a prediction can only match ground truth of its own group.
At each IoU threshold t, ground-truth instances are visited in order; each takes the
not-yet-used predictions of its group with IoU > t, in prediction order: the first becomes its
match (a true positive with that prediction's score); every further one is a duplicate, and
the lower of the two scores is booked as a false positive while the ground truth keeps the
higher (ScanNet leaves the duplicate unused, so it may still match a later ground truth).
Predictions overlapping no ground truth at IoU > t are false positives, unless more than t of
their points lie on ignored ("void") ground truth. Unmatched ground truth are false negatives.
The precision/recall curve is ScanNet's (one point per distinct score, plus precision 1 at
recall 0), integrated with its trapezoid-like step widths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np

AP_THRESHOLDS: tuple[float, ...] = tuple(round(0.5 + 0.05 * i, 2) for i in range(9))
"""IoU thresholds averaged into ``ap``: 0.50, 0.55, ..., 0.90."""


@dataclass
class MatchTable:
    """Everything the matching needs: sizes, scores and pairwise intersections."""

    gt_group: Annotated[np.ndarray, "(G,) int"]
    gt_size: Annotated[np.ndarray, "(G,) int points"]
    pred_group: Annotated[np.ndarray, "(P,) int"]
    pred_size: Annotated[np.ndarray, "(P,) int points"]
    pred_score: Annotated[np.ndarray, "(P,) float confidence"]
    intersection: Annotated[np.ndarray, "(G, P) int points, 0 across groups"]
    pred_void: Annotated[np.ndarray, "(P,) float share of points on void"] | None = None

    def iou(self) -> Annotated[np.ndarray, "(G, P) float64"]:
        inter = self.intersection.astype(np.float64)
        same = self.gt_group[:, None] == self.pred_group[None, :]
        union = self.gt_size[:, None] + self.pred_size[None, :] - inter
        out = np.divide(inter, union, out=np.zeros_like(inter), where=(union > 0) & same)
        return out


def _classify(table: MatchTable, iou: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(true-positive scores, false-positive scores, hard false negatives) at one threshold."""
    n_gt, n_pred = iou.shape
    over = iou > threshold
    used = np.zeros(n_pred, bool)
    tp: list[float] = []
    fp: list[float] = []
    missed = 0
    score = table.pred_score
    for g in range(n_gt):
        best = -math.inf
        matched = False
        for p in np.flatnonzero(over[g]):
            if used[p]:
                continue
            if matched:
                fp.append(min(best, float(score[p])))
                best = max(best, float(score[p]))
            else:
                matched, best, used[p] = True, float(score[p]), True
        if matched:
            tp.append(best)
        else:
            missed += 1
    unmatched = ~over.any(axis=0)
    if table.pred_void is not None:
        unmatched &= table.pred_void <= threshold
    fp.extend(score[unmatched].tolist())
    return np.asarray(tp, np.float64), np.asarray(fp, np.float64), missed


def _curve_area(tp: np.ndarray, fp: np.ndarray, missed: int) -> float:
    """ScanNet's area under the precision/recall curve."""
    scores = np.concatenate([tp, fp])
    truth = np.concatenate([np.ones(len(tp)), np.zeros(len(fp))])
    thresholds, inverse = np.unique(scores, return_inverse=True)
    t_at = np.bincount(inverse, weights=truth, minlength=len(thresholds))
    n_at = np.bincount(inverse, minlength=len(thresholds)).astype(np.float64)
    # Predictions scoring at least each distinct score, from the lowest score up.
    tp_ge = np.cumsum(t_at[::-1])[::-1]
    n_ge = np.cumsum(n_at[::-1])[::-1]
    precision = np.append(tp_ge / n_ge, 1.0)
    recall = np.append(tp_ge / (len(tp) + missed), 0.0)
    padded = np.concatenate([[recall[0]], recall, [0.0]])
    widths = (padded[:-2] - padded[2:]) / 2.0
    return float(np.dot(precision, widths))


def average_precision(table: MatchTable, threshold: float) -> float:
    """AP at one IoU threshold; NaN without ground truth, 0 without predictions."""
    if len(table.gt_size) == 0:
        return math.nan
    if len(table.pred_size) == 0:
        return 0.0
    tp, fp, missed = _classify(table, table.iou(), threshold)
    if len(tp) + len(fp) == 0:
        return 0.0
    return _curve_area(tp, fp, missed)


def _finite_or_none(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


def ap_summary(table: MatchTable) -> dict[str, float | None | dict[str, float | None]]:
    """``ap`` (mean over IoU 0.50:0.05:0.90), ``ap50``, ``ap25`` and ``ap_per_threshold``;
    None where there is no ground truth to find."""
    per = {t: average_precision(table, t) for t in (*AP_THRESHOLDS, 0.25)}
    main = [per[t] for t in AP_THRESHOLDS]
    mean = math.nan if all(math.isnan(v) for v in main) else float(np.nanmean(main))
    return {
        "ap": _finite_or_none(mean),
        "ap50": _finite_or_none(per[0.5]),
        "ap25": _finite_or_none(per[0.25]),
        "ap_per_threshold": {f"{t:.2f}": _finite_or_none(v) for t, v in sorted(per.items())},
    }
