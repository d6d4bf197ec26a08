"""The one error rule of docs/wire.md, checked on a live queryable over loopback Zenoh:
failures to take a request in (or to handle it) are Zenoh error replies with a documented
UTF-8 prefix; a request understood but declined is a normal reply with ``error`` set."""

from __future__ import annotations

import socket
import threading
import time

import msgpack
import numpy as np
import pytest

from services.keyframe_vl.embedder import Embedder
from services.query.core import QueryEngine, QueryIndex
from shared.codec import decode, encode
from shared.config import QueryConfig, TransportConfig
from shared.messages import EmbedReply, EmbedRequest, QueryReply, QueryRequest
from shared.messages.wiredoc.markdown import ERROR_PREFIXES
from shared.topics import Topics
from shared.transport import TypedQueryable, open_session

pytestmark = pytest.mark.zenoh


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def pair():
    port = _free_port()
    a = open_session(TransportConfig(mode="peer", connect=[], listen=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
    b = open_session(TransportConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
    try:
        yield a, b
    finally:
        b.close()
        a.close()


def _ask(session, key: str, payload: bytes | None, timeout: float = 3.0) -> tuple[str, object]:
    """('ok', decoded msgpack) or ('err', text) of the first reply."""
    kwargs = {} if payload is None else {"payload": payload}
    for reply in session.get(key, timeout=timeout, **kwargs):
        if reply.ok is not None:
            return "ok", reply.ok.payload.to_bytes()
        return "err", reply.err.payload.to_bytes().decode("utf-8")
    return "none", None


def _documented(text: str) -> bool:
    return any(text.startswith(p) for p, _ in ERROR_PREFIXES)


class _Refusing:
    name, dim = "refusing", 4

    def encode_text(self, texts):
        if texts == ["boom"]:
            raise KeyError("a bug, not a refusal")
        return np.ones((len(texts), 4), np.float32) / 2

    def encode_image(self, rgb):
        raise ValueError("no ground truth for this image")


def _wait_for(session, key: str, payload: bytes) -> None:
    deadline = time.monotonic() + 10
    while _ask(session, key, payload, 0.5)[0] == "none":
        assert time.monotonic() < deadline, "queryable never answered"


def test_embed_queryable_follows_the_rule(pair):
    a, b = pair
    key = Topics("robot0").vl_embed
    embedder = Embedder(_Refusing(), 0)
    q = TypedQueryable(a, key, EmbedRequest, EmbedReply, lambda env: embedder.embed(env.body), robot_id="robot0")
    good = encode(EmbedRequest(text="chair"), robot_id="robot0", seq=0, stamp=0.0)
    try:
        _wait_for(b, key, good)
        kind, body = _ask(b, key, good)
        assert kind == "ok" and decode(body, EmbedReply).body.embedding.shape == (4,)
        # Transport and decoding failures: error replies, UTF-8, with a documented prefix.
        cases = {
            "empty request: ": None,
            "bad request: not a valid msgpack": b"\xc1garbage",
            "bad request: expected a EmbedRequest": encode(QueryRequest(text="x"), robot_id="robot0", seq=0, stamp=0.0),
            "bad request: EmbedRequest.text": msgpack.packb({"v": 2, "type": "EmbedRequest", "robot": "robot0", "seq": 0, "stamp": 0.0, "body": {"text": 5}}),
            "bad request: EmbedRequest on trackgraph/robot0/vl/embed claims robot 'robot1'": encode(EmbedRequest(text="x"), robot_id="robot1", seq=0, stamp=0.0),
            "internal error: KeyError": encode(EmbedRequest(text="boom"), robot_id="robot0", seq=0, stamp=0.0),
        }
        for want, payload in cases.items():
            kind, text = _ask(b, key, payload)
            assert kind == "err" and _documented(text) and text.startswith(want), (want, kind, text)
        # A request understood but declined: a normal reply with error set, naming the field.
        image = encode(EmbedRequest(image=np.zeros((4, 4, 3), np.uint8)), robot_id="robot0", seq=0, stamp=0.0)
        kind, body = _ask(b, key, image)
        reply = decode(body, EmbedReply).body
        assert kind == "ok" and reply.embedding is None and reply.error == "EmbedRequest.image: no ground truth for this image"
    finally:
        q.close()


def test_query_refusals_are_replies_and_overload_is_an_error(pair):
    a, b = pair
    key = Topics("robot0").query
    engine = QueryEngine(QueryConfig(), lambda req: np.ones(4, np.float32))
    release = threading.Event()

    def handler(env):
        release.wait(5)  # hold the one worker, so the queue fills
        return engine.answer(QueryIndex.empty(), env.body)

    q = TypedQueryable(a, key, QueryRequest, QueryReply, handler, robot_id="robot0", capacity=1)
    try:
        release.set()
        room = encode(QueryRequest(text="chair", room=4), robot_id="robot0", seq=0, stamp=0.0)
        _wait_for(b, key, room)
        kind, body = _ask(b, key, room)
        reply = decode(body, QueryReply).body
        assert kind == "ok" and reply.hits == [] and "unknown room 4" in reply.error
        release.clear()
        pending = [b.get(key, payload=room, timeout=6.0) for _ in range(4)]
        time.sleep(0.5)
        release.set()
        texts = []
        for handle in pending:
            for r in handle:
                texts.append("ok" if r.ok is not None else r.err.payload.to_bytes().decode("utf-8"))
        assert any(t.startswith("overloaded: ") for t in texts), texts
        assert all(t == "ok" or _documented(t) for t in texts), texts
    finally:
        release.set()
        q.close()
