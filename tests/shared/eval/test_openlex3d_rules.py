"""The three rules where the OpenLex3D evaluation's defaults follow the public OpenLex3D
toolbox's defaults (shared/eval/openlex3d.py, shared/eval/cloud.py), each pinned on a tiny
hand-made case whose numbers are worked out in the comments:

1. retrieval alignment: ``per_mask`` with ``alignment_threshold`` 0.001 compared with the
   SQUARED distance (FAISS IndexFlatL2), i.e. a 3.16 cm radius, a point joining every
   instance within it;
2. 5 cm voxel cells computed as Open3D's ``voxel_down_sample`` does, in the cloud's own
   precision (float32 for the clouds written here);
3. a label is clutter when it is a synonym, depiction OR visually-similar label of one of the
   object's clutter objects.
"""

from __future__ import annotations

import numpy as np
import pytest
from eval_fixtures import VocabEncoder, sample, write_gt, write_pred

from shared.eval import eval_openlex3d, load_gt
from shared.eval.cloud import align_instances, cloud_file_dtype, voxel_cells, voxel_downsample
from shared.eval.openlex3d import evaluate_openlex3d, segmentation_frequencies
from shared.eval.prediction import Prediction, load_prediction
from shared.eval.text import encode_texts

FILLERS = ["filler a", "filler b", "filler c", "filler d"]


def _pairs(points, instance, gt_points, threshold, mode):
    p, i = align_instances(np.asarray(points, float), np.asarray(instance), np.asarray(gt_points, float), threshold, mode)
    return sorted(zip(p.tolist(), i.tolist(), strict=True))


# ---------------------------------------------------------------------------- 1. alignment


def test_per_mask_threshold_is_a_squared_distance():
    """One predicted point at the origin; ground-truth points 2.5 cm and 4 cm away.

    Squared distances: 0.025² = 0.000625 < 0.001 -> aligned; 0.04² = 0.0016 >= 0.001 -> not.
    (Read as a Euclidean radius, 0.001 m would align neither.) Threshold 0.002 (4.47 cm):
    0.0016 < 0.002 -> both.
    """
    pred, inst = [[0.0, 0.0, 0.0]], [0]
    gt = [[0.025, 0.0, 0.0], [0.0, 0.04, 0.0]]
    assert _pairs(pred, inst, gt, 0.001, "per_mask") == [(0, 0)]
    assert _pairs(pred, inst, gt, 0.002, "per_mask") == [(0, 0), (1, 0)]
    assert _pairs(pred, inst, gt, 0.001, "global") == [(0, 0)]
    # Strict "<": a point exactly on the radius is out. 0.03125 = 2^-5 is exact in float32,
    # so its squared distance is exactly 0.0009765625, not < 0.0009765625.
    on_radius = [[0.03125, 0.0, 0.0]]
    assert _pairs(pred, inst, on_radius, 0.03125**2, "per_mask") == []
    assert _pairs(pred, inst, on_radius, 0.03125**2, "global") == []
    assert _pairs(pred, inst, on_radius, 0.03125**2 * 1.000001, "per_mask") == [(0, 0)]


def test_per_mask_point_joins_every_instance_within_the_threshold_global_only_the_nearest():
    """Instance 0 at x = 0, instance 1 at x = 0.03; a ground-truth point at x = 0.01.

    Squared distances 0.0001 and 0.0004, both < 0.001: per_mask gives the point to both
    instances; global to instance 0 only (its nearest point). A point at x = 0.06 is
    0.0009 from instance 1 (aligned) and 0.0036 from instance 0 (not).
    """
    pred, inst = [[0.0, 0, 0], [0.03, 0, 0]], [0, 1]
    gt = [[0.01, 0, 0], [0.06, 0, 0]]
    assert _pairs(pred, inst, gt, 0.001, "per_mask") == [(0, 0), (0, 1), (1, 1)]
    assert _pairs(pred, inst, gt, 0.001, "global") == [(0, 0), (1, 1)]


def test_bad_alignment_is_refused():
    with pytest.raises(ValueError, match="per_mask, global"):
        align_instances(np.zeros((1, 3)), np.zeros(1, np.int64), np.zeros((1, 3)), 0.001, "nearest")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="squared distance"):
        align_instances(np.zeros((1, 3)), np.zeros(1, np.int64), np.zeros((1, 3)), 0.0)


