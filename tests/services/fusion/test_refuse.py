"""Re-fusion after pose corrections (``fusion.refuse``): the kept frames fused again at their
corrected poses give the map fusing the true poses gives, segment ids kept; the log on disk
survives a restart."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from services.fusion.corrections.observations import ObservationLog, refuse_wanted
from services.fusion.session import FusionSession
from shared.config import TrackGraphConfig
from shared.runtime.bus import InProcessBus
from tests.services.fusion.test_corrections import Mapper, _correction, _distance, _points, _true

pytestmark = pytest.mark.slow

N = 60


def _mesh(core):
    a = core.tsdf.extract_mesh()
    b = core.tsdf.extract_archived_mesh()
    return np.concatenate([a.vertices, b.vertices]), np.concatenate([a.winners(), b.winners()])


def test_refusing_after_a_correction_of_every_frame_gives_the_true_pose_map(drifting):
    truth = Mapper(drifting, true_poses=True).run(N)
    m = Mapper(drifting)
    m.core.observations = ObservationLog()
    m.run(N)
    m.core.apply_correction(_correction(drifting, upto=N - 1))
    moved = _distance(_points(m.core), _points(truth))
    owner = {t: sid for sid, seg in m.core.segments.segments.items() for t in seg.tracks}
    stats = m.core.refuse()
    assert stats is not None and stats.frames == N and stats.kept_mb > 0
    # The grid is the true-pose grid, voxel for voxel: the same surface, the same winning tracks.
    v, w = _mesh(m.core)
    tv, tw = _mesh(truth)
    order, torder = np.lexsort(v.T), np.lexsort(tv.T)
    np.testing.assert_array_equal(v[order], tv[torder])
    np.testing.assert_array_equal(w[order], tw[torder])
    # Every track stays in its segment, under its id (a track that now has enough surface may
    # start a segment of its own), and the segments lie on the true surface, closer than the
    # move put them.
    refused = _distance(_points(m.core), _points(truth))
    assert owner and all(m.core.segments.segment_of_track(t) == sid for t, sid in owner.items())
    assert refused < 0.5 * moved and refused < 0.01, (moved, refused)
    assert m.core.corrections.refused_frames == N and m.core.corrections.seconds_refuse > 0
    # Once per correction: nothing new to do until the next one.
    assert m.core.refuse() is None


def test_finish_refuses_only_after_a_correction(drifting):
    m = Mapper(drifting)
    m.core.observations = ObservationLog()
    m.run(20)
    m.core.finish()
    assert m.core.corrections.refused_frames == 0
    m.core.apply_correction(_correction(drifting, upto=10))
    m.run(30)
    m.core.finish()
    assert m.core.corrections.refused_frames == 30
    # Frames after the correction were re-fused where its fix puts them, as fusion put them.
    np.testing.assert_allclose(np.stack(m.core.trajectory)[:11], _true(drifting)[:11, :3, 3], atol=1e-9)


def test_a_log_that_lacks_frames_is_not_used(drifting, caplog):
    m = Mapper(drifting)
    m.run(10)
    m.core.observations = ObservationLog()  # kept from frame 10 on only
    m.run(20)
    m.core.apply_correction(_correction(drifting, upto=15))
    with caplog.at_level(logging.WARNING, logger="services.fusion.core"):
        assert m.core.refuse() is None
    assert "the kept observations hold 10 frames, the map fused 20" in caplog.text


def test_the_log_on_disk_reopens_skips_replayed_frames_and_cuts_a_torn_tail(drifting, tmp_path):
    m = Mapper(drifting)
    path = tmp_path / "obs.wal"
    log_ = ObservationLog(path)
    frames = [m.track(i)[0] for i in range(5)]
    for f in frames:
        log_.append(f)
    log_.append(frames[2])  # a journal replay of a frame already kept
    log_.close()
    with open(path, "ab") as fh:
        fh.write(b"TGJR\xff\x00")  # a torn record
    again = ObservationLog(path, fresh=False)
    assert again.frames == [0, 1, 2, 3, 4] and again.covers([0, 1, 2, 3, 4])
    got = list(again)
    assert [g.frame.frame_index for g in got] == [0, 1, 2, 3, 4]
    np.testing.assert_array_equal(got[3].track_ids, frames[3].track_ids)
    np.testing.assert_array_equal(got[3].frame.depth, frames[3].frame.depth)
    again.append(m.track(5)[0])
    again.close()
    assert ObservationLog(path, fresh=False).frames == [0, 1, 2, 3, 4, 5]
    assert ObservationLog(path).frames == []  # a fresh map starts it again


def test_a_restarted_fusion_refuses_every_frame_at_its_end(drifting, tmp_path):
    from shared.graph.store import MapStore

    cfg = TrackGraphConfig.model_validate({"fusion": {"refuse": "on"}})
    assert refuse_wanted(cfg) and not refuse_wanted(TrackGraphConfig())
    assert refuse_wanted(TrackGraphConfig.model_validate({"source": {"corrections": "c.jsonl"}}))

    def session(m: Mapper, resume: bool = False) -> FusionSession:
        c = m.cfg.model_copy(update={"fusion": m.cfg.fusion.model_copy(update={"refuse": "on"})})
        return FusionSession(InProcessBus(m.cfg.robot_id), c, m.core, store=MapStore(tmp_path / "graph"), out=tmp_path, resume=resume)

    part = Mapper(drifting)
    s = session(part)
    part.feed(s, range(12))
    s.save()
    part.feed(s, range(12, 16))  # in the journal and the kept frames, not in the snapshot
    s.disk.journal.sync()
    s.disk.journal.close()
    s.core.observations.close()  # killed
    resumed = Mapper(drifting)
    resumed.tracker, resumed.next = part.tracker, 16
    s = session(resumed, resume=True)
    assert resumed.core.observations.frames == list(range(16))  # the replay added nothing twice
    resumed.feed(s, range(16, 24))
    s._on_correction(_correction(drifting, upto=20))
    s.finish()
    s.close(save=False)
    assert resumed.core.corrections.refused_frames == 24
