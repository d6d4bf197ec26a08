"""The replica behind the query service: deltas in order, a snapshot on a gap or a late join,
deltas held meanwhile and none lost."""

from __future__ import annotations

import numpy as np

from shared.graph.sync import ReplicaSync
from shared.messages.graph import GraphDelta, GraphSnapshot, SegmentNode


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
    s = ReplicaSync(on_change=lambda r: seen.append(r.graph_seq))
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
