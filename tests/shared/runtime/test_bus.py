"""InProcessBus: ordered, deterministic delivery without threads; requests; latest queues."""

from __future__ import annotations

import numpy as np
import pytest

from shared.messages.frames import FrameAck
from shared.messages.rpc import EmbedReply, EmbedRequest
from shared.runtime.bus import BusError, InProcessBus


def test_delivery_in_publication_order_including_what_handlers_publish():
    bus = InProcessBus("robot0")
    seen: list[tuple[str, int]] = []
    echo = bus.publisher("b", FrameAck)
    bus.subscribe("a", FrameAck, lambda env: (seen.append(("a", env.body.frame_index)), echo.put(env.body)))
    bus.subscribe("b", FrameAck, lambda env: seen.append(("b", env.body.frame_index)))
    pub = bus.publisher("a", FrameAck)
    for i in range(3):
        pub.put(FrameAck(frame_index=i, service="tracker"))
    assert seen == []  # nothing before drain
    assert bus.drain() == 6
    assert seen == [("a", 0), ("a", 1), ("a", 2), ("b", 0), ("b", 1), ("b", 2)]
    assert bus.published == {"a": 3, "b": 3}


def test_latest_keeps_newest_and_counts_drops():
    bus = InProcessBus()
    got, drops = [], []
    bus.subscribe("k", FrameAck, lambda env: got.append(env.body.frame_index), policy="latest", capacity=2, on_drop=lambda: drops.append(1))
    pub = bus.publisher("k", FrameAck)
    for i in range(5):
        pub.put(FrameAck(frame_index=i, service="fusion"))
    bus.drain()
    assert got == [3, 4] and len(drops) == 3


def test_request_reply_and_errors():
    bus = InProcessBus()
    with pytest.raises(BusError, match="no queryable"):
        bus.request("vl/embed", EmbedRequest(text="x"), EmbedReply, timeout=1)
    bus.serve("vl/embed", EmbedRequest, EmbedReply, lambda env: EmbedReply(embedding=np.ones(3, np.float32), model="m"))
    assert bus.request("vl/embed", EmbedRequest(text="chair"), EmbedReply, timeout=1).model == "m"
    bus.serve("boom", EmbedRequest, EmbedReply, lambda env: 1 / 0)
    with pytest.raises(BusError, match="internal error: ZeroDivisionError"):
        bus.request("boom", EmbedRequest(text="x"), EmbedReply, timeout=1)


def test_type_checked_publish_and_alive_tokens():
    bus = InProcessBus()
    pub = bus.publisher("k", FrameAck)
    with pytest.raises(TypeError, match="carries FrameAck"):
        pub.put(EmbedRequest(text="x"))
    tok = bus.declare_alive("trackgraph/robot0/alive/tracker")
    assert "trackgraph/robot0/alive/tracker" in bus.alive
    tok.undeclare()
    assert not bus.alive
