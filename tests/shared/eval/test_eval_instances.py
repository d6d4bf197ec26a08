"""Class-agnostic instance AP and segments per object (shared/eval/instances.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from eval_fixtures import Scene, write_pred

from shared.eval import eval_instances


def segments_of(scene: Scene, split: bool) -> list[np.ndarray]:
    """Point sets of predicted segments: one per labelled object, or each scored object cut
    at the middle of its x range (the table's leg goes with its right half)."""
    segs = []
    for oid in (1, 2, 3, 4, 9, 7):
        pts = scene.points[scene.labels == oid]
        if split and oid in (1, 2, 3, 4):
            cut = {1: 0.1, 2: 1.1, 3: 2.05, 4: 3.05}[oid]
            segs += [pts[pts[:, 0] < cut], pts[pts[:, 0] >= cut]]
        else:
            segs.append(pts)
    return segs


def write_segments(root, segs, dim=4):
    pts = np.concatenate(segs)
    index = np.concatenate([np.full(len(s), i) for i, s in enumerate(segs)])
    return write_pred(root, pts, index, np.ones((len(segs), dim), np.float32))


def test_perfect_segments(scene, tmp_path):
    gt = scene.write(tmp_path / "seq")
    out = eval_instances(write_segments(tmp_path / "map", segments_of(scene, split=False)), gt)
    assert out["ap"] == out["ap50"] == out["ap25"] == 1.0
    assert out["segments_per_object"] == 1.0
    assert out["n_gt_objects"] == 4 and out["objects_with_segments"] == 4 and out["object_recall_25"] == 1.0
    json.dumps(out, allow_nan=False)


def test_every_object_split_in_two(scene, tmp_path):
    """Halves (points; confidence = points): chair 500 | 500, table 100 | 100 + 40 (leg),
    mug 75 | 50, lamp 75 | 50. IoUs: chair 0.5, 0.5; table 0.417, 0.583; mug and lamp 0.6, 0.4.
    Wall and object 7 segments lie on void (not scored) and are ignored.

    AP50 (IoU > 0.5): TP 140 (table R), 75 (mug L), 75 (lamp L); the chair is missed;
    FP 500, 500 (chair halves), 100, 50, 50. Distinct scores ascending 50, 75, 100, 140, 500:
      (p 3/8, r 3/4), (1/2, 3/4), (1/4, 1/4), (1/3, 1/4), (0, 0), then (1, 0);
      widths 0, 1/4, 1/4, 1/8, 1/8, 0 -> AP50 = 1/8 + 1/16 + 1/24 = 11/48.
    AP25: chair L TP 500, chair R duplicate FP 500; table L first (100), then R duplicate:
      TP keeps 140, FP 100; mug, lamp: TP 75, FP 50. TP {500, 140, 75, 75}, FP {500, 100, 50, 50}:
      (1/2, 1), (2/3, 1), (1/2, 1/2), (2/3, 1/2), (1/2, 1/4), then (1, 0);
      widths 0, 1/4, 1/4, 1/8, 1/4, 1/8 -> AP25 = 1/6 + 1/8 + 1/12 + 1/8 + 1/8 = 15/24.
    Every half has all its points on its object -> 2 segments per object.
    """
    gt = scene.write(tmp_path / "seq")
    out = eval_instances(write_segments(tmp_path / "map", segments_of(scene, split=True)), gt)
    assert out["segments_per_object"] == 2.0
    assert out["ap50"] == pytest.approx(11 / 48)
    assert out["ap25"] == pytest.approx(15 / 24)
    assert out["ap"] < out["ap50"] + 1e-12


def test_one_split_object(scene, tmp_path):
    segs = segments_of(scene, split=False)
    chair = segs[0]
    segs = [chair[chair[:, 0] < 0.1], chair[chair[:, 0] >= 0.1], *segs[1:]]
    out = eval_instances(write_segments(tmp_path / "map", segs), scene.write(tmp_path / "seq"))
    assert out["segments_per_object"] == pytest.approx((2 + 1 + 1 + 1) / 4)


def test_small_fragment_on_an_object_counts_as_a_duplicate(scene, tmp_path):
    """A 3-point fragment of the lamp: IoU 3/125 < 0.25, but all its points are on the lamp."""
    segs = segments_of(scene, split=False)
    lamp = segs[3]
    segs = [*segs[:3], lamp[3:], lamp[:3], *segs[4:]]
    out = eval_instances(write_segments(tmp_path / "map", segs), scene.write(tmp_path / "seq"))
    assert out["segments_per_object"] == pytest.approx(5 / 4)


def test_unaligned_segments_are_counted_not_scored(scene, tmp_path):
    far = np.array([[50.0, 50.0, 50.0], [50.1, 50.0, 50.0]])
    segs = [*segments_of(scene, split=False), far]
    out = eval_instances(write_segments(tmp_path / "map", segs), scene.write(tmp_path / "seq"))
    assert out["n_pred_unaligned"] == 1 and out["ap"] == 1.0


def test_empty_prediction(scene, tmp_path):
    pred = write_pred(tmp_path / "map", np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 4)))
    out = eval_instances(pred, scene.write(tmp_path / "seq"))
    assert out["ap"] == out["ap50"] == out["ap25"] == 0.0
    assert out["segments_per_object"] is None and out["objects_with_segments"] == 0
    json.dumps(out, allow_nan=False)
