"""SceneGraph versions and deltas, and the receiver-side GraphReplica."""

from __future__ import annotations

import numpy as np

from shared.codec import decode, encode
from shared.graph.scene import (
    BUILDING_ID,
    ApplyResult,
    GraphReplica,
    PlaceGraph,
    SceneGraph,
)
from shared.messages.graph import (
    GraphDelta,
    GraphSnapshot,
    MeshChunk,
    PlaceNode,
    RoomNode,
    SegmentNode,
)


def seg(i, c, rng=None, rows=2, active=True):
    rng = rng or np.random.default_rng(i)
    c = np.asarray(c, float)
    tracks = [10 * i + k for k in range(rows + 1)]
    return SegmentNode(
        id=i, centroid=c, bbox_min=c - 0.1, bbox_max=c + 0.1, tracks=tracks,
        dino=rng.standard_normal(6).astype(np.float32),
        gallery=rng.standard_normal((rows, 4)).astype(np.float32), gallery_tracks=tracks[:rows],
        active=active, num_vertices=25,
    )  # fmt: skip


def places_two_rooms(shift=0.0):
    """Places 0-1 in room 0 (x < 4), 2-3 in room 1, a chain 0-1-2-3."""
    xs = [1.0, 3.0, 5.0, 7.0]
    nodes = [
        PlaceNode(id=k, position=np.array([x + shift, 1.5, 1.0]), radius=0.8, room=0 if x < 4 else 1)
        for k, x in enumerate(xs)
    ]
    rooms = [RoomNode(id=0, centroid=np.array([2.0, 1.5, 1.0])), RoomNode(id=1, centroid=np.array([6.0, 1.5, 1.0]))]
    return PlaceGraph(nodes=nodes, edges=[(0, 1), (2, 1), (2, 3)]), rooms


