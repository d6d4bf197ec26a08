"""Ground truth off the wire (shared/datasets/ground_truth.py): a sequence folder gives the
simulated backends their instance ids by frame index, and by pixel content for image queries."""

from __future__ import annotations

import io
import json
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from shared.config import TrackGraphConfig
from shared.config.base import ConfigError
from shared.datasets.ground_truth import (
    GroundTruthError,
    SequenceGroundTruth,
    StaticGroundTruth,
    sequence_folder,
)

N, H, W = 6, 48, 64


def write_sequence(root: Path, n: int = N) -> tuple[Path, np.ndarray, np.ndarray]:
    """A synthetic-layout sequence of textured frames (lossless PNG colour) with instances."""
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, (n, H, W, 3), dtype=np.uint8)
    rgb[:, :10, :20] = 90  # a flat patch: runs there repeat and must not confuse placement
    inst = np.full((n, H, W), -1, np.int32)
    for i in range(n):
        inst[i, 5 + i : 30 + i, 4:40] = i % 3
        inst[i, 30:, 40:] = 7
    for sub in ("results", "instances"):
        (root / sub).mkdir(parents=True)
    for i in range(n):
        Image.fromarray(rgb[i]).save(root / "results" / f"frame{i:06d}.png")
        Image.fromarray(np.full((H, W), 1000, np.uint16)).save(root / "results" / f"depth{i:06d}.png")
        Image.fromarray((inst[i] + 1).astype(np.uint16)).save(root / "instances" / f"instance{i:06d}.png")
    (root / "traj.txt").write_text("\n".join(" ".join(map(str, np.eye(4).ravel())) for _ in range(n)) + "\n")
    (root / "intrinsics.json").write_text(json.dumps({"fx": 50, "fy": 50, "cx": 31.5, "cy": 23.5, "width": W, "height": H}))
    return root, rgb, inst


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return write_sequence(tmp_path_factory.mktemp("gt") / "seq")


def test_frames_by_index(seq):
    root, _, inst = seq
    gt = SequenceGroundTruth(root, field="tracker.ground_truth", user="ground_truth tracker")
    assert len(gt) == N and gt.shape == (H, W)
    for i in range(N):
        np.testing.assert_array_equal(gt.frame_instances(i), inst[i])
    with pytest.raises(GroundTruthError, match=rf"frame_index {N} is not a frame of the sequence .*seq \(frames 0 to {N - 1}\)"):
        gt.frame_instances(N)
    with pytest.raises(GroundTruthError, match="not an integer"):
        gt.frame_instances("1")  # type: ignore[arg-type]
    # Cached arrays are shared between callers, so nobody may edit them.
    with pytest.raises(ValueError):
        gt.frame_instances(0)[0, 0] = 5


def test_images_and_crops_by_content(seq):
    root, rgb, inst = seq
    gt = SequenceGroundTruth(root)
    gt.prepare_images(background=True)
    np.testing.assert_array_equal(gt.image_instances(rgb[2]), inst[2])  # a whole frame
    rng = np.random.default_rng(0)
    for _ in range(40):
        i = int(rng.integers(N))
        h, w = int(rng.integers(32, H + 1)), int(rng.integers(40, W + 1))
        y, x = int(rng.integers(0, H - h + 1)), int(rng.integers(0, W - w + 1))
        assert gt.locate(rgb[i, y : y + h, x : x + w]) == (i, y, x)
        np.testing.assert_array_equal(gt.image_instances(rgb[i, y : y + h, x : x + w].copy()), inst[i, y : y + h, x : x + w])


def test_images_not_of_the_sequence_are_refused_by_name(seq):
    root, rgb, _ = seq
    gt = SequenceGroundTruth(root, user="simulated VL encoder")
    crop = rgb[1, 10:40, 10:50].copy()
    crop[5, 5] ^= 1  # one pixel off
    with pytest.raises(GroundTruthError, match="40x30 pixels is neither a frame of the sequence .*seq nor a crop of one"):
        gt.image_instances(crop)
    buf = io.BytesIO()
    Image.fromarray(rgb[1]).save(buf, format="JPEG", quality=95)
    with pytest.raises(GroundTruthError, match="simulated VL encoder knows the ground truth of that sequence's own pixels only"):
        gt.image_instances(np.asarray(Image.open(buf).convert("RGB")))
    with pytest.raises(GroundTruthError, match="too small"):
        gt.image_instances(rgb[0, :3, :30])
    with pytest.raises(GroundTruthError, match="larger than the frames"):
        gt.image_instances(np.zeros((H + 1, W, 3), np.uint8))
    with pytest.raises(GroundTruthError, match=r"\(H, W, 3\) uint8"):
        gt.image_instances(np.zeros((H, W), np.uint8))


