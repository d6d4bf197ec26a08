"""Loading ground truth and predictions: every bad input is an EvalInputError naming its file."""

from __future__ import annotations

import json

import numpy as np
import pytest
from eval_fixtures import Scene, write_pred

from shared.eval import EvalInputError, eval_instances, eval_openlex3d, load_gt, load_prediction
from shared.eval.gt import parse_queries


def good_pred(scene: Scene, root):
    keep = scene.labels >= 0
    ids, index = np.unique(scene.labels[keep], return_inverse=True)
    emb = np.eye(len(ids), scene.encoder.dim, dtype=np.float32)
    return write_pred(root, scene.points[keep], index, emb)


def error_of(fn, *args, **kw) -> EvalInputError:
    with pytest.raises(EvalInputError) as info:
        fn(*args, **kw)
    return info.value


@pytest.mark.parametrize("name", ["point_cloud.pcd", "embeddings.npy", "index.npy"])
def test_missing_prediction_file_is_named(scene, tmp_path, name):
    pred = good_pred(scene, tmp_path / "map")
    (pred / name).unlink()
    err = error_of(load_prediction, pred)
    assert err.path.name == name and name in str(err) and "missing" in str(err)


def test_index_of_wrong_length_is_named(scene, tmp_path):
    pred = good_pred(scene, tmp_path / "map")
    np.save(pred / "index.npy", np.load(pred / "index.npy")[:-3])
    err = error_of(load_prediction, pred)
    assert err.path.name == "index.npy"
    assert "point_cloud.pcd" in str(err) and str(len(scene.points[scene.labels >= 0])) in str(err)


@pytest.mark.parametrize("bad", [-1, 99])
def test_index_out_of_range_is_named(scene, tmp_path, bad):
    pred = good_pred(scene, tmp_path / "map")
    idx = np.load(pred / "index.npy")
    idx[5] = bad
    np.save(pred / "index.npy", idx)
    err = error_of(load_prediction, pred)
    assert err.path.name == "index.npy" and "[0, 6)" in str(err)


def test_float_index_is_rejected(scene, tmp_path):
    pred = good_pred(scene, tmp_path / "map")
    np.save(pred / "index.npy", np.load(pred / "index.npy").astype(np.float32))
    assert error_of(load_prediction, pred).path.name == "index.npy"


def test_nan_embeddings_are_named(scene, tmp_path):
    pred = good_pred(scene, tmp_path / "map")
    emb = np.load(pred / "embeddings.npy")
    emb[2, 3] = np.nan
    np.save(pred / "embeddings.npy", emb)
    err = error_of(load_prediction, pred)
    assert err.path.name == "embeddings.npy" and "NaN" in str(err)


