"""Track-map files (shared/eval/track_io.py) and tracking metrics (shared/eval/tracking.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from shared.eval import EvalInputError, TrackWriter, eval_tracking, read_keyframes, read_track_map
from shared.eval.track_io import encode_id_png, instance_path, read_instance_map
from shared.eval.tracking import evaluate_track_maps

H, W = 24, 32


def gt_frame(t: int) -> np.ndarray:
    """Two objects: 0 on the left (8 x 8), 1 on the right (8 x 8), fixed in place."""
    m = np.full((H, W), -1, np.int32)
    m[4:12, 2:10] = 0
    m[4:12, 20:28] = 1
    return m


def write_gt_seq(seq, n: int) -> None:
    (seq / "instances").mkdir(parents=True)
    for t in range(n):
        Image.fromarray((gt_frame(t) + 1).astype(np.uint16)).save(instance_path(seq, t))


def write_run(run, maps: list[np.ndarray], keyframes: list[int]) -> None:
    with TrackWriter(run) as w:
        for t, m in enumerate(maps):
            w.write(t, m, keyframe=t in keyframes)


def relabel(m: np.ndarray, mapping: dict[int, int]) -> np.ndarray:
    out = np.full_like(m, -1)
    for a, b in mapping.items():
        out[m == a] = b
    return out


def test_writer_reader_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    maps = [rng.integers(-1, 65535, size=(H, W)).astype(np.int32) for _ in range(3)]
    with TrackWriter(tmp_path / "run") as w:
        for t, m in enumerate(maps):
            w.write(t * 2, m, keyframe=(t == 1))
        # Rewritten after each keyframe: readable before close().
        assert read_keyframes(tmp_path / "run") == [2]
        w.add_keyframe(0)
    assert read_keyframes(tmp_path / "run") == [0, 2]
    for t, m in enumerate(maps):
        got = read_track_map(tmp_path / "run", t * 2)
        assert got.dtype == np.int32 and np.array_equal(got, m)
    png = Image.open(tmp_path / "run" / "tracks" / "track000002.png")
    assert png.mode.startswith("I;16")
    assert json.loads((tmp_path / "run" / "tracks" / "keyframes.json").read_text()) == [0, 2]


def test_writer_rejects_ids_that_do_not_fit():
    with pytest.raises(ValueError, match="65534"):
        encode_id_png(np.full((2, 2), 65535))
    with pytest.raises(ValueError):
        encode_id_png(np.zeros((2, 2, 3), np.int32))


def test_perfect_tracks(tmp_path):
    write_gt_seq(tmp_path / "seq", 10)
    write_run(tmp_path / "run", [relabel(gt_frame(t), {0: 7, 1: 3}) for t in range(10)], [0, 5])
    out = eval_tracking(tmp_path / "run", tmp_path / "seq")
    assert out["idf1"] == 1.0 and out["id_switches"] == 0 and out["mean_iou"] == 1.0
    assert out["id_switches_per_100_frames_per_object"] == 0.0 and out["fragmentations"] == 0
    assert out["mota"] == 1.0
    assert out["n_frames"] == 10 and out["n_keyframes"] == 2 and out["n_iou_pairs"] == 16
    assert out["n_gt_objects"] == 2 and out["n_tracks"] == 2
    json.dumps(out, allow_nan=False)


def test_swapped_ids_mid_sequence(tmp_path):
    """Frames 0-4: object 0 -> track 1, object 1 -> track 2; frames 5-9 swapped.
    Switches: object 0 (1 -> 2) and object 1 (2 -> 1) at frame 5 -> 2.
    Per 100 frames per object: 100 * 2 / 20 visible object-frames = 10.
    IDF1: co-matched frames (0,1) = (0,2) = (1,2) = (1,1) = 5; the best one-to-one id matching
    keeps 10 of 20 detections -> IDF1 = 2 * 10 / (20 + 20) = 0.5.
    Every mask is still perfect: mean IoU 1, MOTA = 1 - 2 / 20 = 0.9.
    """
    write_gt_seq(tmp_path / "seq", 10)
    maps = [relabel(gt_frame(t), {0: 1, 1: 2} if t < 5 else {0: 2, 1: 1}) for t in range(10)]
    write_run(tmp_path / "run", maps, [0])
    out = eval_tracking(tmp_path / "run", tmp_path / "seq")
    assert out["id_switches"] == 2
    assert out["id_switches_per_100_frames_per_object"] == pytest.approx(10.0)
    assert out["idf1"] == pytest.approx(0.5)
    assert out["mean_iou"] == 1.0 and out["mota"] == pytest.approx(0.9)
    assert out["fragmentations"] == 0


def test_lost_and_recovered_track_is_a_fragmentation_not_a_switch():
    """Object 0 tracked as 4, lost in frames 3-4 (no track), tracked as 4 again from 5."""
    frames = []
    for t in range(8):
        g = gt_frame(t)
        p = relabel(g, {0: 4, 1: 9}) if t not in (3, 4) else relabel(g, {1: 9})
        frames.append((t, p, g))
    out = evaluate_track_maps(frames, set())
    assert out["fragmentations"] == 1 and out["id_switches"] == 0
    # IDTP = 6 (object 0) + 8 (object 1); detections GT 16, predicted 14.
    assert out["idf1"] == pytest.approx(2 * 14 / 30)


def test_switch_across_a_gap_counts_once():
    """Object 0: track 4 in frames 0-2, unmatched 3-4, track 5 from 5: one switch, one fragmentation."""
    frames = []
    for t in range(8):
        g = gt_frame(t)
        mapping = {1: 9, **({0: 4} if t < 3 else {0: 5} if t >= 5 else {})}
        frames.append((t, relabel(g, mapping), g))
    out = evaluate_track_maps(frames, set())
    assert out["id_switches"] == 1 and out["fragmentations"] == 1


def test_mean_iou_uses_non_keyframes_only():
    """Keyframe 0 is perfect; frames 1-2 shift object 0's mask by 4 of 8 columns: IoU 4/12."""
    frames = []
    for t in range(3):
        g = gt_frame(t)
        p = relabel(g, {0: 1, 1: 2})
        if t > 0:
            p[p == 1] = -1
            p[4:12, 6:14] = 1
        frames.append((t, p, g))
    out = evaluate_track_maps(frames, {0})
    assert out["mean_iou"] == pytest.approx((1 / 3 + 1 + 1 / 3 + 1) / 4)
    # IoU 1/3 < 0.5: object 0 is unmatched in frames 1-2 for the identity metrics.
    assert out["matches"] == 4 and out["gt_coverage"] == pytest.approx(4 / 6)


