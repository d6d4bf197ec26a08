"""`trackgraph map` end to end on synthetic scenes: the fusion acceptance of issue 7.

Ground-truth tracked frames (the ``ground_truth`` tracker: perfect masks and identities,
tracks retired when their object leaves the view) isolate fusion from tracking errors.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.cli import main
from services.fusion.core import FusionCore
from services.mapping import prepare_config
from services.tracker.build import build_tracker
from shared.config import TrackGraphConfig
from shared.datasets import open_sequence
from shared.eval import eval_instances
from shared.graph.store import MapStore

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]

GT_TRACKS = {"keyframe_vl": {"vl": {"backend": "simulated"}}, "tracker": {"mode": "ground_truth"}}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out)
    return out


@pytest.fixture(scope="module")
def revisit(tmp_path_factory):
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "revisit"
    # A lighter revisit (320x240, 400 frames) with the same walk: out of the first room,
    # more than 8 m away and back.
    run_synth("revisit", 0, out, {"camera": {"width": 320, "height": 240, "frames": 400}})
    return out


def _config(tmp_path, extra: dict | None = None):
    data = json.loads(json.dumps(GT_TRACKS))
    for k, v in (extra or {}).items():
        data.setdefault(k, {}).update(v)
    path = tmp_path / "cfg.yaml"
    import yaml

    path.write_text(yaml.safe_dump(data))
    return path


def test_ground_truth_tracks_give_ap50_090_on_small(small, tmp_path, capsys):
    out = tmp_path / "map"
    assert main(["map", str(small), "--config", str(_config(tmp_path)), "--out", str(out), "--json"]) == 0
    run = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {"frames", "seconds", "hz", "peak_rss_mb", "segments"} <= set(run) and run["frames"] == 120
    for name in ("mesh.ply", "point_cloud.pcd", "embeddings.npy", "index.npy", "run.json", "config.yaml"):
        assert (out / name).is_file(), name
    scores = eval_instances(out, small)
    assert scores["ap50"] >= 0.9, scores
    assert scores["segments_per_object"] <= 1.1
    # The rooms' footprints beside the map: the dining room and the hall of `small`.
    from services.query.roomtypes import map_room_ranker
    from shared.eval.rooms import eval_rooms

    rooms = eval_rooms(out, small / "gt", rank_rooms=map_room_ranker(out))
    assert rooms["f1"] == 1.0 and rooms["n_pred"] == rooms["n_gt"] == 2, rooms
    # Named from their views and contents (the oracle tracker's encoder answers vl/embed in
    # one process), and each found by its type. The hall is glimpsed in 5 keyframes (every
    # 24th frame), where its labels are within 0.01 of each other: only the dining room's name
    # is pinned.
    names = {r["gt_type"]: r["best_pred_name"] for r in rooms["per_room"]}
    assert names["dining room"] == "dining room" and names["hall"], rooms
    assert rooms["room_type_top1"] == 1.0, rooms


def test_tracker_at_default_noise_gives_ap50_070_on_small(small, tmp_path):
    """The whole mapping half on noisy perception: the simulated segmenter at default noise,
    the tracker propagating with classical features (``deploy/configs/synthetic.yaml``)."""
    from services.mapping import run_map
    from shared.config import load_config

    cfg = load_config(ROOT / "deploy" / "configs" / "synthetic.yaml")
    out = tmp_path / "map"
    run_map(small, cfg, out, progress=False)
    scores = eval_instances(out, small)
    assert scores["ap50"] >= 0.7, scores
    assert scores["ap25"] >= scores["ap50"] >= scores["ap"]
    assert scores["segments_per_object"] <= 1.2, scores


def test_reidentification_removes_revisit_duplicates(revisit, tmp_path):
    from services.mapping import run_map

    spo = {}
    for reid in (True, False):
        cfg = TrackGraphConfig.model_validate({**GT_TRACKS, "fusion": {"reid": {"enabled": reid}}})
        out = tmp_path / f"reid_{reid}"
        run_map(revisit, cfg, out, progress=False)
        spo[reid] = eval_instances(out, revisit)["segments_per_object"]
    assert spo[True] <= 1.1, spo
    assert spo[False] > spo[True] + 0.1, spo


def test_resume_gives_the_uninterrupted_graph(small, tmp_path):
    cfg = prepare_config(TrackGraphConfig.model_validate(GT_TRACKS), small)
    reader = open_sequence(small)
    n = 60

    def run(frames, fusion, tracker):
        for i in frames:
            tracker.begin_frame(reader.frame(i))
            tracked = tracker.end_frame()
            feats = tracker.take_track_features(i)
            if feats is not None:
                fusion.add_track_features(feats)
            fusion.add_frame(tracked)

    tracker = build_tracker(cfg)
    whole = FusionCore(cfg.fusion, device="cpu")
    run(range(n), whole, tracker)
    whole.finish()
    reference = whole.snapshot()

    tracker = build_tracker(cfg)
    first = FusionCore(cfg.fusion, device="cpu")
    run(range(n // 2), first, tracker)
    store = MapStore(tmp_path / "graph")
    store.save(first.snapshot(with_mesh=True), extra_state=first.state_dict())
    state = store.load()
    resumed = FusionCore(cfg.fusion, device="cpu")
    resumed.load_state_dict(state.extra, state.snapshot)
    run(range(n // 2, n), resumed, tracker)
    resumed.finish()
    got = resumed.snapshot()

    assert got.graph_seq == reference.graph_seq
    # The agent layer's poses survive the restart, one per frame fused.
    assert got.trajectory.shape == (n, 7) and got.trajectory_frames.tolist() == list(range(n))
    np.testing.assert_allclose(got.trajectory, reference.trajectory, atol=1e-12)
    assert [(s.id, s.tracks) for s in got.segments] == [(s.id, s.tracks) for s in reference.segments]
    for a, b in zip(got.segments, reference.segments, strict=True):
        np.testing.assert_allclose(a.centroid, b.centroid, atol=1e-6)
        np.testing.assert_array_equal(a.gallery, b.gallery)
    # The keyframe views and what they showed survive too: the rooms' features are the same.
    assert sorted(resumed.views) == sorted(whole.views) and sorted(resumed.view_points) == sorted(whole.view_points)
    assert [r.id for r in got.rooms] == [r.id for r in reference.rooms] and all(r.feature is not None for r in got.rooms)
    for a, b in zip(got.rooms, reference.rooms, strict=True):
        np.testing.assert_allclose(a.feature, b.feature, atol=1e-5)