def test_retrieval_ap_under_the_default_alignment(tmp_path):
    """Query "chair" -> object 1, whose two points lie 2.5 cm and 4 cm from the one predicted
    point (instance 0, feature e_chair; a single instance's min-max score is 0).

    Default per_mask 0.001 m²: only the 2.5 cm point is aligned. Instance size 1, chair 2
    points, intersection 1: IoU = 1 / (2 + 1 - 1) = 0.5. AP25: one TP, no FP -> 1.
    AP50 and up: 0.5 is not > 0.5 -> 0, so ap = 0. Top-1: IoU 0.5 >= 0.25 -> hit.
    Threshold 0.002 m²: both points aligned, IoU 2 / (2 + 2 - 2) = 1 -> ap = ap50 = 1.
    """
    prompts = ["chair", *FILLERS]
    enc = VocabEncoder(prompts)
    gt_dir = write_gt(tmp_path / "seq", np.array([[0.025, 0, 0], [0.0, 0.04, 0]]), np.array([1, 1]),
                      [sample(1, ["chair"])], prompts, {"level0": {"chair": [1]}})  # fmt: skip
    pred_dir = write_pred(tmp_path / "map", np.zeros((1, 3)), np.zeros(1, np.int64), enc.mix({"chair": 1})[None])
    out = eval_openlex3d(pred_dir, gt_dir, encoder=enc)
    assert out["alignment"] == "per_mask" and out["alignment_threshold"] == 0.001
    assert out["gt_points_aligned"] == 0.5
    assert out["ap25"] == 1.0 and out["ap50"] == 0.0 and out["ap"] == 0.0
    assert out["top1_hit_rate"] == 1.0
    wide = eval_openlex3d(pred_dir, gt_dir, encoder=enc, alignment_threshold=0.002)
    assert wide["alignment_threshold"] == 0.002
    assert wide["ap"] == 1.0 and wide["ap50"] == 1.0 and wide["gt_points_aligned"] == 1.0


# ---------------------------------------------------------------------------- 2. voxel cells

X35 = float(np.float32(0.35))  # 0.3499999940395355
X36 = float(np.float32(0.36))  # 0.36000001430511475
X37 = float(np.float32(0.37))  # 0.3700000047683716


def test_float32_cells_differ_from_float64_cells():
    """float32(0.35) = 0.3499999940395355 and float32(0.05) = 0.05000000074505806.
    float64: 0.3499999940395355 / 0.05 = 6.99999988 -> cell 6.
    float32: the exact quotient 6.9999997765 is 2.2e-7 below 7, under half a float32 step
    there (4.77e-7 / 2), so it rounds to 7.0 -> cell 7, the cell of float32(0.36) (7.2000003).
    """
    pts = np.array([[X35, 0, 0], [X36, 0, 0]])
    assert voxel_cells(pts, 0.05, np.float32)[:, 0].tolist() == [7, 7]
    assert voxel_cells(pts, 0.05, np.float64)[:, 0].tolist() == [6, 7]
    # These values are float32 numbers, so the inferred precision is float32.
    assert voxel_cells(pts, 0.05)[:, 0].tolist() == [7, 7]
    cent, _ = voxel_downsample(pts, np.array([0, 0]), 0.05)
    assert len(cent) == 1


def _open3d():
    from shared.o3d import import_open3d

    try:
        return import_open3d()
    except ImportError as exc:  # the fusion extra is not installed here
        pytest.skip(f"open3d unavailable: {exc}")


def test_cells_equal_open3d_voxel_down_sample():
    """Open3D computes the cells in the cloud's dtype: the 0.35/0.36 pair is one voxel in a
    float32 cloud and two in a float64 cloud, as ours. On a seeded cloud of float32 points a
    few float32 steps from cell boundaries, voxel count and centroids equal Open3D's
    (centroids within a float32 step), while float64 cells would give a different count."""
    o3d = _open3d()

    def o3d_down(p: np.ndarray) -> np.ndarray:
        return o3d.t.geometry.PointCloud(o3d.core.Tensor(p)).voxel_down_sample(0.05).point.positions.numpy()

    pair = np.array([[X35, 0, 0], [X36, 0, 0]])
    assert len(o3d_down(pair.astype(np.float32))) == 1
    assert len(o3d_down(pair.astype(np.float64))) == 2
    assert len(voxel_downsample(pair, np.zeros(2, np.int64), 0.05, dtype=np.float64)[0]) == 2

    rng = np.random.default_rng(7)
    k = rng.integers(-60, 60, size=(3000, 3))
    steps = rng.integers(-3, 4, size=(3000, 3))
    base = (k * 0.05).astype(np.float32)
    pts = np.nextafter(base, np.where(steps > 0, np.inf, -np.inf).astype(np.float32))
    pts = np.where(steps == 0, base, pts).astype(np.float32)
    ref = o3d_down(pts).astype(np.float64)
    cent, _ = voxel_downsample(pts.astype(np.float64), np.zeros(len(pts), np.int64), 0.05)
    assert len(cent) == len(ref)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(ref).query(cent)
    assert dist.max() < 1e-6
    f64, _ = voxel_downsample(pts.astype(np.float64), np.zeros(len(pts), np.int64), 0.05, dtype=np.float64)
    assert len(f64) != len(ref)


