"""The ROS 2 bridge as a session: graph deltas in, MarkerArrays out at a bounded rate; the
trajectory as a Path; ROS queries (std_msgs/String JSON) answered through the query service."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.ros2.session import MARKER_ARRAY, POSE_ARRAY, STRING, Ros2BridgeSession, parse_query
from shared.config import TrackGraphConfig
from shared.geometry import Intrinsics
from shared.messages.frames import Frame, TrackedFrame
from shared.messages.graph import GraphDelta, SegmentNode
from shared.messages.rpc import QueryHit, QueryReply, QueryRequest
from shared.ros2.types import decode, encode, msg_class
from shared.ros2.wire import InProcessRosWire
from shared.runtime.bus import InProcessBus
from shared.topics import Topics


def segment(i: int) -> SegmentNode:
    lo = np.array([i, 0.0, 0.0])
    return SegmentNode(
        id=i, centroid=lo + 0.5, bbox_min=lo, bbox_max=lo + 1.0, tracks=[i], dino=np.zeros(4, np.float32),
        gallery=np.ones((1, 4), np.float32), gallery_tracks=[i], active=True,
    )  # fmt: skip


def frame(i: int) -> TrackedFrame:
    T = np.eye(4)
    T[0, 3] = 0.1 * i
    f = Frame(frame_index=i, time_s=10.0 + i / 30, rgb=np.zeros((4, 6, 3), np.uint8), depth=np.zeros((4, 6), np.uint16),
              depth_scale=1000.0, intrinsics=Intrinsics(fx=5, fy=5, cx=3, cy=2, width=6, height=4), T_world_cam=T)  # fmt: skip
    return TrackedFrame(frame=f, track_ids=np.full((4, 6), -1, np.int32), tracks=[])


@pytest.fixture
def rig(clock):
    bus = InProcessBus(clock=clock)
    wire = InProcessRosWire()
    cfg = TrackGraphConfig()
    topics = Topics(cfg.robot_id)
    asked: list[QueryRequest] = []

    def answer(env):
        asked.append(env.body)
        if env.body.text == "nothing":
            return QueryReply(error="no segments yet")
        return QueryReply(hits=[QueryHit(segment=3, score=0.8, centroid=np.array([3.5, 0.5, 0.5]), bbox_min=np.array([3.0, 0, 0]),
                                         bbox_max=np.array([4.0, 1, 1]))], graph_seq=2)  # fmt: skip

    bus.serve(topics.query, QueryRequest, QueryReply, answer)
    s = Ros2BridgeSession(bus, wire, cfg, clock=clock)
    yield s, bus, wire, clock, topics, asked
    s.close()


def markers_sent(wire: InProcessRosWire, topic: str) -> list:
    return [decode(p, MARKER_ARRAY) for _, p in wire.sent[topic]]


def test_markers_follow_deltas_at_a_bounded_rate(rig):
    s, bus, wire, clock, topics, _ = rig
    out = s.cfg.ros2.output
    pub = bus.publisher(topics.graph_delta, GraphDelta)
    pub.put(GraphDelta(graph_seq=1, frame_index=0, segments=[segment(0), segment(1)]))
    bus.drain()
    s.tick(clock())
    first = markers_sent(wire, out.markers_topic)
    assert len(first) == 1
    ns = [m.ns for m in first[0].markers]
    assert ns[0] == "" and first[0].markers[0].action == 3  # DELETEALL first
    assert ns.count("segments") == 2
    # Two more deltas within the period: nothing until it has passed, then the newest graph.
    pub.put(GraphDelta(graph_seq=2, frame_index=1, segments=[segment(2)]))
    pub.put(GraphDelta(graph_seq=3, frame_index=2, removed_segments=[0]))
    bus.drain()
    clock.t += out.markers_min_period_s / 2
    s.tick(clock())
    assert len(markers_sent(wire, out.markers_topic)) == 1
    clock.t += out.markers_min_period_s
    s.tick(clock())
    sent = markers_sent(wire, out.markers_topic)
    assert len(sent) == 2
    assert sorted(m.id for m in sent[-1].markers if m.ns == "segments") == [1, 2]
    # No change: no new array.
    clock.t += 10
    s.tick(clock())
    assert len(markers_sent(wire, out.markers_topic)) == 2
    assert s.book.report().figures["markers_sent"] == 2


def test_trajectory_path_from_tracked_frames(rig):
    s, bus, wire, clock, topics, _ = rig
    pub = bus.publisher(topics.tracks_frame, TrackedFrame)
    for i in range(3):
        pub.put(frame(i))
        bus.drain()
    pub.put(frame(1))  # a stale frame (resent) does not go back in time
    bus.drain()
    s.tick(clock())
    (ros_type, payload), = wire.sent[s.cfg.ros2.output.path_topic]
    path = decode(payload, ros_type)
    assert [round(p.pose.position.x, 6) for p in path.poses] == [0.0, 0.1, 0.2]
    assert path.header.frame_id == "map"
    assert path.poses[2].header.stamp.sec == 10


def _ask(wire: InProcessRosWire, s: Ros2BridgeSession, text: str) -> dict:
    s.answer(encode(msg_class(STRING)(data=text)))
    return json.loads(decode(wire.sent[s.cfg.ros2.output.reply_topic][-1][1], STRING).data)


def test_ros_query_answered_with_hits_markers_and_poses(rig):
    s, bus, wire, clock, topics, asked = rig
    out = s.cfg.ros2.output
    reply = _ask(wire, s, json.dumps({"id": "q1", "text": "red armchair", "top_k": 2}))
    assert reply["id"] == "q1" and reply["error"] is None
    assert reply["hits"][0]["segment"] == 3
    assert asked[-1].text == "red armchair" and asked[-1].top_k == 2
    poses = decode(wire.sent[out.hits_poses_topic][-1][1], POSE_ARRAY)
    assert [round(p.position.x, 6) for p in poses.poses] == [3.5]
    hits = markers_sent(wire, out.hits_markers_topic)[-1]
    assert hits.markers[0].action == 3 and len(hits.markers) > 1
    # Plain text is a text query too (ros2 topic pub ... "data: chair").
    assert _ask(wire, s, "chair")["hits"][0]["segment"] == 3 and asked[-1].text == "chair"


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ('{"text": ', "not JSON"),
        ("[1, 2]", "JSON object"),
        ('{"text": "a", "top_k": 0}', "top_k"),
        ('{"image": [[1]]}', "image queries"),
        ('{"text": "a", "room": 1, "room_text": "kitchen"}', "at most one"),
    ],
)
def test_bad_ros_queries_get_an_error_reply_and_are_counted(rig, text, why):
    s, bus, wire, clock, topics, asked = rig
    reply = _ask(wire, s, text)
    assert why in reply["error"]
    assert not asked
    assert s.queries_refused == 1


def test_undecodable_query_and_service_errors(rig):
    s, bus, wire, clock, topics, asked = rig
    s.answer(b"\x00\x01\x00\x00\xff\xff\xff\x7f")
    reply = json.loads(decode(wire.sent[s.cfg.ros2.output.reply_topic][-1][1], STRING).data)
    assert "invalid CDR" in reply["error"]
    assert "no segments yet" in _ask(wire, s, json.dumps({"id": 5, "text": "nothing"}))["error"]
    assert s.queries_refused == 2 and s.queries_answered == 0
    assert not wire.sent.get(s.cfg.ros2.output.hits_poses_topic)


def test_parse_query_keeps_the_id_and_defaults():
    req, qid = parse_query('{"id": 9, "text": "sofa", "room_text": "living room"}')
    assert qid == 9 and req.text == "sofa" and req.room_text == "living room"
    req, qid = parse_query('"lamp"')
    assert qid is None and req.text == "lamp"
