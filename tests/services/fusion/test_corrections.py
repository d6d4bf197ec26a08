"""Pose corrections in the fusion core and session: the map follows the corrected trajectory,
corrections are absolute and idempotent, late ones still correct, bad ones change nothing.

Ground-truth tracks on a small drifting scene keep fusion apart from tracking errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.fusion.core import FusionCore
from services.fusion.corrections.poses import CorrectionError
from services.fusion.session import FusionSession
from services.mapping import prepare_config
from services.tracker.build import build_tracker
from shared.config import TrackGraphConfig
from shared.datasets import open_sequence
from shared.messages.poses import PoseCorrection
from shared.runtime.bus import InProcessBus
from tests.services.fusion.conftest import FRAMES

pytestmark = pytest.mark.slow

GT_TRACKS = {"keyframe_vl": {"vl": {"backend": "simulated"}}, "tracker": {"mode": "ground_truth"}}
CLOSURE = 40
"""The frame of the (made-up) loop closure: the back end sends the true poses up to it."""


def _true(seq) -> np.ndarray:
    return np.loadtxt(seq / "traj_gt.txt").reshape(-1, 4, 4)


def _correction(seq, cid: int = 1, upto: int = CLOSURE, shift: float = 0.0) -> PoseCorrection:
    poses = _true(seq)[: upto + 1].copy()
    poses[:, 0, 3] += shift
    return PoseCorrection(correction_id=cid, frame_index=upto, frames=np.arange(upto + 1), poses=poses)


class Mapper:
    """A fusion core fed by the ground-truth tracker, frame by frame."""

    def __init__(self, seq, true_poses: bool = False) -> None:
        self.cfg = prepare_config(TrackGraphConfig.model_validate(GT_TRACKS), seq)
        self.reader = open_sequence(seq)
        self.tracker = build_tracker(self.cfg)
        self.core = FusionCore(self.cfg.fusion, device="cpu")
        self.true = _true(seq) if true_poses else None
        self.next = 0

    def track(self, i: int):
        """Frame ``i`` tracked, and the track features it released (or None)."""
        frame = self.reader.frame(i)
        if self.true is not None:
            frame = frame.model_copy(update={"T_world_cam": self.true[i]})
        self.tracker.begin_frame(frame)
        return self.tracker.end_frame(), self.tracker.take_track_features(i)

    def run(self, upto: int) -> FusionCore:
        for i in range(self.next, upto):
            tracked, feats = self.track(i)
            if feats is not None:
                self.core.add_track_features(feats)
            self.core.add_frame(tracked)
        self.next = max(self.next, upto)
        return self.core

    def feed(self, session: FusionSession, frames) -> None:
        """The frames through a fusion session (on this mapper's core) instead."""
        for i in frames:
            tracked, feats = self.track(i)
            if feats is not None:
                session._apply_features(feats)
            session._apply_frame(tracked)


def _points(core: FusionCore) -> np.ndarray:
    return np.concatenate([s.positions for s in core.segments.segments.values() if s.num_vertices])


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """Median distance from the points of ``a`` to their nearest in ``b``."""
    return float(np.median(cKDTree(b).query(a)[0]))


def _state(core: FusionCore) -> dict:
    """What the map holds: segments (geometry, tracks), TSDF arrays, surface, poses."""
    t = core.tsdf.state_dict()
    return {
        "segments": {s.id: (sorted(s.tracks), s.positions.copy(), s.anchors.copy()) for s in core.segments.segments.values()},
        "tsdf": {k: np.asarray(v).copy() for k, v in t.items() if k != "epoch"},
        "surface": core.surface_points().copy(),
        "trajectory": np.stack(core.trajectory).copy(),
        "graph_seq": core.graph.graph_seq,
    }


def _assert_same_state(a: dict, b: dict) -> None:
    assert a["graph_seq"] == b["graph_seq"]
    assert a["segments"].keys() == b["segments"].keys()
    for sid, (tracks, pos, anchors) in a["segments"].items():
        assert tracks == b["segments"][sid][0]
        assert np.array_equal(pos, b["segments"][sid][1]) and np.array_equal(anchors, b["segments"][sid][2])
    for k, v in a["tsdf"].items():
        assert np.array_equal(v, b["tsdf"][k]), k
    assert np.array_equal(a["surface"], b["surface"]) and np.array_equal(a["trajectory"], b["trajectory"])


def test_the_map_moves_to_the_corrected_poses_and_segments_keep_their_ids(drifting):
    truth = Mapper(drifting, true_poses=True).run(CLOSURE + 1)
    drift = Mapper(drifting).run(CLOSURE + 1)
    before = _distance(_points(drift), _points(truth))
    ids_before = sorted(drift.segments.segments)
    out = drift.apply_correction(_correction(drifting))
    after = _distance(_points(drift), _points(truth))
    assert out.status == "applied" and out.frames_moved == CLOSURE  # frame 0 is exact
    # what is left is the blur of surfaces fused from frames that drifted apart before the closure
    assert before > 0.03 and after < 0.4 * before, (before, after)
    # every segment moved under its own id (unless re-identification merged it), and the
    # delta carries each with its new place
    kept = set(ids_before) - set(out.delta.removed_segments)
    assert len(kept) >= len(ids_before) - 2 and kept <= set(drift.segments.segments)
    sent = {s.id: s for s in out.delta.segments}
    assert kept <= set(sent)
    for sid in kept:
        np.testing.assert_allclose(sent[sid].centroid, drift.segments.segments[sid].centroid)
    # the trajectory is the true one now; new frames follow the fix (map -> odom)
    np.testing.assert_allclose(np.stack(drift.trajectory), _true(drifting)[: CLOSURE + 1, :3, 3], atol=1e-9)


def test_new_frames_after_a_correction_follow_it(drifting):
    m = Mapper(drifting)
    m.run(CLOSURE + 1)
    m.core.apply_correction(_correction(drifting))
    m.run(CLOSURE + 21)
    got = np.stack(m.core.trajectory)[CLOSURE + 1 :]
    true = _true(drifting)[CLOSURE + 1 : CLOSURE + 21, :3, 3]
    odom = np.loadtxt(drifting / "traj.txt").reshape(-1, 4, 4)[CLOSURE + 1 : CLOSURE + 21, :3, 3]
    # drift starts again from the closure: far nearer the truth than the raw odometry
    err, err_odom = np.linalg.norm(got - true, axis=1), np.linalg.norm(odom - true, axis=1)
    assert err.mean() < 0.5 * err_odom.mean() and err[0] < 0.02


def test_the_same_correction_twice_or_an_older_one_after_a_newer_leaves_the_map_unchanged(drifting):
    m = Mapper(drifting)
    m.run(CLOSURE + 10)
    m.core.apply_correction(_correction(drifting, cid=1, shift=0.1))
    m.core.apply_correction(_correction(drifting, cid=2))
    once = _state(m.core)
    assert m.core.apply_correction(_correction(drifting, cid=2)).status == "unchanged"  # the same message
    assert m.core.apply_correction(_correction(drifting, cid=3)).status == "unchanged"  # the same poses, a newer id
    with pytest.raises(CorrectionError, match="older correction after a newer one"):
        m.core.apply_correction(_correction(drifting, cid=1, shift=0.1))
    _assert_same_state(_state(m.core), once)
    assert m.core.corrections.applied == 2 and m.core.corrections.unchanged == 2 and m.core.corrections.refused == 1


def test_a_correction_100_frames_late_still_gives_the_corrected_map(drifting):
    on_time = Mapper(drifting)
    on_time.run(CLOSURE + 1)
    on_time.core.apply_correction(_correction(drifting))
    on_time.run(FRAMES)
    late = Mapper(drifting)
    late.run(CLOSURE + 101)
    late.core.apply_correction(_correction(drifting))
    late.run(FRAMES)
    never = Mapper(drifting).run(FRAMES)
    truth = Mapper(drifting, true_poses=True).run(FRAMES)
    # frames fused after the closure (before the correction came) move with the fix too
    np.testing.assert_allclose(np.stack(late.core.trajectory), np.stack(on_time.core.trajectory), atol=1e-9)
    d_on, d_late, d_never = (_distance(_points(m), _points(truth)) for m in (on_time.core, late.core, never))
    # the odometry drifts again after the closure in both, and the late one as the on-time one
    assert d_late < 0.7 * d_never and d_late < d_on + 0.01, (d_on, d_late, d_never)


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ({"frames": [0, 500]}, "unknown"),
        ({"correction_id": 0}, "older correction after a newer one"),
    ],
)
def test_a_refused_correction_is_counted_and_changes_nothing(drifting, bad, why):
    m = Mapper(drifting)
    m.run(30)
    m.core.apply_correction(_correction(drifting, cid=5, upto=20))
    before = _state(m.core)
    c = _correction(drifting, cid=6, upto=25)
    data = {**c.model_dump(), **{k: v for k, v in bad.items() if k != "frames"}}
    if "frames" in bad:
        data.update(frames=np.asarray(bad["frames"]), poses=np.stack([np.eye(4)] * len(bad["frames"])), frame_index=max(bad["frames"]))
    with pytest.raises(CorrectionError, match=why):
        m.core.apply_correction(PoseCorrection.model_validate(data))
    _assert_same_state(_state(m.core), before)
    assert m.core.corrections.refused == 1


