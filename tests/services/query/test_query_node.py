"""The query service over loopback Zenoh: late join and gaps resynchronise from
``graph/snapshot``, queries are embedded through ``vl/embed``, many clients at once, and a
client that vanishes mid-query harms nobody; rooms are asked for by name from the client and
``trackgraph query --live``. Fusion and keyframe_vl are stand-ins that speak
the real messages."""

from __future__ import annotations

import json
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from services.cli import main
from services.keyframe_vl.embedder import WARMUP_TEXT
from services.query.client import QueryClient, QueryRefused, deadline_for
from services.query.node import QueryNode
from services.router import run_router
from shared.codec import encode
from shared.config import TrackGraphConfig
from shared.graph.scene import GraphReplica
from shared.messages.graph import GraphDelta, GraphSnapshot, RoomNode, SegmentNode, SnapshotRequest
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryRequest
from shared.topics import Topics
from shared.transport import (
    LivelinessWatcher,
    TransportError,
    TypedPublisher,
    TypedQueryable,
    open_session,
)

pytestmark = pytest.mark.zenoh

WORDS = ["chair", "table", "lamp", "plant"]
E = np.eye(8, dtype=np.float32)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def seg(i: int, word: str) -> SegmentNode:
    c = np.array([float(i), 0.0, 0.0])
    return SegmentNode(id=i, centroid=c, bbox_min=c - 0.2, bbox_max=c + 0.2, tracks=[i], dino=E[0],
                       gallery=E[WORDS.index(word)][None], gallery_tracks=[i], active=True)  # fmt: skip


class FakeFusion:
    """Publishes deltas and serves snapshots of the graph it holds, like the fusion node."""

    def __init__(self, session, topics: Topics, robot: str) -> None:
        self.graph = GraphReplica()
        self.pub = TypedPublisher(session, topics.graph_delta, GraphDelta, robot_id=robot)
        self.snapshots = 0
        self.requests: list[SnapshotRequest] = []
        self.refuse: str | None = None
        self.q = TypedQueryable(session, topics.graph_snapshot, SnapshotRequest, GraphSnapshot, self._snap, robot_id=robot)

    def _snap(self, env) -> GraphSnapshot:
        self.snapshots += 1
        self.requests.append(env.body)
        snap = self.graph.snapshot()
        return snap if self.refuse is None else snap.model_copy(update={"error": self.refuse})

    def add(self, segment: SegmentNode, publish: bool = True) -> None:
        d = GraphDelta(graph_seq=self.graph.graph_seq + 1, frame_index=self.graph.graph_seq, segments=[segment])
        self.graph.apply_delta(d)
        if publish:
            self.pub.put(d)

    def close(self) -> None:
        self.q.close()
        self.pub.close()


@pytest.fixture
def system():
    """A router, a fake fusion and a fake keyframe_vl (vl/embed); yields (cfg, fusion). Texts
starting "slow" wait for ``fusion.embed_gate``; ``fusion.vl`` is the vl/embed queryable."""
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    cfg = TrackGraphConfig.model_validate({
        "transport": {"mode": "client", "connect": [endpoint], "shared_memory": False, "query_timeout_s": 2.0},
        "query": {"sync_wait_s": 0.5, "workers": 4},
    })  # fmt: skip
    stop = threading.Event()
    router = threading.Thread(target=run_router, args=(cfg.transport.model_copy(update={"mode": "router", "connect": [], "listen": [endpoint]}), stop), daemon=True)
    router.start()
    time.sleep(0.3)
    session = open_session(cfg.transport)
    topics = Topics(cfg.robot_id)
    gate = threading.Event()
    gate.set()

    def embed(env) -> EmbedReply:
        req: EmbedRequest = env.body
        if req.text.startswith("slow"):
            gate.wait(10)  # a test holds the embedding back with fusion.embed_gate
        if req.text == WARMUP_TEXT:  # the service's warm-up: any embedding will do
            return EmbedReply(embedding=E[7], model="fake")
        word = req.text.split()[-1] if req.text else "plant"
        if word not in WORDS:
            return EmbedReply(model="fake", error=f"unknown word {word!r}")
        return EmbedReply(embedding=E[WORDS.index(word)], model="fake")

    vl = TypedQueryable(session, topics.vl_embed, EmbedRequest, EmbedReply, embed, robot_id=cfg.robot_id, workers=2)
    fusion = FakeFusion(session, topics, cfg.robot_id)
    fusion.embed_gate, fusion.vl, fusion.embed, fusion.session = gate, vl, embed, session
    try:
        yield cfg, fusion
    finally:
        gate.set()
        fusion.close()
        fusion.vl.close()
        session.close()
        stop.set()
        router.join(timeout=10)


