"""The query session over the in-process bus, without Zenoh: a late join asks fusion for a
snapshot, a gap resynchronises with the deltas held meanwhile applied, queries are refused
while the replica is out of sync, and the status book counts it all."""

from __future__ import annotations

import numpy as np
import pytest

from services.query.session import QuerySession
from shared.config import TrackGraphConfig
from shared.graph.scene import GraphReplica
from shared.messages.graph import GraphDelta, GraphSnapshot, SegmentNode, SnapshotRequest
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryReply, QueryRequest
from shared.runtime.bus import InProcessBus
from shared.topics import Topics

WORDS = ["chair", "table", "lamp", "plant"]
E = np.eye(8, dtype=np.float32)
TOPICS = Topics("robot0")


def seg(i: int, word: str) -> SegmentNode:
    c = np.array([float(i), 0.0, 0.0])
    return SegmentNode(id=i, centroid=c, bbox_min=c - 0.2, bbox_max=c + 0.2, tracks=[i], dino=E[0],
                       gallery=E[WORDS.index(word)][None], gallery_tracks=[i], active=True)  # fmt: skip


class FakeFusion:
    """Deltas out and snapshots served on the bus, like fusion; ``present`` False makes it absent."""

    def __init__(self, bus: InProcessBus) -> None:
        self.bus = bus
        self.graph = GraphReplica()
        self.pub = bus.publisher(TOPICS.graph_delta, GraphDelta)
        self.requests: list[bool] = []
        self.q = None

    def serve(self) -> None:
        self.q = self.bus.serve(TOPICS.graph_snapshot, SnapshotRequest, GraphSnapshot, self._snap)

    def _snap(self, env) -> GraphSnapshot:
        self.requests.append(env.body.with_mesh)
        return self.graph.snapshot()

    def add(self, segment: SegmentNode, publish: bool = True) -> None:
        d = GraphDelta(graph_seq=self.graph.graph_seq + 1, frame_index=self.graph.graph_seq, segments=[segment])
        self.graph.apply_delta(d)
        if publish:
            self.pub.put(d)


def embed(env) -> EmbedReply:
    word = env.body.text.split()[-1]
    if word not in WORDS:
        return EmbedReply(model="fake", error=f"unknown word {word!r}")
    return EmbedReply(embedding=E[WORDS.index(word)], model="fake")


@pytest.fixture
def system():
    bus = InProcessBus("robot0")
    bus.serve(TOPICS.vl_embed, EmbedRequest, EmbedReply, embed)
    fusion = FakeFusion(bus)
    session = QuerySession(TrackGraphConfig(), bus, sync_wait_s=0)
    yield bus, fusion, session
    session.close()
    bus.close()


def ask(bus: InProcessBus, text: str, **kw) -> QueryReply:
    return bus.request(TOPICS.query, QueryRequest(text=text, **kw), QueryReply, timeout=1)


def inputs(session: QuerySession) -> dict:
    return {i.name: i for i in session.book.report().inputs}


def test_late_join_asks_for_a_snapshot_and_refuses_until_then(system):
    bus, fusion, session = system
    assert "trackgraph/robot0/alive/query" in bus.alive
    fusion.add(seg(1, "chair"), publish=False)  # mapped before the query service existed
    fusion.add(seg(2, "table"), publish=False)
    reply = ask(bus, "chair")
    assert reply.error is not None and "no graph yet" in reply.error and reply.hits == []

    assert session.tick(0.0) is False  # fusion's queryable is not up: backoff
    assert session.tick(0.01) is None  # not due yet
    fusion.serve()
    assert session.tick(10.0) is True and session.sync.synced and session.sync.graph_seq == 2
    assert fusion.requests == [False]  # the query service needs no mesh
    assert [h.segment for h in ask(bus, "a red chair", top_k=2).hits] == [1, 2]

    report = session.book.report()
    assert report.state == "running"
    f = report.figures
    assert (f["graph_seq"], f["synced"], f["segments"], f["snapshots"], f["queries"], f["refused"]) == (2, True, 2, 1, 2, 1)
    assert report.published == {"graph_snapshot": 2, "vl_embed": 1}
    assert inputs(session)["query"].processed == 2 and inputs(session)["graph_snapshot"].received == 1
    assert report.latency_p50_ms is not None


def test_a_gap_asks_for_a_snapshot_and_applies_the_held_deltas(system):
    bus, fusion, session = system
    fusion.serve()
    fusion.add(seg(1, "chair"))
    fusion.add(seg(2, "table"))
    bus.drain()
    assert session.sync.synced and session.sync.graph_seq == 2 and session.tick(0.0) is None  # from the start: no snapshot
    fusion.add(seg(3, "lamp"), publish=False)  # lost on the way
    fusion.add(seg(4, "plant"))
    bus.drain()
    assert not session.sync.synced and session.sync.gaps == 1
    reply = ask(bus, "chair")
    assert "resynchronising (at version 2" in reply.error
    snapshot_at = fusion.graph.graph_seq
    fusion.add(seg(5, "lamp"))  # arrives while the snapshot is on its way: held
    bus.drain()
    assert session.sync.held == 2
    fusion.graph = GraphReplica()  # the snapshot fusion answers with predates delta 5
    for i, w in enumerate(["chair", "table", "lamp", "plant"], 1):
        fusion.add(seg(i, w), publish=False)
    assert fusion.graph.graph_seq == snapshot_at
    assert session.tick(1.0) is True
    assert session.sync.graph_seq == 5 and sorted(session.sync.replica.segments) == [1, 2, 3, 4, 5]
    assert [h.segment for h in ask(bus, "lamp", top_k=2).hits] == [3, 5]
    assert [h.segment for h in ask(bus, "plant", top_k=1).hits] == [4]  # from the snapshot
    f = session.book.report().figures
    assert (f["deltas"], f["snapshots"], f["gaps"], f["stale"], f["refused"]) == (3, 1, 1, 1, 1)
    assert inputs(session)["graph_delta"].received == 4


def test_refusals_carry_the_reason_and_a_bad_delta_is_counted(system, caplog):
    bus, fusion, session = system
    fusion.serve()
    fusion.add(seg(1, "chair"))
    bus.drain()
    assert "unknown word" in ask(bus, "a sofa").error
    assert "unknown room 9" in ask(bus, "chair", room=9).error
    assert "top_k" in ask(bus, "chair", top_k=10_000).error
    assert ask(bus, "chair", top_k=1).hits[0].segment == 1
    report = session.book.report()
    assert report.figures["refused"] == 3 and report.figures["queries"] == 4 and report.errors == 0

    # A delta the replica cannot take (its handler raises) is logged and counted, not raised.
    def boom(delta):
        raise RuntimeError("broken")

    session.sync.on_delta = boom
    fusion.add(seg(2, "table"))
    bus.drain()
    assert inputs(session)["graph_delta"].rejected == 1 and session.book.report().errors == 1