def test_the_session_holds_counts_and_journals_corrections(drifting, tmp_path):
    """Over the bus: a correction waits for its frame; hostile or refused ones are counted, and
    the map goes on."""
    m = Mapper(drifting)
    bus = InProcessBus(m.cfg.robot_id)
    session = FusionSession(bus, m.cfg, m.core)
    try:
        topic = session.topics.poses_correction
        early = _correction(drifting, cid=1, upto=10).model_copy(update={"apply_after_frame": 15})
        pub = bus.publisher(topic, PoseCorrection)
        pub.put(_correction(drifting, cid=9, upto=10).model_copy(update={"apply_after_frame": 1000}))  # due at the map's end
        pub.put(early)
        bus.drain()
        assert len(session.corrections.pending) == 2  # nothing fused yet
        m.feed(session, range(16))
        assert [c.correction_id for c in session.corrections.pending] == [9] and m.core.corrections.applied == 1
        assert m.core.book.last_id == 1
        before = _state(m.core)
        pub.put(_correction(drifting, cid=0, upto=10))  # older than the newest
        unknown = _correction(drifting, cid=2, upto=10)
        pub.put(unknown.model_copy(update={"frames": np.r_[0:10, 99], "poses": np.concatenate([unknown.poses[:10], unknown.poses[:1]]), "frame_index": 99}))
        bus.drain()
        _assert_same_state(_state(m.core), before)
        counters = next(c for c in session.book.report().inputs if c.name == "poses_correction")
        assert counters.received == 4 and counters.rejected == 2 and counters.processed == 1
        assert "frame 99 is unknown" in session.corrections.error
        figures = session.book.report().figures["corrections"]
        assert figures["applied"] == 1 and figures["refused"] == 2 and figures["pending"] == 1
    finally:
        session.close(save=False)
        bus.close()


