"""OpenLex3D segmentation frequencies and retrieval AP (shared/eval/openlex3d.py), pinned on
the hand-built scene of eval_fixtures.py with a one-hot text encoder."""

from __future__ import annotations

import json

import numpy as np
import pytest
from eval_fixtures import Scene, write_pred

from shared.eval import eval_openlex3d
from shared.eval.gt import load_gt
from shared.eval.openlex3d import evaluate_openlex3d
from shared.eval.prediction import Prediction, oracle_prediction

CATS = ("synonyms", "depictions", "vis_sim", "clutter", "missing", "incorrect")


def perfect(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ground truth as a prediction: one instance per labelled object, its first synonym."""
    enc = scene.encoder
    keep = scene.labels >= 0
    ids, index = np.unique(scene.labels[keep], return_inverse=True)
    first = {s["object_id"]: s["labels"]["image_attributes"]["synonyms"][0] for s in scene.samples}
    emb = np.stack([enc.mix({first[i]: 1.0}) if i in first else enc.mix({"filler a": 1.0}) for i in ids])
    return scene.points[keep], index, emb


def assert_categories(out: dict, expected: dict) -> None:
    for c in CATS:
        assert out[c] == pytest.approx(expected.get(c, 0.0), abs=1e-9), c
    assert sum(out[c] for c in CATS) == pytest.approx(1.0)


def test_prediction_equal_to_ground_truth_scores_one(scene, tmp_path):
    gt_dir = scene.write(tmp_path / "seq")
    pred_dir = write_pred(tmp_path / "map", *perfect(scene))
    out = eval_openlex3d(pred_dir, gt_dir, encoder=scene.encoder)
    assert_categories(out, {"synonyms": 1.0})
    assert out["ap"] == out["ap50"] == out["ap25"] == pytest.approx(1.0)
    assert out["top1_hit_rate"] == 1.0
    assert out["n_objects"] == 4  # chair, table, mug, lamp: wall excluded, 7 and -1 unlabelled
    assert out["n_queries"] == 2 and out["n_synonym_queries"] == 2
    json.dumps(out, allow_nan=False)  # strict JSON


def test_oracle_scores_ground_truth_as_prediction(scene, tmp_path):
    gt_dir = scene.write(tmp_path / "seq")
    out = eval_openlex3d(None, gt_dir, oracle=True, encoder=scene.encoder)
    assert out["oracle"] is True
    assert_categories(out, {"synonyms": 1.0})
    assert out["ap50"] == 1.0 and out["top1_hit_rate"] == 1.0


def test_gt_dir_may_be_the_gt_folder_itself(scene, tmp_path):
    scene.write(tmp_path / "seq")
    out = eval_openlex3d(None, tmp_path / "seq" / "gt", oracle=True, encoder=scene.encoder)
    assert out["synonyms"] == 1.0


def test_prediction_shifted_10cm_is_all_missing(scene, tmp_path):
    """Surfaces (the scene's bottom layer, z = 0.005) and their prediction lifted by 10 cm:
    every ground-truth point is 0.1 m from the nearest predicted point."""
    flat = scene.points[:, 2] < 0.01
    scene = Scene(scene.points[flat], scene.labels[flat], scene.parts, scene.samples, scene.encoder)
    gt_dir = scene.write(tmp_path / "seq")
    pts, index, emb = perfect(scene)
    pred_dir = write_pred(tmp_path / "map", pts + np.array([0.0, 0.0, 0.10]), index, emb)
    out = eval_openlex3d(pred_dir, gt_dir, encoder=scene.encoder)
    assert_categories(out, {"missing": 1.0})
    # Retrieval: no ground-truth point lies within 3.16 cm (squared distance 0.001 m²) of a predicted point.
    assert out["ap"] == out["ap50"] == out["ap25"] == 0.0
    assert out["top1_hit_rate"] == 0.0
    assert out["gt_points_aligned"] == 0.0


def test_other_objects_synonyms_are_clutter_only_where_clutter_ids_say(scene, tmp_path):
    """Every instance's labels are another object's synonym (top_n=1 so only that label counts).

    chair -> "table": table (2) is in the chair's clutter ids      -> clutter
    table -> "mug":   mug (3) is in the table's clutter ids        -> clutter
    mug   -> "lamp":  lamp (4) is not in the mug's clutter ids [2]  -> incorrect
    lamp  -> "chair": the lamp has no clutter ids                  -> incorrect
    """
    gt_dir = scene.write(tmp_path / "seq")
    enc = scene.encoder
    pts, index, _ = perfect(scene)  # one instance per object id, in sorted id order
    swapped = {1: "table", 2: "mug", 3: "lamp", 4: "chair", 7: "filler a", 9: "wall"}
    ids = [1, 2, 3, 4, 7, 9]
    emb = np.stack([enc.mix({swapped[i]: 1.0}) for i in ids])
    pred_dir = write_pred(tmp_path / "map", pts, index, emb)
    out = eval_openlex3d(pred_dir, gt_dir, encoder=enc, top_n=1, details=True)
    per = out["per_object"]
    assert per["1"]["clutter"] == 1.0 and per["2"]["clutter"] == 1.0
    assert per["3"]["incorrect"] == 1.0 and per["4"]["incorrect"] == 1.0
    assert_categories(out, {"clutter": 0.5, "incorrect": 0.5})


def test_hand_computed_frequencies_follow_openlex3d(scene, tmp_path):
    """Agreement with OpenLex3D's intersection_over_union_topn on a fixture worked by hand.

    Prediction instances (top-5 labels by construction; fillers match nothing):
      A = chair, x < 0.1 (500 pts): stool, bowl, desk, filler a, filler b
          -> stool is a chair vis_sim                      -> vis_sim   (500 points)
      B = chair, x >= 0.1 (500 pts): table, filler a..d
          -> table is a synonym of object 2, a clutter id of the chair -> clutter (500)
      C = table top (200 pts): desk, table, filler a..c
          -> table is a synonym (beats desk, a vis_sim)    -> synonyms  (200)
          the table leg (40 pts) lies 0.3 m from any predicted point -> missing (40)
      D = mug (125 pts): bowl, striped pattern, filler a..c
          -> depictions beats vis_sim                      -> depictions (125)
      E = lamp (125 pts): chair, filler a..d -> no tier, no clutter -> incorrect (125)
      F = wall (excluded), G = object 7 (unlabelled): not scored.
    Per object: chair vis_sim 1/2, clutter 1/2; table synonyms 200/240, missing 40/240;
    mug depictions 1; lamp incorrect 1. Means over the 4 objects:
      synonyms 200/240/4 = 5/24, depictions 1/4, vis_sim 1/8, clutter 1/8,
      missing 40/240/4 = 1/24, incorrect 1/4.
    """
    gt_dir = scene.write(tmp_path / "seq")
    enc, p = scene.encoder, scene.parts
    chair = p["chair"]
    left = chair[:, 0] < 0.1
    parts = [chair[left], chair[~left], p["table_top"], p["mug"], p["lamp"], p["wall"], p["unknown"]]
    pts = np.concatenate(parts)
    index = np.concatenate([np.full(len(x), i) for i, x in enumerate(parts)])
    emb = np.stack([
        enc.mix({"stool": 5, "bowl": 4, "desk": 3, "filler a": 2, "filler b": 1}),
        enc.mix({"table": 5, "filler a": 4, "filler b": 3, "filler c": 2, "filler d": 1}),
        enc.mix({"desk": 5, "table": 4, "filler a": 3, "filler b": 2, "filler c": 1}),
        enc.mix({"bowl": 5, "striped pattern": 4, "filler a": 3, "filler b": 2, "filler c": 1}),
        enc.mix({"chair": 5, "filler a": 4, "filler b": 3, "filler c": 2, "filler d": 1}),
        enc.mix({"wall": 1}),
        enc.mix({"filler a": 1}),
    ])
    pred_dir = write_pred(tmp_path / "map", pts, index, emb)
    out = eval_openlex3d(pred_dir, gt_dir, encoder=enc, details=True)
    assert_categories(out, {
        "synonyms": 5 / 24, "depictions": 1 / 4, "vis_sim": 1 / 8,
        "clutter": 1 / 8, "missing": 1 / 24, "incorrect": 1 / 4,
    })
    assert out["per_object"]["2"]["points"] == 240
    assert out["per_object"]["2"]["missing"] == pytest.approx(40 / 240)


def test_labels_match_with_spaces_stripped(scene, tmp_path):
    """OpenLex3D removes spaces: the prompt "stripedpattern" hits the depiction "striped pattern"."""
    gt = load_gt(scene.write(tmp_path / "seq"))
    gt.prompts = [p.replace("striped pattern", "stripedpattern") for p in gt.prompts]
    enc = type(scene.encoder)(gt.prompts + ["striped pattern", "chair", "table"])
    mug = scene.labels == 3
    pred = Prediction(scene.points[mug], np.zeros(int(mug.sum()), np.int64), enc.mix({"stripedpattern": 1})[None])
    out = evaluate_openlex3d(pred, gt, enc, top_n=1, details=True)
    assert out["per_object"]["3"]["depictions"] == 1.0


def test_retrieval_ap_worked_by_hand(scene, tmp_path):
    """Queries "chair" -> [1] and "table" -> [2]; instances P0 = chair (1000 pts, e_chair),
    P1 = table top (200 pts, 0.6 e_table + 0.8 e_chair), P2 = lamp (125 pts, e_lamp).

    Normalised scores ((cos + 1) / 2, then min-max over instances):
      "chair": cos 1, 0.8, 0   -> 1.0, 0.8, 0.0
      "table": cos 0, 0.6, 0   -> 0.0, 1.0, 0.0
    GT instances: (chair, 1000 pts), (table, 240 pts: the leg has no predicted point within
    3.16 cm). IoU(P0, chair) = 1; IoU(P1, table) = 200 / 240 = 0.833.
    IoU <= 0.80: both GT matched with score 1.0; FPs 0.8, 0, 0, 0 all score below -> AP 1.
    IoU 0.85, 0.90: the table is missed, P1 (score 1.0) becomes a FP. Scores: TP {1.0}, FP
    {1.0, 0.8, 0, 0, 0}, 1 hard FN. Curve (ascending distinct scores 0, 0.8, 1.0):
      p = 1/6, 1/3, 1/2 at recall 1/2 each, then (p=1, r=0);
      step widths 0, 0, 1/4, 1/4 -> AP = 1/2 * 1/4 + 1 * 1/4 = 0.375.
    ap = (7 * 1 + 2 * 0.375) / 9 = 0.861111; ap50 = ap25 = 1.
    """
    gt_dir = scene.write(tmp_path / "seq")
    enc, p = scene.encoder, scene.parts
    parts = [p["chair"], p["table_top"], p["lamp"]]
    pts = np.concatenate(parts)
    index = np.concatenate([np.full(len(x), i) for i, x in enumerate(parts)])
    emb = np.stack([enc.mix({"chair": 1}), enc.mix({"table": 0.6, "chair": 0.8}), enc.mix({"lamp": 1})])
    out = eval_openlex3d(write_pred(tmp_path / "map", pts, index, emb), gt_dir, encoder=enc)
    per = out["ap_per_threshold"]
    for t in ("0.50", "0.55", "0.60", "0.65", "0.70", "0.75", "0.80", "0.25"):
        assert per[t] == pytest.approx(1.0), t
    assert per["0.85"] == pytest.approx(0.375) and per["0.90"] == pytest.approx(0.375)
    assert out["ap"] == pytest.approx((7 + 2 * 0.375) / 9)
    assert out["ap50"] == 1.0 and out["ap25"] == 1.0
    assert out["top1_hit_rate"] == 1.0
    assert out["n_predictions"] == 6


def test_duplicate_predictions_are_false_positives(scene, tmp_path):
    """Query "chair" -> [1]. The chair is predicted as two halves A (x < 0.1, 500 points) and
    B (500 points) with the same feature e_chair, plus the lamp L (e_lamp). Scores: A = B = 1,
    L = 0.

    Under the default per_mask alignment (squared distance < 0.001 m², i.e. < 3.16 cm) each
    half also takes the neighbouring half's first column (x = 0.085 and x = 0.105 lie 0.02 m
    apart; the next column, 0.04 m, is out): A and B each cover 500 + 100 = 600 chair points.
    IoU(A, chair) = IoU(B, chair) = 600 / (1000 + 600 - 600) = 0.6.
    At IoU 0.25, 0.50, 0.55: A matches the chair (TP 1.0); B is a duplicate (FP 1.0); L
      overlaps nothing (FP 0.0). Distinct scores 0, 1: (p 1/3, r 1), (p 1/2, r 1), then (1, 0);
      widths 0, 1/2, 1/2 -> AP = 1/2 * 1/2 + 1/2 = 0.75.
      Without B it is (p 1/2, r 1), (1, 1), (1, 0) -> 1.0.
    At IoU 0.60 and above: 0.6 is not > 0.6, so nothing matches -> 0.
    With global alignment (each point to its one nearest instance) each half covers its own
    500 points: IoU 0.5, so AP50 is 0 and AP25 is 0.75.
    """
    gt_dir = scene.write(tmp_path / "seq", queries={"chair": [1]})
    enc, p = scene.encoder, scene.parts
    chair = p["chair"]
    left = chair[:, 0] < 0.1

    def run(parts, embs, name, **kw):
        pts = np.concatenate(parts)
        index = np.concatenate([np.full(len(x), i) for i, x in enumerate(parts)])
        return eval_openlex3d(write_pred(tmp_path / name, pts, index, np.stack(embs)), gt_dir, encoder=enc, **kw)

    halves = [chair[left], chair[~left], p["lamp"]]
    feats = [enc.mix({"chair": 1})] * 2 + [enc.mix({"lamp": 1})]
    dup = run(halves, feats, "dup")
    assert dup["alignment"] == "per_mask" and dup["alignment_threshold"] == 0.001
    per = dup["ap_per_threshold"]
    assert per["0.25"] == pytest.approx(0.75) and per["0.50"] == pytest.approx(0.75) and per["0.55"] == pytest.approx(0.75)
    assert per["0.60"] == 0.0 and per["0.90"] == 0.0
    single = run([chair[left], p["lamp"]], [enc.mix({"chair": 1}), enc.mix({"lamp": 1})], "single")
    assert single["ap25"] == pytest.approx(1.0) and single["ap50"] == pytest.approx(1.0)
    flat = run(halves, feats, "dup_global", alignment="global")
    assert flat["alignment"] == "global"
    assert flat["ap25"] == pytest.approx(0.75) and flat["ap50"] == 0.0


def test_empty_prediction_scores_zero(scene, tmp_path):
    gt_dir = scene.write(tmp_path / "seq")
    pred_dir = write_pred(tmp_path / "map", np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, scene.encoder.dim)))
    out = eval_openlex3d(pred_dir, gt_dir, encoder=scene.encoder)
    assert_categories(out, {"missing": 1.0})
    assert out["ap"] == out["ap50"] == out["ap25"] == 0.0
    assert out["top1_hit_rate"] == 0.0
    assert out["n_pred_points"] == 0 and out["n_pred_instances"] == 0
    json.dumps(out, allow_nan=False)


def test_no_queries_gives_none_not_nan(scene, tmp_path):
    gt = load_gt(scene.write(tmp_path / "seq", queries={}))
    out = evaluate_openlex3d(oracle_prediction(gt, scene.encoder), gt, scene.encoder)
    assert out["ap"] is None and out["top1_hit_rate"] is None
    assert out["synonyms"] == 1.0
    json.dumps(out, allow_nan=False)


def test_encoder_is_called_once_per_text_list(scene, tmp_path):
    gt_dir = scene.write(tmp_path / "seq")
    eval_openlex3d(None, gt_dir, oracle=True, encoder=scene.encoder)
    assert scene.encoder.calls == 3  # oracle names, prompts, queries
