"""Loopback Zenoh: typed pub/sub of a full-size RGB-D frame, queryables and liveliness."""

from __future__ import annotations

import socket
import time

import msgpack
import numpy as np
import pytest

from shared.codec import encode
from shared.config import TransportConfig
from shared.geometry import Intrinsics
from shared.messages import EmbedReply, EmbedRequest, Frame, FrameAck, QueryReply, QueryRequest
from shared.topics import Topics
from shared.transport import (
    LivelinessWatcher,
    TransportError,
    TypedPublisher,
    TypedQueryable,
    TypedSubscriber,
    declare_alive,
    open_session,
    request,
)

pytestmark = pytest.mark.zenoh


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def pair():
    """Two peer sessions joined over tcp/127.0.0.1, scouting off, shared memory off."""
    port = free_port()
    a_cfg = TransportConfig(mode="peer", connect=[], listen=[f"tcp/127.0.0.1:{port}"], shared_memory=False)
    b_cfg = TransportConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], shared_memory=False)
    a = open_session(a_cfg)
    b = open_session(b_cfg)
    try:
        yield a, b
    finally:
        b.close()
        a.close()


def _frame(h: int = 680, w: int = 1200, seed: int = 0) -> Frame:
    rng = np.random.default_rng(seed)
    return Frame(
        frame_index=7,
        rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth=rng.integers(0, 65535, (h, w), dtype=np.uint16),
        depth_scale=6553.5,
        intrinsics=Intrinsics(fx=600, fy=600, cx=599.5, cy=339.5, width=w, height=h),
        T_world_cam=np.eye(4),
    )


