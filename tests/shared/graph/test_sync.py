"""The replica behind the query service and the viewer: deltas in order, a snapshot on a gap
or a late join, deltas held meanwhile and none lost, requests retried with backoff."""

from __future__ import annotations

import numpy as np
import pytest

from shared.graph.sync import ReplicaSync
from shared.messages.graph import GraphDelta, GraphSnapshot, MeshChunk, SegmentNode
from shared.runtime.bus import BusError


def seg(i: int) -> SegmentNode:
    c = np.zeros(3)
    return SegmentNode(id=i, centroid=c, bbox_min=c, bbox_max=c, tracks=[i], dino=np.ones(2, np.float32),
                       gallery=np.ones((1, 2), np.float32), gallery_tracks=[i], active=True)  # fmt: skip


def delta(n: int) -> GraphDelta:
    return GraphDelta(graph_seq=n, frame_index=n, segments=[seg(n)])


def snapshot(n: int) -> GraphSnapshot:
    return GraphSnapshot(graph_seq=n, frame_index=n, segments=[seg(i) for i in range(1, n + 1)])


def test_from_the_start_deltas_alone_build_the_graph():
    seen = []
    s = ReplicaSync(on_change=lambda r, mesh: seen.append(r.graph_seq))
    assert not s.synced
    for n in (1, 2, 3):
        assert not s.on_delta(delta(n))
    assert s.synced and s.graph_seq == 3 and seen == [1, 2, 3] and s.snapshots == 0


def test_late_join_holds_deltas_until_the_snapshot():
    s = ReplicaSync()
    assert s.on_delta(delta(5)) and s.on_delta(delta(6)) and not s.synced
    assert s.on_snapshot(snapshot(5))  # the held 6 is applied on top
    assert s.synced and s.graph_seq == 6 and sorted(s.replica.segments) == list(range(1, 7))


def test_a_gap_resynchronises_and_loses_nothing():
    s = ReplicaSync()
    for n in (1, 2):
        s.on_delta(delta(n))
    assert s.on_delta(delta(4)) and not s.synced and s.gaps == 1  # 3 was lost on the way
    assert not s.on_delta(delta(5)) or not s.synced
    assert s.on_snapshot(snapshot(4))
    assert s.synced and s.graph_seq == 5 and sorted(s.replica.segments) == [1, 2, 3, 4, 5]


def test_a_snapshot_older_than_a_held_gap_asks_again():
    s = ReplicaSync()
    s.on_delta(delta(1))
    s.on_delta(delta(5))  # gap after 1
    assert not s.on_snapshot(snapshot(3))  # 4 still missing
    assert not s.synced
    assert s.on_snapshot(snapshot(4)) and s.synced and s.graph_seq == 5


def test_a_stale_snapshot_answer_is_ignored_once_in_sync():
    s = ReplicaSync()
    for n in (1, 2, 3):
        s.on_delta(delta(n))
    assert s.on_snapshot(snapshot(2)) and s.graph_seq == 3


def test_stale_deltas_and_the_held_ones_a_snapshot_covers_are_counted():
    s = ReplicaSync()
    for n in (1, 2):
        s.on_delta(delta(n))
    assert not s.on_delta(delta(2)) and s.stale == 1
    s.on_delta(delta(4))
    s.on_delta(delta(5))
    assert s.on_snapshot(snapshot(5)) and s.stale == 3 and s.deltas == 2  # 4 and 5 came with it


def test_resync_asks_when_due_and_backs_off_while_nobody_answers():
    s = ReplicaSync(retry_min_s=0.5, retry_max_s=2.0)
    asked: list[float] = []

    def absent(now: float):
        def fetch():
            asked.append(now)
            raise BusError("no queryable")

        return fetch

    # A new replica asks at once; each failure doubles the wait, up to retry_max_s.
    for now in (0.0, 0.1, 0.5, 1.0, 1.4, 1.5, 3.0, 3.4, 3.5, 5.5):
        s.resync(now, absent(now))
    assert asked == [0.0, 0.5, 1.5, 3.5, 5.5]
    assert (s.requests, s.failures) == (5, 5)
    # Fusion answers: in sync, and nothing more is due.
    assert s.resync(7.5, lambda: snapshot(2)) is True and s.synced and s.graph_seq == 2
    assert s.resync(7.6, lambda: pytest.fail("asked while in sync")) is None
    # A gap is news: the next request goes out at once, whatever the backoff was.
    s.on_delta(delta(4))
    assert s.due(7.6) and s.resync(7.6, lambda: snapshot(4)) and s.graph_seq == 4


def test_a_snapshot_too_old_for_the_held_deltas_is_asked_again_at_once():
    s = ReplicaSync(retry_min_s=1.0)
    s.on_delta(delta(1))
    s.on_delta(delta(5))
    assert s.resync(0.0, lambda: snapshot(3)) is False and s.due(0.0)
    assert s.resync(0.0, lambda: snapshot(4)) is True and s.graph_seq == 5


def test_mesh_changes_are_told_to_the_owner():
    seen = []
    s = ReplicaSync(on_change=lambda r, mesh: seen.append((r.graph_seq, mesh)))
    mesh = MeshChunk(vertices=np.zeros((3, 3), np.float32), colors=np.zeros((3, 3), np.uint8),
                     faces=np.array([[0, 1, 2]], np.int32), segment_ids=np.full(3, -1, np.int32))  # fmt: skip
    s.on_delta(delta(1))
    s.on_delta(delta(2).model_copy(update={"mesh": mesh}))
    s.on_delta(delta(4))  # gap
    s.on_snapshot(snapshot(3))
    assert seen == [(1, False), (2, True), (4, False)]
    assert s.replica.mesh is not None  # a snapshot without a mesh keeps the replica's
