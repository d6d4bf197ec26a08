"""The live viewer on loopback Zenoh: deltas with a gap, snapshot resync (after a failed
request), tracked frames, a bad payload, liveliness, and the recording it leaves."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest
from test_recording import BOXES, make_mesh, make_segment, make_tracked

from services.viewer import recording as vr
from services.viewer.node import ViewerNode
from shared.config import TransportConfig
from shared.config.root import TrackGraphConfig
from shared.graph.scene import PlaceGraph, SceneGraph
from shared.messages.frames import TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, PlaceNode, RoomNode, SnapshotRequest
from shared.topics import Topics
from shared.transport import LivelinessWatcher, TypedPublisher, TypedQueryable, open_session

pytestmark = pytest.mark.zenoh


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(fn, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if fn():
            return True
        time.sleep(0.02)
    return False


@pytest.fixture
def pair():
    port = free_port()
    a = open_session(TransportConfig(mode="peer", connect=[], listen=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
    b = open_session(TransportConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
    try:
        yield a, b
    finally:
        b.close()
        a.close()


def _updates(graph: SceneGraph) -> list[GraphDelta]:
    """Six versions: segments appear one by one, then places and rooms, then a mesh."""
    places = PlaceGraph(
        nodes=[PlaceNode(id=k, position=np.array([x, 2.0, 1.0]), radius=0.5, room=int(x > 3)) for k, x in enumerate((1.0, 2.5, 4.5))],
        edges=[(0, 1), (1, 2)],
    )
    rooms = [RoomNode(id=0, centroid=np.array([1.5, 2.0, 1.0])), RoomNode(id=1, centroid=np.array([4.5, 2.0, 1.0]))]
    segs = [make_segment(i, lo, hi, None) for i, (lo, hi) in BOXES.items()]
    return [
        graph.apply_update(segments_changed=[segs[0]], frame_index=0),
        graph.apply_update(segments_changed=[segs[1]], frame_index=1),
        graph.apply_update(places=places, rooms=rooms, frame_index=2),
        graph.apply_update(segments_changed=[segs[2]], frame_index=3),
        graph.apply_update(mesh=make_mesh(), frame_index=4),
        graph.apply_update(segments_removed=[1], frame_index=5),
    ]


def test_viewer_resyncs_after_a_gap_and_records(pair, tmp_path):
    a, b = pair
    topics = Topics("robot0")
    cfg = TrackGraphConfig(transport=TransportConfig(mode="peer", connect=[], shared_memory=False, query_timeout_s=0.5))
    out = tmp_path / "live.rrd"
    watcher = LivelinessWatcher(a, topics.alive_all)
    node = ViewerNode(cfg, out, session=b, frame_every=2)
    deltas = TypedPublisher(a, topics.graph_delta, GraphDelta, robot_id="robot0")
    frames = TypedPublisher(a, topics.tracks_frame, TrackedFrame, robot_id="robot0")
    queryable = None
    graph = SceneGraph()

    def figures() -> dict:
        return node.book.report().figures

    def inputs() -> dict:
        return {i.name: i for i in node.book.report().inputs}

    try:
        assert watcher.wait_for(topics.alive("viewer"), timeout=5)
        assert deltas.wait_for_subscribers(5) and frames.wait_for_subscribers(5)
        d = _updates(graph)  # graph is now at version 6
        deltas.put(d[0])
        deltas.put(d[1])
        assert wait_until(lambda: figures()["graph_seq"] == 2)  # there from the start: no snapshot needed
        assert figures()["synced"]

        # A gap (3 lost) while no snapshot service runs: requests fail and are retried with
        # backoff, the replica stays at 2 and the deltas that keep coming are held.
        failed = figures()["snapshot_failures"]
        deltas.put(d[3])
        assert wait_until(lambda: figures()["snapshot_failures"] > failed)
        f = figures()
        assert f["graph_seq"] == 2 and not f["synced"] and f["gaps"] == 1
        deltas.put(d[4])

        # A bad payload is rejected by the link, counted in the book, and changes nothing.
        a.put(topics.graph_delta, b"\x00not msgpack")
        assert wait_until(lambda: inputs()["graph_delta"].rejected == 1)
        assert node.stats()["links"][topics.graph_delta]["rejected"] == 1

        requests = []

        def serve(env):
            requests.append(env.body.with_mesh)
            return graph.snapshot(with_mesh=env.body.with_mesh)

        queryable = TypedQueryable(a, topics.graph_snapshot, SnapshotRequest, GraphSnapshot, serve, robot_id="robot0")
        # The next retry gets the snapshot at 6, which already has the held 4 and 5.
        assert wait_until(lambda: figures()["snapshots"] == 1)
        assert requests == [True]  # the viewer wants the mesh
        later = graph.apply_update(segments_changed=[make_segment(7, (0, 0, 0), (1, 1, 1), None)], frame_index=6)
        deltas.put(later)
        assert wait_until(lambda: figures()["graph_seq"] == 7)
        f = figures()
        assert (f["deltas"], f["snapshots"], f["stale"], f["synced"]) == (3, 1, 2, True)
        assert sorted(node.replica.segments) == [0, 2, 7]
        assert node.replica.mesh is not None

        for k in range(4):
            frames.put(make_tracked(index=k))
            assert wait_until(lambda k=k: figures()["frames_received"] == k + 1)
        assert figures()["frames_logged"] == 2  # frames 0 and 2
        report = node.book.report()
        assert report.state == "running" and report.errors == 0 and inputs()["tracks_frame"].processed == 4
    finally:
        node.close()
        if queryable is not None:
            queryable.close()
        deltas.close()
        frames.close()
    assert watcher.wait_for(topics.alive("viewer"), present=False, timeout=5)
    watcher.close()

    assert out.stat().st_size > 5_000
    paths = vr.entity_paths(out)
    assert {"/" + p for p in (vr.SEGMENT_BOXES, vr.MESH, vr.PLACES, vr.RGB_IMAGE, vr.TRACKS_IMAGE, vr.TRAJECTORY)} <= paths
    # The newest graph version in the file has the segments of the replica (1 removed).
    from rerun.chunk import RrdReader

    rows = []
    for c in RrdReader(out).stream().to_chunks():
        if str(c.entity_path) == "/" + vr.SEGMENT_BOXES:
            rb = c.to_record_batch()
            rows += zip(rb.column(vr.GRAPH_TIMELINE).to_pylist(), rb.column("Boxes3D:labels").to_pylist(), strict=True)
    seq, labels = max(rows, key=lambda r: r[0])
    assert seq == 7 and [lab.split()[0] for lab in labels] == ["0", "2", "7"]
    node.close()  # twice is harmless