def test_concurrent_first_image_queries_build_one_index(seq):
    root, rgb, inst = seq
    gt = SequenceGroundTruth(root)
    out: list[np.ndarray] = []

    def ask(i: int) -> None:
        out.append(gt.image_instances(rgb[i, 4:44, 8:60]))

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(N)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(out) == N and gt._index is not None


def test_folder_errors_name_the_field(seq, tmp_path):
    root, _, _ = seq
    with pytest.raises(GroundTruthError, match="keyframe_vl.segmenter.ground_truth is not set: the simulated segmenter"):
        sequence_folder(None, "keyframe_vl.segmenter.ground_truth", "simulated segmenter")
    with pytest.raises(GroundTruthError, match="tracker.ground_truth: .*nowhere is not a folder"):
        sequence_folder(tmp_path / "nowhere", "tracker.ground_truth", "ground_truth tracker")
    with pytest.raises(GroundTruthError, match="keyframe_vl.vl.ground_truth: .* has no instances/ folder"):
        sequence_folder(tmp_path, "keyframe_vl.vl.ground_truth", "simulated VL encoder")
    (root / "gt").mkdir(exist_ok=True)
    assert sequence_folder(root / "gt", "keyframe_vl.vl.ground_truth", "x") == root  # the older SEQ/gt form
    (tmp_path / "broken" / "instances").mkdir(parents=True)
    with pytest.raises(GroundTruthError, match="tracker.ground_truth: .*broken is not a readable synthetic sequence"):
        SequenceGroundTruth(tmp_path / "broken", field="tracker.ground_truth")


def test_static_ground_truth():
    rgb = np.zeros((4, 8, 3), np.uint8)
    ids = np.ones((4, 8), np.int32)
    gt = StaticGroundTruth({3: ids}, images=[(rgb, ids)])
    np.testing.assert_array_equal(gt.frame_instances(3), ids)
    np.testing.assert_array_equal(gt.image_instances(rgb.copy()), ids)
    with pytest.raises(GroundTruthError, match="frame_index 4 has no ground truth"):
        gt.frame_instances(4)
    with pytest.raises(GroundTruthError, match="none of the 1 images"):
        gt.image_instances(np.ones((4, 8, 3), np.uint8))


def test_config_points_every_simulated_backend_at_a_synthetic_sequence(seq, tmp_path):
    root, _, _ = seq
    sim = TrackGraphConfig.model_validate(
        {"keyframe_vl": {"segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}}, "tracker": {"mode": "ground_truth"}}
    )
    keys = [k for k, _ in sim.ground_truth_fields()]
    assert keys == ["keyframe_vl.segmenter.ground_truth", "keyframe_vl.vl.ground_truth", "tracker.ground_truth"]
    got = sim.with_ground_truth(root)
    assert {v for _, v in got.ground_truth_fields()} == {str(root.resolve())}
    # Not synthetic: left unset (the backend names the key when it is made).
    assert sim.with_ground_truth(tmp_path) is sim
    # Real backends need none.
    assert TrackGraphConfig().ground_truth_fields() == []
    # A folder set by hand is kept, and must exist.
    other = tmp_path / "other"
    other.mkdir()
    kept = TrackGraphConfig.model_validate({"keyframe_vl": {"segmenter": {"backend": "simulated", "ground_truth": str(other)}}})
    assert kept.with_ground_truth(root).keyframe_vl.segmenter.ground_truth == str(other)
    gone = TrackGraphConfig.model_validate({"tracker": {"mode": "ground_truth", "ground_truth": str(tmp_path / "gone")}})
    with pytest.raises(ConfigError, match="tracker.ground_truth: .*gone is not a folder"):
        gone.with_ground_truth(root)
