"""Rooms asked for by name: ``target: rooms`` ranks the rooms by their open-vocabulary
feature, ``room_text`` filters the segments to the best-matching room; the index holds the
rooms that have a feature, the session embeds a room_text through its deadline-aware, cached
path, and the client's ``rooms``/``room_text`` build the right requests."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from services.keyframe_vl.embedder import WARMUP_TEXT
from services.query.client import QueryClient, QueryRefused
from services.query.core import QueryEngine, QueryError, QueryIndex, hit_rows, room_rows
from services.query.session import QuerySession
from shared.config import TrackGraphConfig
from shared.config.query import QueryConfig
from shared.messages.base import Envelope
from shared.messages.graph import GraphDelta, GraphSnapshot, RoomNode, SegmentNode, SnapshotRequest
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryReply, QueryRequest
from shared.runtime.bus import InProcessBus
from shared.topics import Topics

E = np.eye(4, dtype=np.float32)
TOPICS = Topics("robot0")


def unit(v) -> np.ndarray:
    v = np.asarray(v, np.float32)
    return v / np.linalg.norm(v)


def seg(i: int, row: np.ndarray, room: int | None) -> SegmentNode:
    c = np.array([float(i), 0.0, 0.0])
    return SegmentNode(id=i, centroid=c, bbox_min=c - 0.1, bbox_max=c + 0.1, tracks=[i], dino=E[0],
                       gallery=np.asarray(row, np.float32)[None], gallery_tracks=[i], active=True, room=room)  # fmt: skip


def room(i: int, feature, name: str = "", box: bool = True) -> RoomNode:
    c = np.array([float(i), 1.0, 1.2])
    return RoomNode(
        id=i, centroid=c, name=name, feature=None if feature is None else np.asarray(feature, np.float32),
        bbox_min=c - [2.0, 1.5, 1.2] if box else None, bbox_max=c + [2.0, 1.5, 1.3] if box else None,
    )  # fmt: skip


# Room 1 is the kitchen, room 2 mostly "sleep", room 3 all "sleep", room 4 has no feature yet.
ROOMS = [room(3, E[1], "hall"), room(1, E[0], "kitchen"), room(2, unit([0.6, 0.8, 0, 0]), "bedroom"), room(4, None)]
SEGMENTS = [seg(10, E[2], 1), seg(11, unit([0, 0, 1, 1]), 2), seg(12, E[2], 3), seg(13, E[3], 1), seg(14, E[2], None)]
TEXTS = {"kitchen": E[0], "sleep": E[1], "sink": E[2], "mix": unit([1, 1, 0, 0]), "short": np.ones(3, np.float32)}


def engine(calls: list | None = None, **cfg) -> QueryEngine:
    def embed(req: EmbedRequest) -> np.ndarray:
        if calls is not None:
            calls.append(req.text)
        return E[0] if req.text is None else TEXTS[req.text]  # any image looks like a kitchen

    return QueryEngine(QueryConfig(**cfg), embed)


def expected_order(index: QueryIndex, q: np.ndarray) -> tuple[list[int], dict[int, float]]:
    """Rooms with a feature by cosine with ``q``, best first, ties by id: computed here."""
    scores = {r.id: float(unit(r.feature) @ unit(q)) for r in ROOMS if r.feature is not None}
    return sorted(scores, key=lambda i: (-round(scores[i], 6), i)), scores


def test_the_index_holds_the_rooms_with_a_feature_from_room_nodes():
    index = QueryIndex.build(5, SEGMENTS, ROOMS)
    assert index.room_ids == {1, 2, 3, 4}  # every room, with or without a feature
    assert [r.id for r in index.room_nodes] == [1, 2, 3] and index.room_feature_ids.tolist() == [1, 2, 3]
    assert index.room_dim == 4 and index.room_features_count == 3
    assert [r.name for r in index.room_nodes] == ["kitchen", "bedroom", "hall"]
    np.testing.assert_allclose(np.linalg.norm(index.room_features, axis=1), 1.0, atol=1e-6)
    # Plain ids still work (rooms known, none rankable), and mix with nodes.
    ids_only = QueryIndex.build(5, SEGMENTS, [1, 2, 3, 4])
    assert ids_only.room_ids == index.room_ids and ids_only.room_nodes == () and ids_only.room_dim == 0
    assert ids_only.room_features_count == 0
    mixed = QueryIndex.build(5, SEGMENTS, [7, ROOMS[1]])
    assert mixed.room_ids == {1, 2, 3, 7} and [r.id for r in mixed.room_nodes] == [1]  # 2, 3 from segments
    # A room feature that is not unit length is normalised like gallery rows.
    scaled = QueryIndex.build(5, [], [room(1, 3 * E[0])])
    np.testing.assert_allclose(scaled.room_features, E[:1], atol=1e-6)
    with pytest.raises(TypeError, match="RoomNode objects or room ids"):
        QueryIndex.build(5, [], ["kitchen"])


def test_rooms_are_ranked_by_cosine_best_first_with_ties_by_id():
    index = QueryIndex.build(5, SEGMENTS, ROOMS)
    for text in ("mix", "kitchen", "sleep"):
        reply = engine().answer(index, QueryRequest(text=text, target="rooms"))
        order, scores = expected_order(index, TEXTS[text])
        assert reply.error is None and reply.hits == [] and reply.graph_seq == 5
        assert [r.room for r in reply.rooms] == order, text
        assert [r.score for r in reply.rooms] == pytest.approx([scores[i] for i in order], abs=1e-6)
    # "mix" is 45 degrees from both the kitchen (1) and the hall (3): equal scores, by id.
    mix = engine().answer(index, QueryRequest(text="mix", target="rooms")).rooms
    assert [r.room for r in mix] == [2, 1, 3] and mix[1].score == pytest.approx(mix[2].score)
    best = mix[0]
    assert best.name == "bedroom" and np.array_equal(best.centroid, ROOMS[2].centroid)
    assert np.array_equal(best.bbox_min, ROOMS[2].bbox_min) and np.array_equal(best.bbox_max, ROOMS[2].bbox_max)
    # top_k as for segments: the request's, else the default, capped by the maximum.
    assert len(engine().answer(index, QueryRequest(text="mix", target="rooms", top_k=2)).rooms) == 2
    assert len(engine(default_top_k=1).answer(index, QueryRequest(text="mix", target="rooms")).rooms) == 1
    assert "top_k 1000" in engine().answer(index, QueryRequest(text="mix", target="rooms", top_k=1000)).error
    # An image query ranks rooms too.
    picture = engine().answer(index, QueryRequest(image=np.zeros((4, 4, 3), np.uint8), target="rooms"))
    assert [r.room for r in picture.rooms] == expected_order(index, E[0])[0]


def test_a_graph_without_room_features_ranks_no_rooms():
    reply = engine().answer(QueryIndex.build(5, SEGMENTS, [1, 2, 3]), QueryRequest(text="kitchen", target="rooms"))
    assert reply.error is None and reply.rooms == [] and reply.hits == []
    assert engine().answer(QueryIndex.empty(), QueryRequest(text="kitchen", target="rooms")).rooms == []


def test_room_text_picks_the_best_room_and_filters_its_segments():
    index = QueryIndex.build(5, SEGMENTS, ROOMS)
    calls: list = []
    reply = engine(calls).answer(index, QueryRequest(text="sink", room_text="kitchen"))
    assert reply.error is None and calls == ["sink", "kitchen"]  # both through the engine's embed
    order, _ = expected_order(index, TEXTS["kitchen"])
    assert [r.room for r in reply.rooms] == order and reply.rooms[0].room == 1
    # Exactly what asking for room 1 by id gives.
    by_id = engine().answer(index, QueryRequest(text="sink", room=1))
    assert [h.segment for h in reply.hits] == [h.segment for h in by_id.hits] == [10, 13]
    assert hit_rows(reply.hits) == hit_rows(by_id.hits) and by_id.rooms == []
    # The other room: "sleep" is the hall (3), whose only segment is 12.
    sleep = engine().answer(index, QueryRequest(text="sink", room_text="sleep", top_k=1))
    assert [r.room for r in sleep.rooms] == [3] and [h.segment for h in sleep.hits] == [12]
    # A request's own embed (the service's, cut to its deadline) embeds the room_text too.
    own: list = []
    engine().answer(index, QueryRequest(text="sink", room_text="kitchen"), embed=lambda r: own.append(r.text) or TEXTS[r.text])
    assert own == ["sink", "kitchen"]


def test_room_text_is_refused_while_no_room_has_a_feature():
    calls: list = []
    reply = engine(calls).answer(QueryIndex.build(5, SEGMENTS, [1, 2, 3]), QueryRequest(text="sink", room_text="kitchen"))
    assert reply.hits == [] and reply.error.startswith("no room has a feature yet: ") and "'kitchen'" in reply.error
    assert calls == []  # refused before anything was embedded


@pytest.mark.parametrize(
    "req, words",
    [
        (QueryRequest(text="mix", target="rooms", room_text="kitchen"), "room_text (a filter of segments) does not apply"),
        (QueryRequest(text="mix", target="rooms", room=1), "room (a filter of segments) does not apply"),
        (QueryRequest(text="mix", target="rooms", center=np.zeros(3), radius=1.0), "center"),
        (QueryRequest(text="short", target="rooms"), "the query embedding is 3-d but the map's room features are 4-d"),
        (QueryRequest(text="sink", room_text="short"), "the room_text embedding is 3-d but the map's room features are 4-d"),
        (QueryRequest(text="sink", room_text="x" * 600), "room_text has 600 characters; at most 512"),
    ],
)
def test_bad_room_queries_are_refused_with_the_reason(req, words):
    reply = engine(max_text_chars=512).answer(QueryIndex.build(5, SEGMENTS, ROOMS), req)
    assert reply.hits == [] and reply.rooms == [] and words in reply.error


def test_room_and_room_text_together_fail_validation():
    with pytest.raises(ValueError, match="at most one of room and room_text"):
        QueryRequest(text="sink", room=1, room_text="kitchen")
    with pytest.raises(ValueError, match="room_text is empty"):
        QueryRequest(text="sink", room_text="  ")


def test_room_features_of_another_dimension_are_refused_when_indexed():
    with pytest.raises(QueryError, match="room features are 3-d but the segments' gallery rows are 4-d"):
        QueryIndex.build(5, SEGMENTS, [room(1, np.ones(3))])
    with pytest.raises(QueryError, match="room 2 has a 3-d feature, other rooms 4-d"):
        QueryIndex.build(5, [], [room(1, E[0]), room(2, np.ones(3))])
    # Without segments, any one dimension is fine; without room features, any galleries.
    assert QueryIndex.build(5, [], [room(1, np.ones(3))]).room_dim == 3
    assert QueryIndex.build(5, SEGMENTS, [room(1, None)]).room_dim == 0


def test_room_rows_have_the_contract_keys():
    index = QueryIndex.build(5, SEGMENTS, ROOMS + [room(6, unit([1, 0, 0, 1e-7]), "attic", box=False)])
    rooms = engine().answer(index, QueryRequest(text="kitchen", target="rooms")).rooms
    rows = room_rows(rooms)
    assert all(set(r) == {"room", "score", "margin", "name", "centroid", "bbox"} for r in rows)
    assert [r["room"] for r in rows] == [1, 6, 2, 3]
    kitchen, attic = rows[0], rows[1]
    assert kitchen["name"] == "kitchen" and kitchen["score"] == round(rooms[0].score, 6)
    assert kitchen["centroid"] == [1.0, 1.0, 1.2] and kitchen["bbox"] == [[-1.0, -0.5, 0.0], [3.0, 2.5, 2.5]]
    assert attic["bbox"] is None and attic["name"] == "attic"


# ---------------------------------------------------------------- the session


def session_embed(env) -> EmbedReply:
    """vl/embed: the TEXTS above, any embedding for the warm-up."""
    text = env.body.text
    return EmbedReply(embedding=E[3] if text == WARMUP_TEXT else TEXTS[text], model="fake")


def test_the_session_embeds_room_text_through_its_deadline_and_cache(clock):
    bus = InProcessBus("robot0")
    embedded: list[str] = []
    timeouts: list[float] = []
    real_request = bus.request

    def request(key, body, reply_type, *, timeout):
        if key == TOPICS.vl_embed:
            embedded.append(body.text)
            timeouts.append(timeout)
        return real_request(key, body, reply_type, timeout=timeout)

    bus.request = request
    bus.serve(TOPICS.vl_embed, EmbedRequest, EmbedReply, session_embed)
    graph = GraphSnapshot(graph_seq=1, frame_index=0, segments=SEGMENTS, rooms=ROOMS)
    bus.serve(TOPICS.graph_snapshot, SnapshotRequest, GraphSnapshot, lambda env: graph)
    # No room labels: this pins the deadline and the cache (the margin has its own test).
    cfg = TrackGraphConfig.model_validate({"transport": {"query_timeout_s": 2.0}, "fusion": {"graph": {"room_labels": []}}})
    session = QuerySession(cfg, bus, sync_wait_s=0, clock=clock)
    try:
        session.tick(clock.t)
        session.tick(clock.t + 10)
        assert session.sync.synced and [r.id for r in session.index.room_nodes] == [1, 2, 3]
        embedded.clear()
        timeouts.clear()

        def env(**kw) -> Envelope[QueryRequest]:
            return Envelope(body=QueryRequest(text="sink", room_text="kitchen", **kw), robot_id="robot0", seq=0, stamp=0.0, received=clock.t - 0.7)

        reply = session.on_query(env(deadline_s=1.0))
        assert reply.error is None and reply.rooms[0].room == 1 and [h.segment for h in reply.hits] == [10, 13]
        # Both texts went over vl/embed with what was left of the 1 s budget.
        assert embedded == ["sink", "kitchen"] and timeouts == [pytest.approx(0.3), pytest.approx(0.3)]
        # Asked again, both come from the cache; rooms ranked the same way.
        again = session.on_query(env())
        assert embedded == ["sink", "kitchen"] and again.hits == reply.hits and again.rooms == reply.rooms
        # A later delta that changes a room's feature is in the next answer.
        moved = ROOMS[0].model_copy(update={"feature": E[0]})  # the hall now looks like a kitchen
        bus.publisher(TOPICS.graph_delta, GraphDelta).put(GraphDelta(graph_seq=2, frame_index=1, rooms=[moved]))
        bus.drain()
        ranked = session.on_query(Envelope(body=QueryRequest(text="kitchen", target="rooms"), robot_id="robot0", seq=0, stamp=0.0))
        assert [r.room for r in ranked.rooms][:2] == [1, 3] and ranked.rooms[1].score == pytest.approx(1.0)
    finally:
        session.close()
        bus.close()


# ---------------------------------------------------------------- the client


def test_the_client_asks_for_rooms_and_for_room_text(monkeypatch):
    graph = {"index": QueryIndex.build(5, SEGMENTS, ROOMS)}
    sent: list[QueryRequest] = []

    def fake_request(session, key, req, reply_type, **kw):
        """The query service's answer, without Zenoh."""
        sent.append(req)
        assert key == TOPICS.query and reply_type is QueryReply
        return SimpleNamespace(body=engine().answer(graph["index"], req))

    monkeypatch.setattr("services.query.client.request", fake_request)
    client = QueryClient(session=object(), timeout_s=2.0)
    rooms = client.rooms("mix", top_k=2)
    assert [r.room for r in rooms] == [2, 1] and sent[-1].target == "rooms" and sent[-1].top_k == 2
    assert client.rooms(image=np.zeros((4, 4, 3), np.uint8))[0].room == 1 and sent[-1].image is not None
    hits = client.query("sink", room_text="kitchen")
    assert [h.segment for h in hits] == [10, 13] and sent[-1].room_text == "kitchen" and sent[-1].target == "segments"
    with pytest.raises(QueryRefused, match="room features are 4-d"):
        client.rooms("short")
    graph["index"] = QueryIndex.build(5, SEGMENTS, [1, 2])
    with pytest.raises(QueryRefused, match="no room has a feature yet"):
        client.query("sink", room_text="kitchen")
    assert client.rooms("kitchen") == []  # no features: an empty answer, not a refusal


