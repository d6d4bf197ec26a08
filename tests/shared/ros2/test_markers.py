"""RViz markers, trajectory path and query-hit poses built from the scene graph."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from shared.geometry import quat_to_matrix
from shared.graph.scene import GraphReplica
from shared.messages.graph import Edge, GraphSnapshot, PlaceNode, RoomNode, SegmentNode
from shared.messages.rpc import QueryHit, QueryReply, RoomHit
from shared.ros2.markers import (
    MIN_SCALE_M,
    graph_markers,
    header,
    hits_markers,
    hits_pose_array,
    marker_count,
    pose_msg,
    replica_markers,
    trajectory_path,
)
from shared.ros2.types import decode, encode

FRAME = "map"
STAMP = 1_700_000_123_456_789_000
DELETEALL, ADD = 3, 0
CUBE, LINE_STRIP, LINE_LIST, SPHERE_LIST, TEXT = 1, 4, 5, 7, 9


def seg(i: int, c, size=0.4, active=True, room=None) -> SegmentNode:
    c = np.asarray(c, np.float64)
    h = np.full(3, size / 2)
    return SegmentNode(
        id=i, centroid=c, bbox_min=c - h, bbox_max=c + h, tracks=[i], dino=np.ones(4, np.float32),
        gallery=np.ones((1, 4), np.float32), gallery_tracks=[i], active=active, room=room,
    )


def small_graph():
    segs = [
        seg(3, [0.0, 0.0, 0.5], room=1),
        seg(7, [1.0, 0.5, 0.8], active=False, room=1),
        seg(12, [4.0, 1.0, 0.3], size=0.0, room=2),  # degenerate box: a single point
    ]
    places = [
        PlaceNode(id=1, position=np.array([0.5, 0.0, 1.0]), radius=0.8, room=1, active=True),
        PlaceNode(id=2, position=np.array([1.5, 0.0, 1.0]), radius=0.6, room=1),
        PlaceNode(id=5, position=np.array([4.0, 0.0, 1.0]), radius=0.7, room=2),
    ]
    rooms = [
        RoomNode(id=1, centroid=np.array([1.0, 0.0, 1.0]), name="kitchen",
                 bbox_min=np.array([-1.0, -1.0, 0.0]), bbox_max=np.array([2.5, 1.5, 2.5])),
        RoomNode(id=2, centroid=np.array([4.0, 0.0, 1.0])),  # unnamed, no box
    ]
    edges = [
        Edge(kind="segment_place", source=3, target=1),
        Edge(kind="segment_place", source=7, target=2),
        Edge(kind="segment_place", source=12, target=5),
        Edge(kind="place_place", source=1, target=2),
        Edge(kind="place_place", source=2, target=5),
        Edge(kind="place_room", source=1, target=1),
        Edge(kind="place_room", source=2, target=1),
        Edge(kind="place_room", source=5, target=2),
        Edge(kind="room_building", source=1, target=0),
        Edge(kind="room_building", source=2, target=0),
    ]
    return segs, places, rooms, edges


def replica_of(segs, places, rooms, edges) -> GraphReplica:
    r = GraphReplica()
    r.apply_snapshot(GraphSnapshot(graph_seq=4, frame_index=10, segments=segs, places=places, rooms=rooms, edges=edges))
    return r


def by_ns(arr) -> dict[str, dict[int, object]]:
    out: dict[str, dict[int, object]] = {}
    for m in arr.markers:
        assert m.id not in out.setdefault(m.ns, {}), f"duplicate marker id {m.ns}/{m.id}"
        out[m.ns][m.id] = m
    return out


def same(a, b) -> bool:
    """Equal messages (dataclass == trips on their numpy fields; their CDR bytes do not)."""
    return encode(a) == encode(b)


def assert_well_formed(arr, frame=FRAME, stamp=STAMP):
    """What RViz needs of every marker: a frame, the stamp, w=1, positive finite scales, visible
    colours in [0, 1], forever, not frame-locked; DELETEALL exactly once and first."""
    assert arr.markers[0].action == DELETEALL
    assert sum(m.action == DELETEALL for m in arr.markers) == 1
    for m in arr.markers:
        assert m.header.frame_id == frame
        assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == stamp
        q = m.pose.orientation
        assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
        assert m.scale.x >= MIN_SCALE_M and m.scale.y >= MIN_SCALE_M and m.scale.z >= MIN_SCALE_M
        assert (m.lifetime.sec, m.lifetime.nanosec) == (0, 0) and m.frame_locked is False
        for c in [m.color, *m.colors]:
            assert 0 <= c.r <= 1 and 0 <= c.g <= 1 and 0 <= c.b <= 1 and 0 < c.a <= 1
        nums = [m.pose.position.x, m.pose.position.y, m.pose.position.z, m.scale.x, m.scale.y, m.scale.z]
        nums += [v for p in m.points for v in (p.x, p.y, p.z)]
        assert all(math.isfinite(v) for v in nums), f"{m.ns}/{m.id} has a non-finite number"
        if m.type == LINE_LIST:
            assert len(m.points) % 2 == 0 and m.points
        if m.colors:
            assert len(m.colors) == len(m.points)


def test_graph_markers_namespaces_and_counts():
    segs, places, rooms, edges = small_graph()
    arr = graph_markers(segs, places, rooms, edges, frame_id=FRAME, stamp_ns=STAMP)
    assert_well_formed(arr)
    ns = by_ns(arr)
    assert marker_count(arr) == {
        "": 1, "segments": 3, "centroids": 1, "ids": 3, "places": 1, "rooms": 3,
        "edges/segment_place": 1, "edges/place_place": 1, "edges/place_room": 1, "edges/room_building": 1,
    }
    assert sorted(ns["segments"]) == [3, 7, 12] and sorted(ns["ids"]) == [3, 7, 12]
    assert all(m.type == LINE_LIST and len(m.points) == 24 for m in ns["segments"].values())
    assert [m.text for m in ns["ids"].values()] == ["3", "7", "12"]
    assert ns["centroids"][0].type == SPHERE_LIST and len(ns["centroids"][0].points) == 3
    assert ns["places"][0].type == SPHERE_LIST and len(ns["places"][0].points) == 3
    # room 1: label (2 * id) and footprint (2 * id + 1); room 2 has no box, only a label
    assert sorted(ns["rooms"]) == [2, 3, 4]
    assert ns["rooms"][2].type == TEXT and ns["rooms"][2].text == "kitchen"
    assert ns["rooms"][4].text == "room 2"
    assert ns["rooms"][2].pose.position.z > 1.0  # above the centroid
    foot = ns["rooms"][3]
    assert foot.type == LINE_STRIP and len(foot.points) == 5
    assert (foot.points[0].x, foot.points[0].y) == (foot.points[-1].x, foot.points[-1].y)  # closed
    assert {p.z for p in foot.points} == {0.0}  # on the floor
    for kind, n in [("segment_place", 3), ("place_place", 2), ("place_room", 3), ("room_building", 2)]:
        m = ns[f"edges/{kind}"][0]
        assert m.type == LINE_LIST and len(m.points) == 2 * n


def test_segment_box_geometry_and_colours():
    segs, places, rooms, edges = small_graph()
    ns = by_ns(graph_markers(segs, places, rooms, edges, frame_id=FRAME, stamp_ns=STAMP))
    box3 = np.array([[p.x, p.y, p.z] for p in ns["segments"][3].points])
    np.testing.assert_allclose(box3.min(0), segs[0].bbox_min)
    np.testing.assert_allclose(box3.max(0), segs[0].bbox_max)
    # each of the 12 edges runs along exactly one axis
    d = np.abs(box3[1::2] - box3[0::2])
    assert np.all((d > 1e-9).sum(1) == 1)
    # the degenerate box of segment 12 gets the minimum extent, not zero
    box12 = np.array([[p.x, p.y, p.z] for p in ns["segments"][12].points])
    np.testing.assert_allclose(box12.max(0) - box12.min(0), MIN_SCALE_M)
    # inactive segment 7 is dimmer than active ones
    a, i = ns["segments"][3].color, ns["segments"][7].color
    assert i.a < a.a and max(i.r, i.g, i.b) < max(a.r, a.g, a.b)
    # the centroid sphere of a segment has the segment's colour
    c = ns["centroids"][0].colors[1]
    assert (c.r, c.g, c.b, c.a) == (i.r, i.g, i.b, i.a)
    # distinct ids get distinct colours
    cols = {(m.color.r, m.color.g, m.color.b) for m in ns["segments"].values()}
    assert len(cols) == 3


def test_edges_join_the_right_nodes():
    segs, places, rooms, edges = small_graph()
    ns = by_ns(graph_markers(segs, places, rooms, edges, frame_id=FRAME, stamp_ns=STAMP))
    pts = [(p.x, p.y, p.z) for p in ns["edges/segment_place"][0].points]
    assert pts[:2] == [(0.0, 0.0, 0.5), (0.5, 0.0, 1.0)]  # segment 3 centroid -> place 1
    pts = [(p.x, p.y, p.z) for p in ns["edges/place_room"][0].points]
    assert pts[:2] == [(0.5, 0.0, 1.0), (1.0, 0.0, 1.0)]  # place 1 -> room 1 centroid
    bld = ns["edges/room_building"][0].points
    assert bld[1].z > 2.5 and (bld[1].x, bld[1].y, bld[1].z) == (bld[3].x, bld[3].y, bld[3].z)


def test_ids_stable_and_removed_segment_absent():
    segs, places, rooms, edges = small_graph()
    a = by_ns(graph_markers(segs, places, rooms, edges, frame_id=FRAME, stamp_ns=STAMP))
    # the same graph given in another order: same markers, same ids
    b = by_ns(graph_markers(segs[::-1], places[::-1], rooms[::-1], edges[::-1], frame_id=FRAME, stamp_ns=STAMP))
    assert {k: sorted(v) for k, v in a.items()} == {k: sorted(v) for k, v in b.items()}
    for ns_name in a:
        for i in a[ns_name]:
            assert same(a[ns_name][i], b[ns_name][i])
    # segment 7 removed (its edge goes with it): it is nowhere in the new array
    segs2 = [s for s in segs if s.id != 7]
    edges2 = [e for e in edges if not (e.kind == "segment_place" and e.source == 7)]
    c = by_ns(graph_markers(segs2, places, rooms, edges2, frame_id=FRAME, stamp_ns=STAMP))
    assert sorted(c["segments"]) == [3, 12] and sorted(c["ids"]) == [3, 12]
    assert len(c["centroids"][0].points) == 2 and len(c["edges/segment_place"][0].points) == 4
    assert same(c["segments"][3], a["segments"][3])  # the others keep their ids and looks


def test_replica_adapter_matches_graph_markers_and_drops_dangling_edges():
    segs, places, rooms, edges = small_graph()
    rep = replica_of(segs, places, rooms, edges)
    direct = graph_markers(segs, places, rooms, edges, frame_id=FRAME, stamp_ns=STAMP)
    assert same(replica_markers(rep, frame_id=FRAME, stamp_ns=STAMP), direct)
    # an edge to a segment not given is left out, not drawn to the origin
    extra = [*edges, Edge(kind="segment_place", source=99, target=1)]
    ns = by_ns(graph_markers(segs, places, rooms, extra, frame_id=FRAME, stamp_ns=STAMP))
    assert len(ns["edges/segment_place"][0].points) == 6


def test_show_ids_false_drops_text():
    segs, places, rooms, edges = small_graph()
    arr = graph_markers(segs, places, rooms, edges, frame_id="odom", stamp_ns=5, show_ids=False)
    assert_well_formed(arr, frame="odom", stamp=5)
    assert "ids" not in marker_count(arr)
    assert all(m.type != TEXT for m in arr.markers)
    assert sorted(by_ns(arr)["rooms"]) == [3]  # room 1's footprint stays


def test_empty_graph_is_just_deleteall():
    arr = graph_markers([], [], [], [], frame_id=FRAME, stamp_ns=STAMP)
    assert len(arr.markers) == 1 and arr.markers[0].action == DELETEALL and arr.markers[0].ns == ""
    assert same(replica_markers(GraphReplica(), frame_id=FRAME, stamp_ns=STAMP), arr)
    assert_well_formed(arr)


def test_encode_decode_round_trip():
    segs, places, rooms, edges = small_graph()
    arr = graph_markers(segs, places, rooms, edges, frame_id=FRAME, stamp_ns=STAMP)
    back = decode(encode(arr), "visualization_msgs/msg/MarkerArray")
    assert len(back.markers) == len(arr.markers)
    for m, d in zip(arr.markers, back.markers, strict=True):
        key = [(x.ns, x.id, x.type, x.action, x.text, x.header.frame_id) for x in (m, d)]
        assert key[0] == key[1]
        assert (d.header.stamp.sec, d.header.stamp.nanosec) == (m.header.stamp.sec, m.header.stamp.nanosec)
        assert [(p.x, p.y, p.z) for p in d.points] == [(p.x, p.y, p.z) for p in m.points]
        assert d.scale.x == m.scale.x and d.pose.position.z == m.pose.position.z
        assert d.color.a == pytest.approx(m.color.a) and len(d.colors) == len(m.colors)
    # the other distros' definitions build and encode too
    for distro in ("humble", "kilted"):
        a2 = graph_markers(segs, places, rooms, edges, frame_id=FRAME, stamp_ns=STAMP, distro=distro)
        assert len(decode(encode(a2, distro=distro), "visualization_msgs/msg/MarkerArray", distro).markers) == len(arr.markers)


def random_pose(rng) -> np.ndarray:
    q = rng.normal(size=4)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = rng.normal(size=3)
    return T


def quat_of(pose) -> np.ndarray:
    o = pose.orientation
    return np.array([o.w, o.x, o.y, o.z])


def test_pose_msg_and_header():
    rng = np.random.default_rng(0)
    # random rotations, plus the near-180-degree ones where a naive trace formula divides by ~0
    Ts = [random_pose(rng) for _ in range(20)] + [np.diag([1.0, -1, -1, 1]), np.diag([-1.0, 1, -1, 1]), np.diag([-1.0, -1, 1, 1])]
    for T in Ts:
        p = pose_msg(T)
        q = quat_of(p)
        assert np.linalg.norm(q) == pytest.approx(1.0) and q[0] >= 0
        np.testing.assert_allclose(quat_to_matrix(q), T[:3, :3], atol=1e-9)
        np.testing.assert_allclose([p.position.x, p.position.y, p.position.z], T[:3, 3])
    with pytest.raises(ValueError, match="rigid"):
        pose_msg(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="rigid"):
        pose_msg(np.full((4, 4), np.nan))
    h = header("map", 3_000_000_007)
    assert (h.frame_id, h.stamp.sec, h.stamp.nanosec) == ("map", 3, 7)
    with pytest.raises(ValueError, match="frame_id"):
        header("", 0)
    with pytest.raises(ValueError, match="stamp"):
        header("map", -1)


def test_trajectory_path():
    rng = np.random.default_rng(1)
    poses = np.stack([random_pose(rng) for _ in range(5)])
    stamps = np.arange(5, dtype=np.int64) * 100_000_000 + 10**18
    path = trajectory_path(poses, stamps, frame_id="map")
    assert path.header.frame_id == "map" and len(path.poses) == 5
    assert path.header.stamp.sec * 10**9 + path.header.stamp.nanosec == stamps[-1]
    for T, s, ps in zip(poses, stamps, path.poses, strict=True):
        assert ps.header.frame_id == "map" and ps.header.stamp.sec * 10**9 + ps.header.stamp.nanosec == s
        np.testing.assert_allclose(quat_to_matrix(quat_of(ps.pose)), T[:3, :3], atol=1e-9)
        np.testing.assert_allclose([ps.pose.position.x, ps.pose.position.y, ps.pose.position.z], T[:3, 3])
    back = decode(encode(path), "nav_msgs/msg/Path")
    assert [p.pose.position.x for p in back.poses] == [p.pose.position.x for p in path.poses]
    empty = trajectory_path(np.zeros((0, 4, 4)), np.zeros(0, np.int64), frame_id="map")
    assert empty.poses == [] and empty.header.stamp.sec == 0
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        trajectory_path(np.zeros((3, 3, 3)), np.zeros(3, np.int64), frame_id="map")
    with pytest.raises(ValueError, match="stamps_ns"):
        trajectory_path(poses, stamps[:4], frame_id="map")
    bad = poses.copy()
    bad[2, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"poses\[2\]"):
        trajectory_path(bad, stamps, frame_id="map")


def hit(i: int, score: float, c) -> QueryHit:
    c = np.asarray(c, np.float64)
    return QueryHit(segment=i, score=score, centroid=c, bbox_min=c - 0.2, bbox_max=c + np.array([0.2, 0.2, 0.0]))


def test_hits_markers_and_poses_for_segments():
    hits = [hit(7, 0.61, [1.0, 0.5, 0.8]), hit(3, 0.42, [0.0, 0.0, 0.5]), hit(12, 0.3, [4.0, 1.0, 0.3])]
    reply = QueryReply(hits=hits, graph_seq=4)
    arr = hits_markers(reply, frame_id=FRAME, stamp_ns=STAMP)
    assert_well_formed(arr)
    ns = by_ns(arr)
    assert marker_count(arr) == {"": 1, "hits": 3, "hits/labels": 3}
    assert [ns["hits/labels"][i].text for i in range(3)] == ["#1 7 0.61", "#2 3 0.42", "#3 12 0.30"]
    best = ns["hits"][0]
    assert best.type == CUBE
    np.testing.assert_allclose([best.pose.position.x, best.pose.position.y, best.pose.position.z], [1.0, 0.5, 0.7])
    np.testing.assert_allclose([best.scale.x, best.scale.y, best.scale.z], [0.4, 0.4, 0.2])
    assert best.color.g > best.color.r and ns["hits"][2].color.r > ns["hits"][2].color.g  # green best, red last
    pa = hits_pose_array(reply, frame_id=FRAME, stamp_ns=STAMP)
    assert pa.header.frame_id == FRAME
    assert [(p.position.x, p.position.y, p.position.z) for p in pa.poses] == [(1.0, 0.5, 0.8), (0.0, 0.0, 0.5), (4.0, 1.0, 0.3)]
    assert all(quat_of(p).tolist() == [1.0, 0.0, 0.0, 0.0] for p in pa.poses)
    assert len(decode(encode(pa), "geometry_msgs/msg/PoseArray").poses) == 3
    assert len(decode(encode(arr), "visualization_msgs/msg/MarkerArray").markers) == 7


def test_hits_for_rooms_and_errors():
    reply = QueryReply(rooms=[
        RoomHit(room=2, score=0.7, margin=0.1, name="kitchen", centroid=np.array([4.0, 0.0, 1.0])),
        RoomHit(room=1, score=0.5, centroid=np.array([1.0, 0.0, 1.0]), bbox_min=np.zeros(3), bbox_max=np.full(3, 2.5)),
    ])
    arr = hits_markers(reply, frame_id=FRAME, stamp_ns=STAMP)
    assert_well_formed(arr)
    ns = by_ns(arr)
    assert marker_count(arr) == {"": 1, "hits/rooms": 2}
    assert [ns["hits/rooms"][i].text for i in range(2)] == ["#1 kitchen 0.70", "#2 room 1 0.50"]
    assert (ns["hits/rooms"][0].pose.position.x, ns["hits/rooms"][0].pose.position.y) == (4.0, 0.0)
    assert ns["hits/rooms"][1].pose.position.z > 2.5  # above the room's box
    pa = hits_pose_array(reply, frame_id=FRAME, stamp_ns=STAMP)
    assert [(p.position.x, p.position.y) for p in pa.poses] == [(4.0, 0.0), (1.0, 0.0)]
    # an error reply clears the previous hits and gives no goals
    err = QueryReply(error="deadline exceeded: 5 s")
    assert [m.action for m in hits_markers(err, frame_id=FRAME, stamp_ns=STAMP).markers] == [DELETEALL]
    assert hits_pose_array(err, frame_id=FRAME, stamp_ns=STAMP).poses == []


def big_graph(rng, n_seg=500, n_place=200, n_room=5):
    segs = []
    for i in range(n_seg):
        c = rng.uniform(0, 20, 3)
        segs.append(SegmentNode(
            id=i, centroid=c, bbox_min=c - rng.uniform(0, 0.5, 3), bbox_max=c + rng.uniform(0, 0.5, 3), tracks=[i],
            dino=np.ones(8, np.float32), gallery=np.ones((1, 8), np.float32), gallery_tracks=[i], active=bool(i % 3),
        ))
    places = [PlaceNode(id=i, position=rng.uniform(0, 20, 3), radius=0.5, room=i % n_room) for i in range(n_place)]
    rooms = [RoomNode(id=i, centroid=rng.uniform(0, 20, 3), bbox_min=np.zeros(3), bbox_max=np.full(3, 5.0))
             for i in range(n_room)]
    edges = [Edge(kind="segment_place", source=i, target=int(rng.integers(n_place))) for i in range(n_seg)]
    edges += [Edge(kind="place_place", source=i, target=(i + 1) % n_place) for i in range(n_place)]
    edges += [Edge(kind="place_place", source=i, target=(i + 7) % n_place) for i in range(n_place - 100)]
    edges += [Edge(kind="place_room", source=i, target=i % n_room) for i in range(n_place)]
    edges += [Edge(kind="room_building", source=i, target=0) for i in range(n_room)]
    return segs, places, rooms, edges


def test_large_graph_build_and_encode_time():
    """500 segments, 200 places, 5 rooms, ~1000 edges: well formed; the time is printed (run
    with -s), not asserted, as it depends on the machine."""
    segs, places, rooms, edges = big_graph(np.random.default_rng(2))
    rep = replica_of(segs, places, rooms, edges)
    assert len(rep.edges) == 1005
    t0 = time.perf_counter()
    arr = replica_markers(rep, frame_id=FRAME, stamp_ns=STAMP)
    t1 = time.perf_counter()
    payload = encode(arr)
    t2 = time.perf_counter()
    print(f"\n500-segment graph: {len(arr.markers)} markers, build {1e3 * (t1 - t0):.1f} ms, "
          f"encode {1e3 * (t2 - t1):.1f} ms, {len(payload) / 1024:.0f} KiB")
    counts = marker_count(arr)
    assert counts["segments"] == 500 and counts["ids"] == 500 and counts["rooms"] == 10
    assert len(decode(payload, "visualization_msgs/msg/MarkerArray").markers) == len(arr.markers)
