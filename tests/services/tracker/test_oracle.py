"""The ground-truth tracker reads identities from its ground-truth source by frame index: a
Frame carries none."""

from __future__ import annotations

import numpy as np
import pytest

from services.tracker.oracle import GroundTruthTracker
from shared.datasets.ground_truth import GroundTruthError, StaticGroundTruth
from shared.geometry import Intrinsics
from shared.messages import Frame
from shared.perception import KeyframeImage

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


class ViewEncoder:
    """Crops: unit e_0 each. View: a unit vector drawn from the frame index; frames in ``bad`` fail."""

    name = "fake-view"
    dim = 8

    def __init__(self, bad: tuple[int, ...] = (), views: bool = True) -> None:
        self.bad = set(bad)
        if not views:
            self.encode_view = None  # as an encoder without the method: getattr finds None

    def encode_crops(self, image, masks):
        return np.tile(np.eye(self.dim, dtype=np.float32)[0], (len(masks), 1))

    def encode_view(self, image):
        if image.frame_index in self.bad:
            raise RuntimeError("view tower out of memory")
        v = np.random.default_rng(image.frame_index).standard_normal(self.dim).astype(np.float32)
        return v / np.linalg.norm(v)


def _run(tracker: GroundTruthTracker, n: int) -> list:
    out = []
    for i in range(n):
        tracker.begin_frame(_frame(i))
        tracker.end_frame()
        out.append(tracker.take_track_features(i))
    return out


def test_keyframe_features_carry_the_view_even_when_no_track_changed():
    enc = ViewEncoder()
    truth = StaticGroundTruth({i: _ids(5) for i in range(5)})
    out = _run(GroundTruthTracker(keyframe_interval=2, encoder=enc, ground_truth=truth), 5)
    # Frame 0: the new track and the view; 1, 3: nothing; 2, 4: the view alone (the object's
    # 36 pixels are under the 50 the oracle embeds a crop of: no track changes).
    assert [f is not None for f in out] == [True, False, True, False, True]
    assert [len(out[k].tracks) for k in (0, 2, 4)] == [1, 0, 0]
    for k in (0, 2, 4):
        assert out[k].frame_index == k
        np.testing.assert_array_equal(out[k].view, enc.encode_view(KeyframeImage(k, np.zeros((H, W, 3), np.uint8))))


def test_no_view_from_an_encoder_without_one_or_when_it_fails():
    truth = StaticGroundTruth({i: _ids(5) for i in range(3)})
    out = _run(GroundTruthTracker(keyframe_interval=2, encoder=ViewEncoder(views=False), ground_truth=truth), 3)
    assert out[0] is not None and out[0].view is None and out[1] is None and out[2] is None
    out = _run(GroundTruthTracker(keyframe_interval=2, encoder=ViewEncoder(bad=(0,)), ground_truth=truth), 3)
    assert out[0] is not None and out[0].view is None and len(out[0].tracks) == 1
    assert out[2] is not None and out[2].view is not None


def test_a_view_untaken_at_its_frame_is_not_placed_at_a_later_one():
    truth = StaticGroundTruth({i: _ids(5) for i in range(3)})
    tracker = GroundTruthTracker(keyframe_interval=2, encoder=ViewEncoder(), ground_truth=truth)
    tracker.begin_frame(_frame(0))  # frame 0's end and features never taken (it failed downstream)
    tracker.begin_frame(_frame(1))
    tracker.end_frame()
    feats = tracker.take_track_features(1)
    assert feats is not None and feats.view is None and len(feats.tracks) == 1  # the new track only


def test_the_oracle_sends_its_views_to_fusion_through_the_session(clock):
    from services.tracker.session import TrackerSession
    from shared.config import TrackGraphConfig
    from shared.messages.keyframes import TrackFeatures
    from shared.runtime.bus import InProcessBus
    from shared.topics import Topics

    truth = StaticGroundTruth({i: _ids(5, 9) for i in range(3)})
    bus = InProcessBus("robot0", clock=clock)
    TrackerSession(bus, TrackGraphConfig(), GroundTruthTracker(keyframe_interval=2, encoder=ViewEncoder(), ground_truth=truth), clock=clock)
    t = Topics("robot0")
    got: list[TrackFeatures] = []
    bus.subscribe(t.tracks_features, TrackFeatures, lambda env: got.append(env.body))
    frames = bus.publisher(t.frames, Frame)
    for i in range(3):
        frames.put(_frame(i))
        bus.drain()
    assert [(f.frame_index, len(f.tracks)) for f in got] == [(0, 2), (2, 0)]
    assert [f.serial for f in got] == [0, 1] and all(f.view is not None for f in got)