def test_a_text_ranks_rooms_by_its_margin_over_the_other_labels():
    """Room 1 is described well (cos 0.8 with "dining room", 0.5 with "hall"); room 2, a
    glimpsed hall, poorly (0.45 with "hall", 0.3 with "dining room"). By cosine "hall" picks
    room 1 (0.5 > 0.45); by margin over the other label room 2 (0.45 - 0.3 = 0.15 against
    0.5 - 0.8 = -0.3). An image query ranks by cosine; so does an engine without labels."""
    d, h = np.array([1.0, 0, 0, 0]), np.array([0, 1.0, 0, 0])
    # Room features with the stated cosines against the label axes (the rest on axis 2).
    f1 = unit([0.8, 0.5, np.sqrt(1 - 0.64 - 0.25), 0])
    f2 = unit([0.3, 0.45, np.sqrt(1 - 0.09 - 0.2025), 0])
    texts = {"dining room": d, "hall": h}
    rooms = [room(1, f1, "dining room"), room(2, f2, "hall")]
    index = QueryIndex.build(3, SEGMENTS, rooms)

    def embed(req):
        return (texts[req.text] if req.text is not None else f1).astype(np.float32)

    labelled = QueryEngine(QueryConfig(), embed, ["dining room", "Hall "])
    got = labelled.answer(index, QueryRequest(text="hall", target="rooms")).rooms
    assert [r.room for r in got] == [2, 1]
    assert got[0].margin == pytest.approx(0.15, abs=1e-6) and got[1].margin == pytest.approx(-0.3, abs=1e-6)
    assert got[0].score == pytest.approx(0.45, abs=1e-6)
    assert [r.room for r in QueryEngine(QueryConfig(), embed).answer(index, QueryRequest(text="hall", target="rooms")).rooms] == [1, 2]
    # room_text chooses by the margin too.
    assert labelled.answer(index, QueryRequest(text="dining room", room_text="hall")).rooms[0].room == 2
    image = np.zeros((4, 4, 3), np.uint8)
    by_image = labelled.answer(index, QueryRequest(image=image, target="rooms")).rooms
    assert [r.room for r in by_image] == [1, 2] and by_image[0].margin is None