def _wait_matched(fn, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if fn():
            return True
        time.sleep(0.02)
    return False


def test_frame_pubsub_bytes_intact(pair):
    a, b = pair
    topics = Topics("robot0")
    sub = TypedSubscriber(b, topics.frames, Frame)
    pub = TypedPublisher(a, topics.frames, Frame, robot_id="robot0")
    frame = _frame()
    try:
        env = None
        # Declarations propagate asynchronously; publish until the first frame arrives.
        deadline = time.monotonic() + 5
        while env is None and time.monotonic() < deadline:
            pub.put(frame)
            env = sub.recv(timeout=0.2)
        assert env is not None, "no frame arrived over loopback"
        assert env.robot_id == "robot0"
        assert env.body.rgb.tobytes() == frame.rgb.tobytes()
        assert env.body.depth.tobytes() == frame.depth.tobytes()
        assert env.body.intrinsics == frame.intrinsics
        np.testing.assert_array_equal(env.body.T_world_cam, frame.T_world_cam)
    finally:
        pub.close()
        sub.close()


def test_subscriber_counts_and_skips_bad_payloads(pair):
    a, b = pair
    key = Topics("robot0").frames
    got = []
    sub = TypedSubscriber(b, key, Frame, callback=got.append)
    good = encode(_frame(8, 10), robot_id="robot0", seq=0, stamp=0.0)
    bad = [b"", b"\xc1", good[: len(good) // 2], msgpack.packb({"v": 1, "type": "Frame"})]
    try:
        raw = a.declare_publisher(key)
        assert _wait_matched(lambda: (raw.put(good), len(got) > 0)[1])
        base = len(got)
        for p in bad:
            raw.put(p)
        raw.put(good)
        assert _wait_matched(lambda: len(got) >= base + 1 and sub.stats.rejected >= len(bad))
        assert sub.stats.rejected == len(bad)
        assert "Frame" in sub.stats.last_error or "msgpack" in sub.stats.last_error or "envelope" in sub.stats.last_error
        raw.undeclare()
    finally:
        sub.close()


def test_latest_policy_drops_and_counts(pair):
    a, b = pair
    key = Topics("robot0").frames
    sub = TypedSubscriber(b, key, Frame, policy="latest", capacity=2)
    pub = TypedPublisher(a, key, Frame, robot_id="robot0")
    try:
        small = _frame(4, 4)
        assert _wait_matched(lambda: (pub.put(small), sub.pending() > 0)[1])
        for _ in range(20):
            pub.put(small)
        assert _wait_matched(lambda: sub.stats.dropped > 0)
        assert sub.pending() <= 2
        last = None
        while (env := sub.recv(timeout=0.2)) is not None:
            last = env
        assert last is not None and last.seq == pub.seq - 1, "latest policy must keep the newest"
    finally:
        pub.close()
        sub.close()


def test_queryable_replies_and_rejects(pair):
    a, b = pair
    key = Topics("robot0").vl_embed

    def handler(env):
        if env.body.text == "boom":
            raise RuntimeError("exploded")
        return EmbedReply(embedding=np.full(4, 0.5, np.float32), model="test")

    q = TypedQueryable(a, key, EmbedRequest, EmbedReply, handler, robot_id="robot0")
    try:
        assert _wait_matched(lambda: _try(lambda: request(b, key, EmbedRequest(text="x"), EmbedReply, robot_id="robot0", timeout=0.5)))
        rep = request(b, key, EmbedRequest(text="chair"), EmbedReply, robot_id="robot0", timeout=2)
        np.testing.assert_array_equal(rep.body.embedding, np.full(4, 0.5, np.float32))
        with pytest.raises(TransportError, match="bad request"):
            request(b, key, QueryRequest(text="chair"), QueryReply, robot_id="robot0", timeout=2)
        with pytest.raises(TransportError, match="internal error.*exploded"):
            request(b, key, EmbedRequest(text="boom"), EmbedReply, robot_id="robot0", timeout=2)
        # Still serving after the failures.
        assert request(b, key, EmbedRequest(text="lamp"), EmbedReply, robot_id="robot0", timeout=2).body.model == "test"
        # A request that claims another robot is refused, named, and counted.
        with pytest.raises(TransportError, match="claims robot 'robot1'"):
            request(b, key, EmbedRequest(text="chair"), EmbedReply, robot_id="robot1", timeout=2)
        assert q.stats.rejected == 2 and q.stats.handler_errors == 1
    finally:
        q.close()


def test_request_without_queryable_times_out(pair):
    _, b = pair
    t0 = time.monotonic()
    with pytest.raises(TransportError, match="no reply"):
        request(b, Topics("robot0").query, QueryRequest(text="x"), QueryReply, robot_id="c", timeout=0.3)
    assert time.monotonic() - t0 < 3


def test_liveliness_token_appears_and_disappears():
    port = free_port()
    watcher_s = open_session(TransportConfig(mode="peer", connect=[], listen=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
    try:
        key = Topics("robot0").alive("fusion")
        watcher = LivelinessWatcher(watcher_s, Topics("robot0").alive_all)
        service = open_session(TransportConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
        try:
            token = declare_alive(service, key)
            assert watcher.wait_for(key, present=True, timeout=5)
        finally:
            service.close()
        assert watcher.wait_for(key, present=False, timeout=5), "token must vanish when its session closes"
        del token
        watcher.close()
    finally:
        watcher_s.close()


def test_open_session_refuses_bad_endpoint_in_config():
    with pytest.raises(ValueError, match="endpoint"):
        TransportConfig(connect=["127.0.0.1:7447"])


def _try(fn) -> bool:
    try:
        fn()
        return True
    except TransportError:
        return False


def test_envelope_from_another_robot_is_refused_and_counted(pair):
    a, b = pair
    topics = Topics("robot0")
    rejected: list[str] = []
    sub = TypedSubscriber(b, topics.frame_ack, FrameAck, on_reject=rejected.append)
    wrong = TypedPublisher(a, topics.frame_ack, FrameAck, robot_id="robot1")
    right = TypedPublisher(a, topics.frame_ack, FrameAck, robot_id="robot0")
    try:
        assert _wait_matched(right.has_subscribers)
        wrong.put(FrameAck(frame_index=1, service="tracker"))
        right.put(FrameAck(frame_index=2, service="tracker"))
        env = sub.recv(timeout=5)
        assert env is not None and env.body.frame_index == 2
        assert sub.stats.rejected == 1
        assert "claims robot 'robot1'" in rejected[0] and "robot 'robot0'" in rejected[0]
    finally:
        wrong.close()
        right.close()
        sub.close()