def mesh(n, seed=0):
    rng = np.random.default_rng(seed)
    return MeshChunk(
        vertices=rng.random((n, 3)).astype(np.float32), colors=rng.integers(0, 255, (n, 3)).astype(np.uint8),
        faces=rng.integers(0, n, (n // 2, 3)).astype(np.int32), segment_ids=rng.integers(-1, 3, n).astype(np.int32),
    )  # fmt: skip


def wire(msg):
    """Through the codec, as a delta travels."""
    return decode(encode(msg, robot_id="r0", seq=1, stamp=0.0), type(msg)).body


def same(a: GraphSnapshot, b: GraphSnapshot) -> bool:
    return encode(a, robot_id="r", seq=0, stamp=0.0) == encode(b, robot_id="r", seq=0, stamp=0.0)


def edge_set(msg):
    return {(e.kind, e.source, e.target) for e in msg.edges}


def test_first_update_has_everything_and_derived_edges():
    g = SceneGraph()
    places, rooms = places_two_rooms()
    d = g.apply_update([seg(0, [0.8, 1.4, 0.5]), seg(1, [6.9, 1.0, 0.3]), seg(2, [3.2, 2.0, 1.0])], [], places, rooms, frame_index=7)
    assert d.graph_seq == 1 and d.frame_index == 7
    assert [s.id for s in d.segments] == [0, 1, 2]
    assert [s.room for s in d.segments] == [0, 1, 0]
    assert len(d.places) == 4 and len(d.rooms) == 2 and not d.removed_edges
    assert edge_set(d) == {
        ("segment_place", 0, 0), ("segment_place", 1, 3), ("segment_place", 2, 1),
        ("place_place", 0, 1), ("place_place", 1, 2), ("place_place", 2, 3),
        ("place_room", 0, 0), ("place_room", 1, 0), ("place_room", 2, 1), ("place_room", 3, 1),
        ("room_building", 0, BUILDING_ID), ("room_building", 1, BUILDING_ID),
    }  # fmt: skip


def test_an_unchanged_update_gives_an_empty_delta():
    g = SceneGraph()
    places, rooms = places_two_rooms()
    segs = [seg(0, [0.8, 1.4, 0.5]), seg(1, [6.9, 1.0, 0.3])]
    g.apply_update(segs, [], places, rooms)
    again = places_two_rooms(shift=1e-4)  # below the tolerance: no churn
    d = g.apply_update([seg(0, [0.8, 1.4, 0.5])], [], again[0], again[1])
    assert d.graph_seq == 2
    assert not (d.segments or d.places or d.rooms or d.edges or d.removed_edges)
    assert not (d.removed_segments or d.removed_places or d.removed_rooms)
    assert g.places[0].position[0] == 1.0  # kept the previous version


def test_removals_take_their_edges_and_removal_wins():
    g = SceneGraph()
    places, rooms = places_two_rooms()
    g.apply_update([seg(0, [0.8, 1.4, 0.5]), seg(1, [6.9, 1.0, 0.3])], [], places, rooms)
    d = g.apply_update([seg(1, [6.9, 1.0, 0.4])], [1], None, None)
    assert d.removed_segments == [1] and not d.segments
    assert edge_set(GraphDelta(graph_seq=0, frame_index=0, edges=d.removed_edges)) == {("segment_place", 1, 3)}
    # Drop room 1 and place 3: their edges go, segment 0 stays in room 0.
    nodes = [p for p in places.nodes if p.id != 3]
    nodes[2] = nodes[2].model_copy(update={"room": None})
    d = g.apply_update([], [], PlaceGraph(nodes, [(0, 1), (1, 2), (2, 3)]), rooms[:1])
    assert d.removed_places == [3] and d.removed_rooms == [1]
    assert [p.id for p in d.places] == [2]
    assert edge_set(GraphDelta(graph_seq=0, frame_index=0, edges=d.removed_edges)) == {
        ("place_place", 2, 3), ("place_room", 2, 1), ("place_room", 3, 1), ("room_building", 1, BUILDING_ID),
    }  # fmt: skip
    assert ("place_place", 1, 2) in g.edges and all(k[2] != 3 for k in g.edges if k[0] == "place_place")


def test_locator_is_used_and_checked():
    g = SceneGraph()
    places, rooms = places_two_rooms()
    # A locator that says "place 2" for everything east of x = 3, and a stale id 99 west of it.
    places.locate = lambda pts: np.where(pts[:, 0] > 3, 2, 99)
    g.apply_update([seg(0, [3.1, 1.5, 0.5]), seg(1, [0.5, 1.5, 0.5])], [], places, rooms)
    assert ("segment_place", 0, 2) in g.edges  # the locator's choice, not the Euclidean place 1
    assert ("segment_place", 1, 0) in g.edges  # unknown id: Euclidean fallback
    assert g.segments[0].room == 1


def random_session(steps=40, seed=0):
    """A graph driven through random changes; yields each delta."""
    rng = np.random.default_rng(seed)
    g = SceneGraph()
    next_id, live = 0, {}
    place_ids = list(range(6))
    for step in range(steps):
        changed, removed = [], []
        for _ in range(rng.integers(0, 4)):
            if live and rng.random() < 0.5:
                sid = int(rng.choice(list(live)))
                changed.append(seg(sid, live[sid] + rng.normal(0, 0.05, 3), rng, rows=int(rng.integers(0, 3)), active=bool(rng.random() < 0.7)))
            else:
                live[next_id] = rng.uniform([0, 0, 0], [8, 3, 2])
                changed.append(seg(next_id, live[next_id], rng))
                next_id += 1
        if live and rng.random() < 0.2:
            sid = int(rng.choice(list(live)))
            removed.append(sid)
            del live[sid]
        places = rooms = None
        if step % 5 == 0:
            if rng.random() < 0.5:
                place_ids = sorted(set(place_ids[1:]) | {max(place_ids) + 1})
            nodes = [
                PlaceNode(id=p, position=rng.uniform([0, 0, 1], [8, 3, 1]), radius=float(rng.uniform(0.2, 1)), room=int(p % 2))
                for p in place_ids
            ]
            edges = [(place_ids[k], place_ids[k + 1]) for k in range(len(place_ids) - 1)]
            places = PlaceGraph(nodes, edges)
            rooms = [RoomNode(id=r, centroid=rng.uniform([0, 0, 1], [8, 3, 1])) for r in range(2 if step < 20 else 1)]
        m = mesh(int(rng.integers(3, 30)), step) if step % 7 == 3 else None
        yield g, g.apply_update(changed, removed, places, rooms, m, frame_index=step * 10)


def test_every_delta_applied_to_a_replica_equals_the_snapshot():
    replica = GraphReplica()
    for g, delta in random_session():
        assert replica.apply_delta(wire(delta)) is ApplyResult.APPLIED
        assert same(replica.snapshot(with_mesh=True), g.snapshot(with_mesh=True))
    assert g.graph_seq == 40 and len(g.segments) > 5


def test_gap_needs_a_snapshot_and_duplicates_are_ignored():
    session = random_session(steps=12, seed=3)
    replica = GraphReplica()
    pairs = list(session)
    deltas = [d for _, d in pairs]
    g_final = pairs[-1][0]
    assert replica.apply_delta(deltas[0]) is ApplyResult.APPLIED
    before = replica.snapshot(True)
    assert replica.apply_delta(deltas[2]) is ApplyResult.NEED_SNAPSHOT
    assert same(replica.snapshot(True), before)  # untouched by the refused delta
    assert replica.apply_delta(deltas[0]) is ApplyResult.STALE
    # A fresh replica joining late also asks for a snapshot.
    assert GraphReplica().apply_delta(deltas[5]) is ApplyResult.NEED_SNAPSHOT

    # Recover: a snapshot at version 9 (rebuilt by replaying), then deltas 10..12.
    mid = GraphReplica()
    for d in deltas[:9]:
        mid.apply_delta(d)
    replica.apply_snapshot(wire(mid.snapshot(with_mesh=True)))
    assert replica.graph_seq == 9
    assert replica.apply_delta(deltas[8]) is ApplyResult.STALE
    for d in deltas[9:]:
        assert replica.apply_delta(d) is ApplyResult.APPLIED
    assert same(replica.snapshot(True), g_final.snapshot(True))


def test_resume_from_snapshot_continues_versions():
    *_, (g, _) = random_session(steps=10, seed=5)
    snap = wire(g.snapshot(with_mesh=True))
    resumed = SceneGraph.from_snapshot(snap)
    assert same(resumed.snapshot(True), g.snapshot(True))
    replica = GraphReplica()
    replica.apply_snapshot(snap)
    d = resumed.apply_update([seg(500, [1.0, 1.0, 1.0])], [], resumed.place_graph(), list(resumed.rooms.values()))
    assert d.graph_seq == 11
    assert [s.id for s in d.segments] == [500] and not d.places and not d.removed_edges
    assert replica.apply_delta(d) is ApplyResult.APPLIED
    assert same(replica.snapshot(True), resumed.snapshot(True))


def test_snapshot_without_mesh_keeps_the_replica_mesh():
    g = SceneGraph()
    g.apply_update(mesh=mesh(10))
    replica = GraphReplica()
    # Delta 1 carried the mesh and was missed: delta 2 shows the gap.
    assert replica.apply_delta(g.apply_update([seg(0, [1, 1, 1])])) is ApplyResult.NEED_SNAPSHOT
    assert replica.mesh is None
    replica.apply_snapshot(g.snapshot(with_mesh=True))
    replica.apply_snapshot(g.snapshot(with_mesh=False))
    assert replica.mesh is not None and replica.mesh.vertices.shape == (10, 3)