def test_cells_decide_a_category(tmp_path):
    """Predicted points a = f32(0.35) (instance 0, "table"), b = f32(0.36), c = f32(0.37)
    (instance 1, "chair"); one ground-truth chair point at f32(0.34) (cell 6 either way).

    float32 cells (Open3D, default): a, b, c share cell 7 -> one voxel, majority instance 1
    ("chair"), centroid 0.36; the chair point is 0.02 m from it -> synonyms 1.
    float64 cells: a alone in cell 6 ("table", centroid 0.35, 0.01 m away) is nearer than
    cell 7's centroid 0.365 (0.025 m) -> "table" is no tier of the chair -> incorrect 1.
    """
    prompts = ["chair", "table", *FILLERS]
    enc = VocabEncoder(prompts)
    gt_dir = write_gt(tmp_path / "seq", np.array([[float(np.float32(0.34)), 0, 0]]), np.array([1]),
                      [sample(1, ["chair"])], prompts, {})  # fmt: skip
    pts = np.array([[X35, 0, 0], [X36, 0, 0], [X37, 0, 0]])
    emb = np.stack([enc.mix({"table": 1}), enc.mix({"chair": 1})])
    pred_dir = write_pred(tmp_path / "map", pts, np.array([0, 1, 1]), emb)
    assert cloud_file_dtype(pred_dir / "point_cloud.pcd") == np.float32
    out = eval_openlex3d(pred_dir, gt_dir, encoder=enc, top_n=1)
    assert out["n_pred_points_downsampled"] == 1
    assert out["synonyms"] == 1.0 and out["incorrect"] == 0.0
    gt, pred = load_gt(gt_dir), load_prediction(pred_dir)
    old = segmentation_frequencies(pred, gt, encode_texts(enc, gt.prompts), top_n=1, positions=np.float64)
    assert old["n_pred_points_downsampled"] == 2
    assert old["incorrect"] == 1.0 and old["synonyms"] == 0.0


# ---------------------------------------------------------------------------- 3. clutter


def test_clutter_objects_depictions_and_vis_sim_are_clutter(tmp_path):
    """Object 1 "chair" (clutter [2]); object 2 "table" (depiction "table drawing", vis_sim
    "desk"); object 3 "lamp" (clutter []). Four chair points 0.5 m apart, each predicted by
    its own instance, top-1 labels: "table drawing" (a depiction of the clutter object
    2 -> clutter), "desk" (its vis_sim -> clutter), "table" (its synonym -> clutter),
    "filler a" (nothing -> incorrect). Chair: clutter 3/4, incorrect 1/4. The lamp's point,
    predicted "table drawing", is incorrect: the table is not one of the lamp's clutter.
    Means over the 3 objects: table synonyms 1 -> synonyms 1/3; clutter 3/4 / 3 = 1/4;
    incorrect (1/4 + 1) / 3 = 5/12.
    """
    prompts = ["chair", "table", "table drawing", "desk", "lamp", *FILLERS]
    enc = VocabEncoder(prompts)
    chair = np.array([[0.025 + 0.5 * i, 0.025, 0.025] for i in range(4)])
    table, lamp = np.array([[3.025, 0.025, 0.025]]), np.array([[4.025, 0.025, 0.025]])
    pts = np.concatenate([chair, table, lamp])
    labels = np.array([1, 1, 1, 1, 2, 3])
    samples = [sample(1, ["chair"], clutter=[2]),
               sample(2, ["table"], depictions=["table drawing"], vis_sim=["desk"]),
               sample(3, ["lamp"])]  # fmt: skip
    gt_dir = write_gt(tmp_path / "seq", pts, labels, samples, prompts, {})
    tops = ["table drawing", "desk", "table", "filler a", "table", "table drawing"]
    emb = np.stack([enc.mix({t: 1}) for t in tops])
    out = eval_openlex3d(write_pred(tmp_path / "map", pts, np.arange(6), emb), gt_dir, encoder=enc, top_n=1, details=True)
    chair_out = out["per_object"]["1"]
    assert chair_out["clutter"] == pytest.approx(3 / 4) and chair_out["incorrect"] == pytest.approx(1 / 4)
    assert out["per_object"]["3"]["incorrect"] == 1.0
    assert out["synonyms"] == pytest.approx(1 / 3)
    assert out["clutter"] == pytest.approx(1 / 4)
    assert out["incorrect"] == pytest.approx(5 / 12)


def test_own_tiers_beat_clutter(tmp_path):
    """Object 1 "chair" (vis_sim "stool", clutter [2]); object 2 "table" (vis_sim "stool").
    The chair predicted "stool": it is the chair's own vis_sim, which comes before clutter
    (OpenLex3D's match checks the main categories first) -> vis_sim 1, clutter 0."""
    prompts = ["chair", "table", "stool", *FILLERS]
    enc = VocabEncoder(prompts)
    samples = [sample(1, ["chair"], vis_sim=["stool"], clutter=[2]), sample(2, ["table"], vis_sim=["stool"])]
    gt = load_gt(write_gt(tmp_path / "seq", np.array([[0.025, 0.025, 0.025]]), np.array([1]), samples, prompts, {}))
    pred = Prediction(gt.points.copy(), np.zeros(1, np.int64), enc.mix({"stool": 1})[None])
    out = evaluate_openlex3d(pred, gt, enc, top_n=1)
    assert out["vis_sim"] == 1.0 and out["clutter"] == 0.0
