"""The viewer session over the in-process bus, without Zenoh: a late join and a gap are
repaired from a snapshot (with the mesh) in ``tick``, the deltas held meanwhile applied, and
the recording holds the newest graph."""

from __future__ import annotations

from test_recording import BOXES, make_mesh, make_segment, make_tracked

from services.viewer import recording as vr
from services.viewer.session import ViewerSession
from shared.config.root import TrackGraphConfig
from shared.graph.scene import SceneGraph
from shared.messages.frames import TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, SnapshotRequest
from shared.runtime.bus import InProcessBus
from shared.topics import Topics

TOPICS = Topics("robot0")


def test_late_join_gap_and_held_deltas(tmp_path):
    bus = InProcessBus("robot0")
    graph = SceneGraph()
    segs = [make_segment(i, lo, hi, None) for i, (lo, hi) in BOXES.items()]
    graph.apply_update(segments_changed=[segs[0]], frame_index=0)  # before the viewer existed
    graph.apply_update(mesh=make_mesh(), frame_index=1)
    pub_d = bus.publisher(TOPICS.graph_delta, GraphDelta)
    pub_f = bus.publisher(TOPICS.tracks_frame, TrackedFrame)
    out = tmp_path / "live.rrd"
    viewer = ViewerSession(TrackGraphConfig(), bus, out, frame_every=3)
    asked: list[bool] = []
    try:
        assert "trackgraph/robot0/alive/viewer" in bus.alive
        assert viewer.tick(0.0) is False  # no fusion yet: retried after the backoff
        d3 = graph.apply_update(segments_changed=[segs[1]], frame_index=2)
        pub_d.put(d3)
        bus.drain()
        assert viewer.sync.held == 1 and viewer.sync.graph_seq == 0

        def serve(env):
            asked.append(env.body.with_mesh)
            return graph.snapshot(with_mesh=env.body.with_mesh)

        bus.serve(TOPICS.graph_snapshot, SnapshotRequest, GraphSnapshot, serve)
        assert viewer.tick(0.1) is None  # still in the backoff
        assert viewer.tick(1.0) is True and asked == [True]
        assert viewer.sync.graph_seq == 3 and sorted(viewer.sync.replica.segments) == [0, 1]
        assert viewer.sync.replica.mesh is not None

        # A lost delta: the next one is held, the snapshot brings the replica past both.
        graph.apply_update(segments_changed=[segs[2]], frame_index=3)
        pub_d.put(graph.apply_update(segments_removed=[0], frame_index=4))
        bus.drain()
        assert not viewer.sync.synced and viewer.sync.gaps == 1
        assert viewer.tick(1.01) is True and viewer.sync.graph_seq == 5 and sorted(viewer.sync.replica.segments) == [1, 2]

        for k in range(5):
            pub_f.put(make_tracked(index=k))
            bus.drain()
        report = viewer.book.report()
        f = report.figures
        assert (f["deltas"], f["snapshots"], f["stale"], f["frames_logged"], f["frames_received"]) == (0, 2, 2, 2, 5)
        assert {i.name: i.processed for i in report.inputs} == {"graph_delta": 2, "graph_snapshot": 2, "tracks_frame": 5}
        assert report.published == {"graph_snapshot": 3} and report.errors == 0
    finally:
        viewer.close()
        bus.close()
    assert "trackgraph/robot0/alive/viewer" not in bus.alive
    paths = vr.entity_paths(out)
    assert {"/" + p for p in (vr.SEGMENT_BOXES, vr.MESH, vr.RGB_IMAGE, vr.TRAJECTORY)} <= paths


def test_latest_frames_only_and_drops_counted(tmp_path):
    bus = InProcessBus("robot0")
    viewer = ViewerSession(TrackGraphConfig(), bus, tmp_path / "v.rrd", frame_every=1)
    pub_f = bus.publisher(TOPICS.tracks_frame, TrackedFrame)
    try:
        for k in range(4):
            pub_f.put(make_tracked(index=k))
        bus.drain()  # the viewer keeps only the newest frame
        counts = {i.name: i for i in viewer.book.report().inputs}["tracks_frame"]
        assert (counts.received, counts.dropped, viewer.frames_logged) == (1, 3, 1)
    finally:
        viewer.close()
        viewer.close()  # twice is harmless
        bus.close()
