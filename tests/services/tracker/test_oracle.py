"""The ground-truth tracker reads identities from its ground-truth source by frame index: a
Frame carries none."""

from __future__ import annotations

import numpy as np
import pytest

from services.tracker.oracle import GroundTruthTracker
from shared.datasets.ground_truth import GroundTruthError, StaticGroundTruth
from shared.geometry import Intrinsics
from shared.messages import Frame

H, W = 12, 16


def _frame(i: int, h: int = H, w: int = W) -> Frame:
    return Frame(frame_index=i, rgb=np.zeros((h, w, 3), np.uint8), depth=np.full((h, w), 1000, np.uint16), depth_scale=1000.0,
                 intrinsics=Intrinsics(fx=10, fy=10, cx=w / 2, cy=h / 2, width=w, height=h), T_world_cam=np.eye(4))  # fmt: skip


def _ids(*objects: int) -> np.ndarray:
    out = np.full((H, W), -1, np.int32)
    for k, obj in enumerate(objects):
        out[:, 4 * k : 4 * k + 3] = obj
    return out


def test_tracks_follow_the_sources_identities():
    truth = StaticGroundTruth({0: _ids(5, 9), 1: _ids(9), 2: _ids(9, 5)})
    tracker = GroundTruthTracker(keyframe_interval=2, ground_truth=truth, retire_frames=0)
    out = []
    for i in range(3):
        tracker.begin_frame(_frame(i))
        out.append(tracker.end_frame())
    first = {int(t) for t in np.unique(out[0].track_ids) if t >= 0}
    assert len(first) == 2 and out[0].keyframe
    # Object 9 keeps its track in every frame; object 5 comes back with its own.
    assert out[1].track_ids[0, 0] == out[0].track_ids[0, 4] == out[2].track_ids[0, 0]
    assert out[2].track_ids[0, 4] == out[0].track_ids[0, 0]
    feats = tracker.take_track_features(2)
    assert feats is not None and {t.track_id for t in feats.tracks} == first


def test_missing_ground_truth_is_an_error_naming_the_frame(tmp_path):
    tracker = GroundTruthTracker(ground_truth=StaticGroundTruth({0: _ids(1)}))
    with pytest.raises(GroundTruthError, match="Frame 3: .*frame_index 3 has no ground truth"):
        tracker.begin_frame(_frame(3))
    with pytest.raises(GroundTruthError, match="Frame 0: .*12x8 but the frame is 16x12.*tracker.ground_truth"):
        GroundTruthTracker(ground_truth=StaticGroundTruth({0: np.zeros((8, 12), np.int32)})).begin_frame(_frame(0))
    with pytest.raises(GroundTruthError, match="tracker.ground_truth is not set"):
        GroundTruthTracker()
    with pytest.raises(GroundTruthError, match="tracker.ground_truth: .* has no instances/"):
        GroundTruthTracker(ground_truth=str(tmp_path))