def wait(cond, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_late_join_gap_and_answers(system):
    cfg, fusion = system
    fusion.add(seg(1, "chair"), publish=False)  # mapped before the query service existed
    fusion.add(seg(2, "table"), publish=False)
    node = QueryNode(cfg)
    try:
        with QueryClient(cfg.transport, robot_id=cfg.robot_id) as client:
            assert wait(lambda: node.sync.synced and node.sync.graph_seq == 2), node.stats()
            hits = client.query("a red chair", top_k=2)
            assert [h.segment for h in hits] == [1, 2] and hits[0].score == pytest.approx(1.0)
            assert client.last_graph_seq == 2
            # Live deltas, then one lost on the way: the node resynchronises from a snapshot.
            fusion.add(seg(3, "lamp"))
            assert wait(lambda: node.sync.graph_seq == 3)
            fusion.add(seg(4, "plant"), publish=False)
            fusion.add(seg(5, "lamp"))
            assert wait(lambda: node.sync.synced and node.sync.graph_seq == 5), node.stats()
            assert node.sync.gaps == 1 and fusion.snapshots >= 2
            assert [h.segment for h in client.query("lamp", top_k=2)] == [3, 5]
            assert [h.segment for h in client.query("plant", top_k=1)] == [4]  # from the snapshot
            # Refusals carry the reason and leave the service up.
            with pytest.raises(QueryRefused, match="unknown word"):
                client.query("a sofa")
            with pytest.raises(QueryRefused, match="unknown room 9"):
                client.query("chair", room=9)
            with pytest.raises(QueryRefused, match="top_k"):
                client.query("chair", top_k=10_000)
            assert client.query("chair", top_k=1)[0].segment == 1
        report = node.book.report()
        assert report.state == "running" and report.figures["gaps"] == 1 and report.figures["segments"] == 5
        assert {i.name: i.received for i in report.inputs}["graph_delta"] == 2  # 3 and 5; 4 was lost
    finally:
        node.close()
    assert node.stats()["refused"] == 3


def test_no_graph_yet_is_an_error_not_an_empty_answer(system):
    cfg, fusion = system
    fusion.q.close()  # fusion is not there at all
    node = QueryNode(cfg)
    try:
        with QueryClient(cfg.transport, robot_id=cfg.robot_id) as client:
            with pytest.raises(QueryRefused, match="no graph yet"):
                client.query("chair")
    finally:
        node.close()


def test_many_clients_at_once_and_a_client_vanishing_mid_query(system):
    cfg, fusion = system
    for i, w in enumerate(WORDS * 5):
        fusion.add(seg(i + 1, w))
    node = QueryNode(cfg)
    try:
        assert wait(lambda: node.sync.synced and node.sync.graph_seq == 20), node.stats()
        # A client that sends a query and closes its session before the answer.
        rude = open_session(cfg.transport)
        rude.get(Topics(cfg.robot_id).query, payload=encode(QueryRequest(text="chair"), robot_id="rude", seq=0, stamp=0.0))
        rude.close()

        def one_client(k: int) -> list[int]:
            with QueryClient(cfg.transport, robot_id=cfg.robot_id) as client:
                return [client.query(WORDS[(k + j) % 4], top_k=5)[0].segment for j in range(20)]

        with ThreadPoolExecutor(8) as pool:
            results = list(pool.map(one_client, range(8)))
        for k, tops in enumerate(results):
            # The best segment of each word is its first one (ties rank by id).
            assert tops == [WORDS.index(WORDS[(k + j) % 4]) + 1 for j in range(20)]
        stats = node.stats()
        assert stats["query_link"]["handler_errors"] == 0 and stats["errors"] == 0
    finally:
        node.close()


def test_client_asks_fusion_for_the_whole_map_and_hears_why_not(system):
    cfg, fusion = system
    fusion.add(seg(1, "chair"), publish=False)
    with QueryClient(cfg.transport, robot_id=cfg.robot_id) as client:
        snap = client.snapshot(whole_map=True)
        assert [s.id for s in snap.segments] == [1] and snap.error is None
        assert fusion.requests[-1].whole_map and not fusion.requests[-1].with_mesh
        fusion.refuse = "SnapshotRequest.whole_map: the whole map's mesh is 9 bytes, over the codec's limit"
        with pytest.raises(QueryRefused, match="whole_map: the whole map's mesh is 9 bytes"):
            client.snapshot(whole_map=True)


def test_alive_only_once_vl_embed_answers_the_warm_up(system):
    cfg, fusion = system
    fusion.vl.close()  # keyframe_vl still loading its models
    watcher = LivelinessWatcher(fusion.session, "trackgraph/robot0/alive/**")
    node = QueryNode(cfg)
    try:
        time.sleep(1.5)  # three warm-up tries
        assert "trackgraph/robot0/alive/query" not in watcher.alive() and node.book.report().state == "starting"
        fusion.vl = TypedQueryable(fusion.session, Topics(cfg.robot_id).vl_embed, EmbedRequest, EmbedReply, fusion.embed, robot_id=cfg.robot_id)
        assert watcher.wait_for("trackgraph/robot0/alive/query", timeout=5), node.stats()
        report = node.book.report()
        assert report.state == "running" and report.figures["warmup_s"] >= 1.5 and node.session.warmup_tries >= 3
    finally:
        node.close()
        watcher.close()


def test_overloaded_at_once_and_a_waiting_request_answered_at_its_deadline(system):
    cfg, fusion = system
    cfg = cfg.model_copy(update={"query": cfg.query.model_copy(update={"workers": 1, "queue_size": 1})})
    fusion.add(seg(1, "chair"))
    fusion.add(seg(2, "table"))
    node = QueryNode(cfg)
    clients = [QueryClient(cfg.transport, robot_id=cfg.robot_id, timeout_s=5.0) for _ in range(3)]
    try:
        assert wait(lambda: node.session.ready and node.sync.synced and node.sync.graph_seq == 2), node.stats()
        fusion.embed_gate.clear()
        with ThreadPoolExecutor(2) as pool:
            busy = pool.submit(clients[0].query, "slow chair")  # takes the one worker
            assert wait(lambda: node.session._slots._value == 0)
            t0 = time.monotonic()
            waiting = pool.submit(clients[1].ask, QueryRequest(text="table", deadline_s=0.5))  # the one queue place
            assert wait(lambda: node.session._waiting == 1)
            with pytest.raises(TransportError, match="overloaded: "):
                clients[2].query("chair")
            overloaded_after = time.monotonic() - t0
            late = waiting.result(5)
            late_after = time.monotonic() - t0
            fusion.embed_gate.set()
            assert [h.segment for h in busy.result(5)][:1] == [1]
        assert overloaded_after < 0.5  # at once, while the queued one still waits
        assert late.error.startswith("deadline exceeded: ") and 0.45 <= late_after < 1.5, (late.error, late_after)
        assert [h.segment for h in clients[2].query("table", top_k=1)] == [2]  # free again
        report = node.book.report()
        assert (report.figures["overloaded"], report.figures["expired"]) == (1, 1)
        assert {i.name: i.dropped for i in report.inputs}["query"] == 1
    finally:
        fusion.embed_gate.set()
        for c in clients:
            c.close()
        node.close()


def test_the_client_sends_a_deadline_from_its_timeout(system):
    cfg, fusion = system
    fusion.add(seg(1, "chair"))
    node = QueryNode(cfg)
    seen: list[float | None] = []
    real = node.session.on_query

    def spy(env):
        seen.append(env.body.deadline_s)
        assert env.received is not None and env.received <= time.monotonic()
        return real(env)

    node.queryable.handler = spy  # what the queryable hands each decoded request
    try:
        assert wait(lambda: node.session.ready and node.sync.synced), node.stats()
        with QueryClient(cfg.transport, robot_id=cfg.robot_id, timeout_s=3.0) as client:
            client.query("chair")
            client.ask(QueryRequest(text="chair", deadline_s=1.25))
        assert seen == [pytest.approx(deadline_for(3.0)), 1.25] and deadline_for(3.0) == pytest.approx(2.8)
    finally:
        node.close()


def test_rooms_by_name_over_zenoh_from_the_client_and_the_command_line(system, capsys):
    cfg, fusion = system

    def room(i: int, word: str, name: str) -> RoomNode:
        return RoomNode(id=i, centroid=np.array([4.0 * i, 0.0, 1.2]), name=name, feature=E[WORDS.index(word)])

    # Room 0 "looks like" a table, room 1 a lamp; a lamp stands in each.
    segs = [seg(1, "lamp").model_copy(update={"room": 0}), seg(2, "lamp").model_copy(update={"room": 1})]
    d = GraphDelta(graph_seq=1, frame_index=0, segments=segs, rooms=[room(0, "table", "dining room"), room(1, "lamp", "study")])
    fusion.graph.apply_delta(d)
    node = QueryNode(cfg)
    try:
        assert wait(lambda: node.session.ready and node.sync.synced and node.sync.graph_seq == 1), node.stats()
        with QueryClient(cfg.transport, robot_id=cfg.robot_id) as client:
            rooms = client.rooms("a table")
            assert [r.room for r in rooms] == [0, 1] and rooms[0].name == "dining room" and rooms[0].score == pytest.approx(1.0)
            assert [h.segment for h in client.query("lamp", room_text="a table")] == [1]
            assert client.ask(QueryRequest(text="lamp", room_text="a lamp")).rooms[0].room == 1
        capsys.readouterr()
        endpoint = cfg.transport.connect[0]
        assert main(["query", "--live", "a lamp", "--rooms", "--json", "--connect", endpoint]) == 0
        rows = json.loads(capsys.readouterr().out)
        assert [r["room"] for r in rows] == [1, 0] and rows[0]["name"] == "study" and rows[0]["bbox"] is None
        assert main(["query", "--live", "lamp", "--in-room", "a table", "--json", "--connect", endpoint]) == 0
        assert [r["segment"] for r in json.loads(capsys.readouterr().out)] == [1]
    finally:
        node.close()
