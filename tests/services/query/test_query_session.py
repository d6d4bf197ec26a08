"""The query session over the in-process bus, without Zenoh: a late join asks fusion for a
snapshot, a gap resynchronises with the deltas held meanwhile applied, queries are refused
while the replica is out of sync, the status book counts it all; the session is alive only
once its text-embedding path answered a warm-up, a request past its deadline is answered
with an error and not worked on, and text embeddings are kept in a bounded LRU."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from services.keyframe_vl.embedder import WARMUP_TEXT
from services.query.session import QuerySession
from shared.config import TrackGraphConfig
from shared.graph.scene import GraphReplica
from shared.messages.base import Envelope
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
    if env.body.text == WARMUP_TEXT:  # the service's warm-up: any embedding will do
        return EmbedReply(embedding=E[7], model="fake")
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
    assert "trackgraph/robot0/alive/query" not in bus.alive  # alive once the warm-up is answered
    fusion.add(seg(1, "chair"), publish=False)  # mapped before the query service existed
    fusion.add(seg(2, "table"), publish=False)
    reply = ask(bus, "chair")
    assert reply.error is not None and "no graph yet" in reply.error and reply.hits == []

    assert session.tick(0.0) is False  # fusion's queryable is not up: backoff
    assert "trackgraph/robot0/alive/query" in bus.alive and session.book.report().state == "running"  # vl/embed answered
    assert session.tick(0.01) is None  # not due yet
    fusion.serve()
    assert session.tick(10.0) is True and session.sync.synced and session.sync.graph_seq == 2
    assert fusion.requests == [False]  # the query service needs no mesh
    assert [h.segment for h in ask(bus, "a red chair", top_k=2).hits] == [1, 2]

    report = session.book.report()
    assert report.state == "running"
    f = report.figures
    assert (f["graph_seq"], f["synced"], f["segments"], f["snapshots"], f["queries"], f["refused"]) == (2, True, 2, 1, 2, 1)
    assert report.published == {"graph_snapshot": 2, "vl_embed": 2}  # the warm-up, then "a red chair"
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


class Clock:
    """A settable clock for the session (deadlines count in it)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def query_env(text: str, *, received: float | None, **kw) -> Envelope[QueryRequest]:
    return Envelope(body=QueryRequest(text=text, **kw), robot_id="robot0", seq=0, stamp=0.0, received=received)


def test_alive_only_once_the_embedding_path_answers_the_warm_up():
    bus = InProcessBus("robot0")
    cfg = TrackGraphConfig.model_validate({"query": {"warmup_retry_s": 2.0}})
    session = QuerySession(cfg, bus, sync_wait_s=0)
    try:
        assert session.tick(0.0) is False  # no fusion, and no vl/embed either: not ready
        assert not session.ready and bus.alive == set() and session.book.report().state == "starting"
        asked: list[str] = []

        def slow_to_load(env) -> EmbedReply:
            asked.append(env.body.text)
            return embed(env)

        bus.serve(TOPICS.vl_embed, EmbedRequest, EmbedReply, slow_to_load)
        session.tick(1.0)
        assert asked == []  # the next try is 2 s after the failed one
        session.tick(2.0)
        assert len(asked) == 1 and session.ready and "trackgraph/robot0/alive/query" in bus.alive
        report = session.book.report()
        assert report.state == "running" and report.figures["warmup_s"] is not None and session.warmup_tries == 2
        session.tick(3.0)
        assert len(asked) == 1  # once ready, no more warm-ups
    finally:
        session.close()
        bus.close()
    assert bus.alive == set()  # the token goes with the session


def test_a_local_encoder_is_loaded_by_the_warm_up():
    class Local:
        warmed = 0

        def warm_up(self) -> None:
            self.warmed += 1

        def embed(self, req: EmbedRequest) -> EmbedReply:
            return EmbedReply(embedding=E[WORDS.index(req.text)], model="local")

    bus = InProcessBus("robot0")
    local = Local()
    session = QuerySession(TrackGraphConfig(), bus, embedder=local, sync_wait_s=0)
    try:
        session.tick(0.0)
        assert local.warmed == 1 and session.ready and "trackgraph/robot0/alive/query" in bus.alive
    finally:
        session.close()
        bus.close()


def counting_embedder() -> tuple[InProcessBus, FakeFusion, list[str]]:
    """A bus with a vl/embed that records every text it embeds, and a fake fusion serving."""
    bus = InProcessBus("robot0")
    embedded: list[str] = []

    def counting(env) -> EmbedReply:
        embedded.append(env.body.text)
        return embed(env)

    bus.serve(TOPICS.vl_embed, EmbedRequest, EmbedReply, counting)
    fusion = FakeFusion(bus)
    fusion.serve()
    return bus, fusion, embedded


def test_a_request_past_its_deadline_is_answered_with_an_error_and_not_worked_on():
    bus, fusion, embedded = counting_embedder()
    clock = Clock()
    session = QuerySession(TrackGraphConfig(), bus, sync_wait_s=0, clock=clock)
    try:
        session.tick(clock.t)
        fusion.add(seg(1, "chair"))
        bus.drain()
        embedded.clear()
        # Waited 0.6 s for a worker with a 0.5 s budget: refused at once, nothing embedded.
        late = session.on_query(query_env("chair", received=clock.t - 0.6, deadline_s=0.5))
        assert late.error.startswith("deadline exceeded: waited 0.600 s") and late.hits == [] and embedded == []
        # Within its budget it is answered; the budget counts from receipt, not the sender's stamp.
        ok = session.on_query(query_env("chair", received=clock.t - 0.4, deadline_s=0.5))
        assert ok.error is None and [h.segment for h in ok.hits] == [1] and embedded == ["chair"]
        # No deadline: never expired, however long it waited.
        assert session.on_query(query_env("chair", received=clock.t - 99.0)).error is None
        f = session.book.report().figures
        assert (f["expired"], f["refused"], f["queries"]) == (1, 1, 3)
    finally:
        session.close()
        bus.close()