def test_corrupt_npy_and_pcd_are_named(scene, tmp_path):
    pred = good_pred(scene, tmp_path / "map")
    (pred / "embeddings.npy").write_bytes(b"not numpy")
    assert error_of(load_prediction, pred).path.name == "embeddings.npy"
    pred = good_pred(scene, tmp_path / "map2")
    (pred / "point_cloud.pcd").write_bytes(b"garbage")
    assert error_of(load_prediction, pred).path.name == "point_cloud.pcd"
    pred = good_pred(scene, tmp_path / "map3")
    data = (pred / "point_cloud.pcd").read_bytes()
    (pred / "point_cloud.pcd").write_bytes(data[: len(data) // 2])  # truncated body
    assert error_of(load_prediction, pred).path.name == "point_cloud.pcd"


def test_mismatched_feature_dimension_names_embeddings(scene, tmp_path):
    gt_dir = scene.write(tmp_path / "seq")
    keep = scene.labels >= 0
    ids, index = np.unique(scene.labels[keep], return_inverse=True)
    pred = write_pred(tmp_path / "map", scene.points[keep], index, np.ones((len(ids), 7), np.float32))
    err = error_of(eval_openlex3d, pred, gt_dir, encoder=scene.encoder)
    assert err.path.name == "embeddings.npy"
    assert "dimension 7" in str(err) and f"dimension {scene.encoder.dim}" in str(err)


def test_missing_prediction_folder(scene, tmp_path):
    gt_dir = scene.write(tmp_path / "seq")
    err = error_of(eval_instances, tmp_path / "nope", gt_dir)
    assert err.path == tmp_path / "nope"


@pytest.mark.parametrize(
    "name", ["gt_categories.json", "points.npy", "labels.npy", "prompt_list.txt", "gt_categories_query_to_object_mapping_all.json"]
)
def test_missing_gt_file_is_named(scene, tmp_path, name):
    root = scene.write(tmp_path / "seq")
    (root / "gt" / name).unlink()
    err = error_of(load_gt, root)
    assert name in str(err)


def test_gt_labels_of_wrong_length_are_named(scene, tmp_path):
    root = scene.write(tmp_path / "seq")
    np.save(root / "gt" / "labels.npy", scene.labels[:-1].astype(np.int32))
    err = error_of(load_gt, root)
    assert err.path.name == "labels.npy" and "points.npy" in str(err)


def test_gt_nan_points_are_named(scene, tmp_path):
    root = scene.write(tmp_path / "seq")
    pts = scene.points.astype(np.float32)
    pts[10, 1] = np.nan
    np.save(root / "gt" / "points.npy", pts)
    err = error_of(load_gt, root)
    assert err.path.name == "points.npy" and "NaN" in str(err)


def test_gt_bad_json_is_named(scene, tmp_path):
    root = scene.write(tmp_path / "seq")
    (root / "gt" / "gt_categories.json").write_text("{not json")
    assert error_of(load_gt, root).path.name == "gt_categories.json"
    (root / "gt" / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": [{"labels": {}}]}}))
    assert "object_id" in str(error_of(load_gt, root))
    (root / "gt" / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": [
        {"object_id": 1, "labels": {"image_attributes": {"synonyms": ["a"], "clutter": ["x"]}}}]}}))
    assert "clutter" in str(error_of(load_gt, root))


def test_gt_empty_prompt_list_is_named(scene, tmp_path):
    root = scene.write(tmp_path / "seq")
    (root / "gt" / "prompt_list.txt").write_text("\n\n")
    assert error_of(load_gt, root).path.name == "prompt_list.txt"


def test_real_openlex3d_category_format_loads(scene, tmp_path):
    """OpenLex3D's own files: string clutter ids, no category field, tiers may be absent."""
    root = scene.write(tmp_path / "seq")
    samples = [
        {"object_id": 1, "labels": {"image_attributes": {"synonyms": ["chair"], "clutter": ["2"]}}},
        {"object_id": 2, "labels": {"image_attributes": {"synonyms": ["table"], "vis_sim": ["desk"]}}},
    ]
    (root / "gt" / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": samples}}))
    gt = load_gt(root)
    assert gt.objects[1].clutter == (2,) and gt.objects[1].category is None
    assert gt.objects[2].depictions == () and gt.objects[2].vis_sim == ("desk",)
    assert list(gt.evaluated_object_ids()) == [1, 2]


def test_query_mapping_nested_by_level_or_flat(tmp_path):
    nested = parse_queries({"level0": {"cushion": [65, 66]}, "level1": {"gingham cushion": [65]}}, tmp_path / "q.json")
    assert [(q.query_id, q.text, q.object_ids) for q in nested] == [
        ("level0_cushion", "cushion", (65, 66)), ("level1_gingham cushion", "gingham cushion", (65,)),
    ]
    flat = parse_queries({"cushion": [65, "66"]}, tmp_path / "q.json")
    assert flat[0].object_ids == (65, 66) and flat[0].level is None
    with pytest.raises(EvalInputError):
        parse_queries({"cushion": 65}, tmp_path / "q.json")


def test_other_query_mapping_name_is_found(scene, tmp_path):
    root = scene.write(tmp_path / "seq")
    gt = root / "gt"
    (gt / "gt_categories_query_to_object_mapping_all.json").rename(gt / "gt_categories_query_to_object_mapping_level0.json")
    assert len(load_gt(root).queries) == 2
