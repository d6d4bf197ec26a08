"""ScanNet-style greedy AP (shared/eval/ap.py) and the point-cloud helpers (shared/eval/cloud.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.eval.ap import AP_THRESHOLDS, MatchTable, ap_summary, average_precision
from shared.eval.cloud import contingency, transfer_instances, voxel_downsample


def table(gt_size, pred_size, score, inter, gt_group=None, pred_group=None, void=None) -> MatchTable:
    inter = np.asarray(inter, np.int64).reshape(len(gt_size), len(pred_size))
    return MatchTable(
        gt_group=np.zeros(len(gt_size), np.int64) if gt_group is None else np.asarray(gt_group),
        gt_size=np.asarray(gt_size),
        pred_group=np.zeros(len(pred_size), np.int64) if pred_group is None else np.asarray(pred_group),
        pred_size=np.asarray(pred_size),
        pred_score=np.asarray(score, np.float64),
        intersection=inter,
        pred_void=None if void is None else np.asarray(void, np.float64),
    )


def test_thresholds():
    assert AP_THRESHOLDS == (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9)


def test_perfect_is_one():
    t = table([10, 20], [10, 20], [0.9, 0.8], [[10, 0], [0, 20]])
    s = ap_summary(t)
    assert s["ap"] == s["ap50"] == s["ap25"] == 1.0


def test_ranked_false_positive_worked_by_hand():
    """Two GT; predictions by score: FP 0.9, TP 0.8, TP 0.7.
    Distinct scores ascending 0.7, 0.8, 0.9:
    >= 0.7: tp 2, n 3 -> p 2/3, r 1;  >= 0.8: tp 1, n 2 -> p 1/2, r 1/2;  >= 0.9: tp 0 -> p 0, r 0;
    then (1, 0). Recall [1, 1/2, 0, 0] padded [1, 1, 1/2, 0, 0, 0]:
    widths (1 - 1/2)/2, (1 - 0)/2, (1/2 - 0)/2, 0 = 1/4, 1/2, 1/4, 0
    AP = 2/3 * 1/4 + 1/2 * 1/2 + 0 * 1/4 + 1 * 0 = 1/6 + 1/4 = 5/12.
    """
    t = table([10, 10], [10, 10, 10], [0.9, 0.8, 0.7], [[0, 10, 0], [0, 0, 10]])
    assert average_precision(t, 0.5) == pytest.approx(5 / 12)


def test_duplicate_keeps_higher_score_and_books_lower_as_false_positive():
    """One GT (10 points); A (score 0.4) and B (0.9) both overlap it with IoU 1 and 0.6.
    GT takes A first (prediction order), then B is a duplicate: the GT keeps max(0.4, 0.9) =
    0.9 and a FP is booked at min = 0.4. Curve: >= 0.4: p 1/2, r 1; >= 0.9: p 1, r 1; (1, 0)
    -> widths 0, 1/2, 1/2 -> AP = 1/2 * 0 + 1 * 1/2 + 1 * 1/2 = 1.
    At IoU 0.7 only A matches (score 0.4) and B is an unmatched FP (0.9): >= 0.4: p 1/2, r 1;
    >= 0.9: p 0, r 0; (1, 0) -> recall [1, 0, 0] padded [1, 1, 0, 0, 0]: widths 1/2, 1/2, 0
    -> AP = 1/2 * 1/2 + 0 = 1/4.
    """
    t = table([10], [10, 6], [0.4, 0.9], [[10, 6]])
    assert average_precision(t, 0.5) == pytest.approx(1.0)
    assert average_precision(t, 0.7) == pytest.approx(0.25)


def test_groups_do_not_match_across():
    t = table([10], [10], [1.0], [[10]], gt_group=[0], pred_group=[1])
    assert average_precision(t, 0.5) == pytest.approx(0.0)


def test_void_heavy_unmatched_prediction_is_ignored():
    """Pred 1 matches nothing; 80% of its points are void -> ignored at thresholds < 0.8."""
    t = table([10], [10, 10], [0.5, 0.9], [[10, 0]], void=[0.0, 0.8])
    assert average_precision(t, 0.5) == pytest.approx(1.0)
    assert average_precision(t, 0.85) < 1.0


def test_no_gt_is_none_and_no_prediction_is_zero():
    s = ap_summary(table([], [5], [1.0], np.zeros((0, 1))))
    assert s["ap"] is None and s["ap50"] is None
    s = ap_summary(table([5], [], [], np.zeros((1, 0))))
    assert s["ap"] == 0.0 and s["ap25"] == 0.0
    assert math.isnan(average_precision(table([], [], [], np.zeros((0, 0))), 0.5))


def test_voxel_downsample_centroids_and_majority():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [0.02, 0.04, 0.01], [0.12, 0.0, 0.0]])
    inst = np.array([2, 5, 5, 1])
    cent, maj = voxel_downsample(pts, inst, 0.05)
    order = np.argsort(cent[:, 0])
    assert np.allclose(cent[order], [[0.02, 0.02, 0.01], [0.12, 0.0, 0.0]])
    assert list(maj[order]) == [5, 1]
    # A tie goes to the lower instance number.
    _, maj = voxel_downsample(pts[:2], np.array([7, 3]), 0.05)
    assert list(maj) == [3]
    cent, maj = voxel_downsample(np.zeros((0, 3)), np.zeros(0, np.int64), 0.05)
    assert cent.shape == (0, 3) and maj.shape == (0,)


def test_transfer_and_contingency():
    pred = np.array([[0, 0, 0], [1, 0, 0]], float)
    gt = np.array([[0.01, 0, 0], [0.99, 0, 0], [0.5, 0, 0]])
    got = transfer_instances(pred, np.array([4, 2]), gt, 0.03)
    assert list(got) == [4, 2, -1]
    assert list(transfer_instances(np.zeros((0, 3)), np.zeros(0, np.int64), gt, 0.03)) == [-1, -1, -1]
    c = contingency(np.array([0, 0, 1, -1]), 2, np.array([1, 1, 0, 0]), 2)
    assert c.tolist() == [[0, 2], [1, 0]]