def test_the_embedding_round_trip_is_cut_to_the_deadline():
    bus = InProcessBus("robot0")
    timeouts: list[float] = []
    real_request = bus.request

    def request(key, body, reply_type, *, timeout):
        if key == TOPICS.vl_embed:
            timeouts.append(timeout)
        return real_request(key, body, reply_type, timeout=timeout)

    bus.request = request
    bus.serve(TOPICS.vl_embed, EmbedRequest, EmbedReply, embed)
    fusion = FakeFusion(bus)
    fusion.serve()
    clock = Clock()
    cfg = TrackGraphConfig.model_validate({"transport": {"query_timeout_s": 2.0}})
    session = QuerySession(cfg, bus, sync_wait_s=0, clock=clock)
    try:
        session.tick(clock.t)
        fusion.add(seg(1, "table"))
        bus.drain()
        timeouts.clear()
        session.on_query(query_env("a table", received=clock.t - 0.7, deadline_s=1.0))
        session.on_query(query_env("the table", received=clock.t, deadline_s=5.0))
        assert timeouts == [pytest.approx(0.3), 2.0]  # what is left of 1 s; the service's own 2 s
    finally:
        session.close()
        bus.close()


def test_text_embeddings_are_kept_in_a_bounded_lru():
    bus, fusion, embedded = counting_embedder()
    session = QuerySession(TrackGraphConfig.model_validate({"query": {"embed_cache_size": 2}}), bus, sync_wait_s=0)
    try:
        session.tick(0.0)
        fusion.add(seg(1, "chair"))
        bus.drain()
        embedded.clear()
        for text in ["chair", "table", "chair", "lamp", "chair", "table"]:
            assert ask(bus, text).error is None
        # "chair" stays (used last before "lamp" came), "table" was the least recently used.
        assert embedded == ["chair", "table", "lamp", "table"]
    finally:
        session.close()
        bus.close()


def test_an_overloaded_answer_is_counted():
    bus = InProcessBus("robot0")
    seen: dict = {}
    real_serve = bus.serve

    def serve(key, *a, **kw):
        if key == TOPICS.query:
            seen.update(capacity=kw["capacity"], workers=kw["workers"], on_drop=kw["on_drop"])
        return real_serve(key, *a, **kw)

    bus.serve = serve
    session = QuerySession(TrackGraphConfig.model_validate({"query": {"queue_size": 3, "workers": 2}}), bus, sync_wait_s=0)
    try:
        # A thread per worker and per queue place, none waiting in the queryable itself.
        assert (seen["capacity"], seen["workers"]) == (0, 5)
        seen["on_drop"]()  # what the queryable calls as it answers "overloaded"
        report = session.book.report()
        assert report.figures["overloaded"] == 1 and {i.name: i.dropped for i in report.inputs}["query"] == 1
    finally:
        session.close()
        bus.close()


def test_a_request_waiting_for_a_worker_is_answered_at_its_deadline():
    bus = InProcessBus("robot0")
    gate, working = threading.Event(), threading.Event()

    def slow(env) -> EmbedReply:
        if env.body.text == "slow chair":
            working.set()
            gate.wait(5)
        return embed(env)

    bus.serve(TOPICS.vl_embed, EmbedRequest, EmbedReply, slow)
    fusion = FakeFusion(bus)
    fusion.serve()
    session = QuerySession(TrackGraphConfig.model_validate({"query": {"workers": 1}}), bus, sync_wait_s=0)
    try:
        session.tick(0.0)
        fusion.add(seg(1, "chair"))
        bus.drain()
        with ThreadPoolExecutor(1) as pool:
            busy = pool.submit(session.on_query, query_env("slow chair", received=None))
            assert working.wait(5)  # the one worker is taken
            t0 = time.monotonic()
            late = session.on_query(query_env("chair", received=t0, deadline_s=0.3))
            took = time.monotonic() - t0
            gate.set()
            assert busy.result(5).error is None
        assert late.error.startswith("deadline exceeded: waited 0.3") and late.error.endswith("not worked on"), late.error
        assert 0.29 <= took < 1.0, took  # answered when the budget ran out, not when the worker came free
        assert session.on_query(query_env("chair", received=time.monotonic(), deadline_s=0.3)).error is None
        assert session.book.report().figures["expired"] == 1
    finally:
        gate.set()
        session.close()
        bus.close()


def test_the_local_encoder_runs_on_the_query_device(monkeypatch):
    import shared.perception.encoders as encoders

    asked = []

    class Encoder:
        name, dim = "fake", 4

        def encode_text(self, texts):
            return np.ones((len(texts), 4), np.float32) / 2

    def make(cfg, device="cpu", fp16=True, ground_truth=None):
        asked.append((device, fp16))
        return Encoder()

    monkeypatch.setattr(encoders, "make_vl_encoder", make)
    cfg = TrackGraphConfig.model_validate({"query": {"embed": "local", "device": "cpu"}, "keyframe_vl": {"fp16": False}})
    bus = InProcessBus("robot0")
    QuerySession(cfg, bus, sync_wait_s=0).close()
    assert asked == [("cpu", False)]
    torch = pytest.importorskip("torch")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="query.device 'cuda:1'"):
        QuerySession(cfg.model_copy(update={"query": cfg.query.model_copy(update={"device": "cuda:1"})}), bus, sync_wait_s=0)
    bus.close()