def test_tiny_masks_are_ignored_on_both_sides():
    g = gt_frame(0)
    g[0, 0] = 5  # a one-pixel object
    p = relabel(g, {0: 1, 1: 2})
    p[23, 31] = 8  # a one-pixel track
    out = evaluate_track_maps([(0, p, g)], set(), min_area_frac=0.01)
    assert out["gt_detections"] == 2 and out["pred_detections"] == 2 and out["idf1"] == 1.0


def test_strided_run_is_scored_on_its_frames(tmp_path):
    write_gt_seq(tmp_path / "seq", 10)
    with TrackWriter(tmp_path / "run") as w:
        for t in range(0, 10, 3):
            w.write(t, relabel(gt_frame(t), {0: 0, 1: 1}), keyframe=t == 0)
    out = eval_tracking(tmp_path / "run", tmp_path / "seq")
    assert out["n_frames"] == 4 and out["idf1"] == 1.0


def test_smaller_track_maps_are_resized(tmp_path):
    write_gt_seq(tmp_path / "seq", 2)
    small = [relabel(gt_frame(t), {0: 0, 1: 1})[::2, ::2] for t in range(2)]
    write_run(tmp_path / "run", small, [0])
    out = eval_tracking(tmp_path / "run", tmp_path / "seq")
    assert out["idf1"] == 1.0 and out["mean_iou"] == 1.0


def test_missing_inputs_are_named(tmp_path):
    write_gt_seq(tmp_path / "seq", 2)
    with pytest.raises(EvalInputError, match="tracks"):
        eval_tracking(tmp_path / "nothing", tmp_path / "seq")
    write_run(tmp_path / "run", [gt_frame(0), gt_frame(1), gt_frame(2)], [0])
    with pytest.raises(EvalInputError) as info:
        eval_tracking(tmp_path / "run", tmp_path / "seq")
    assert info.value.path.name == "instance000002.png"
    (tmp_path / "run" / "tracks" / "keyframes.json").unlink()
    with pytest.raises(EvalInputError) as info:
        eval_tracking(tmp_path / "run", tmp_path / "seq")
    assert info.value.path.name == "keyframes.json"
    (tmp_path / "run" / "tracks" / "keyframes.json").write_text('{"frames": 1}')
    with pytest.raises(EvalInputError, match="list"):
        read_keyframes(tmp_path / "run")
    (tmp_path / "seq" / "instances" / "instance000000.png").write_bytes(b"not a png")
    with pytest.raises(EvalInputError, match="PNG"):
        read_instance_map(tmp_path / "seq", 0)