def test_a_restarted_fusion_applies_a_pending_correction_at_the_same_frame(drifting, tmp_path):
    """A correction waiting for its frame is kept in the snapshot, and one that came after it
    in the journal: a fusion killed and resumed applies both where the uninterrupted one does."""
    from shared.graph.store import MapStore

    def session(m: Mapper, out, resume: bool = False) -> FusionSession:
        return FusionSession(InProcessBus(m.cfg.robot_id), m.cfg, m.core, store=MapStore(out / "graph"), out=out, resume=resume)

    first = _correction(drifting, cid=1, upto=8).model_copy(update={"apply_after_frame": 20})
    second = _correction(drifting, cid=2, upto=22).model_copy(update={"apply_after_frame": 24})

    whole = Mapper(drifting)
    s = session(whole, tmp_path / "whole")
    s._on_correction(first)
    whole.feed(s, range(14))
    s._on_correction(second)
    whole.feed(s, range(14, 30))
    s.close(save=False)

    part = Mapper(drifting)
    s = session(part, tmp_path / "part")
    s._on_correction(first)
    part.feed(s, range(10))
    s.save()  # the snapshot holds the pending correction
    part.feed(s, range(10, 14))
    s._on_correction(second)  # in the journal only
    s.disk.journal.sync()
    s.disk.journal.close()  # killed: no final save
    resumed = Mapper(drifting)
    resumed.tracker, resumed.next = part.tracker, 14
    s = session(resumed, tmp_path / "part", resume=True)
    assert [c.correction_id for c in s.corrections.pending] == [1, 2] and resumed.core.last_frame_index == 13
    resumed.feed(s, range(14, 30))
    s.close(save=False)
    assert resumed.core.corrections.applied == whole.core.corrections.applied == 2
    _assert_same_state(_state(resumed.core), _state(whole.core))
