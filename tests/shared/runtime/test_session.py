"""The sessions' common base: inputs and outputs counted under their topic names, a failing
handler counted and survived, held messages counted later, queryables, the ticker."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from shared.messages.frames import FrameAck
from shared.messages.rpc import EmbedReply, EmbedRequest
from shared.runtime.bus import BusError, InProcessBus
from shared.runtime.session import LATER, Session, Ticker
from shared.topics import Topics


class Echo(Session):
    """Forwards the even acks, holds the odd ones, fails on 13: enough to count."""

    service = "tracker"

    def __init__(self, bus) -> None:
        super().__init__(bus)
        self.seen: list[int] = []
        self.out = self.output("tracks_end", FrameAck)
        self.subscribe("frame_ack", FrameAck, self.on_ack)
        self.serve("vl_embed", EmbedRequest, EmbedReply, self.on_embed)

    def on_ack(self, msg: FrameAck):
        if msg.frame_index == 13:
            raise ValueError("unlucky")
        self.seen.append(msg.frame_index)
        if msg.frame_index % 2:
            return LATER
        self.out.put(msg)
        return None

    def on_embed(self, req: EmbedRequest) -> EmbedReply:
        if req.text == "boom":
            raise ValueError("no")
        return EmbedReply(embedding=np.ones(2, np.float32), model="m")


def test_inputs_outputs_and_failures_are_counted_by_topic_name():
    bus = InProcessBus()
    s = Echo(bus)
    pub = bus.publisher(Topics("robot0").frame_ack, FrameAck)
    for k in (0, 1, 13, 2):
        pub.put(FrameAck(frame_index=k, service="fusion"))
    assert s.queued() == 4 and s.queued("frame_ack") == 4 and s.queued("vl_embed") == 0
    bus.drain()
    assert s.seen == [0, 1, 2]  # the failing message did not stop the next one
    report = s.book.report()
    c = {i.name: i for i in report.inputs}["frame_ack"]
    assert (c.received, c.processed, c.rejected) == (4, 2, 1)  # 1 is held (LATER), 13 failed
    assert report.errors == 1 and report.published == {"tracks_end": 2}


def test_queryable_counts_and_a_failing_handler_is_the_callers_error():
    bus = InProcessBus()
    s = Echo(bus)
    key = Topics("robot0").vl_embed
    assert bus.request(key, EmbedRequest(text="x"), EmbedReply, timeout=1).model == "m"
    with pytest.raises(BusError, match="ValueError: no"):
        bus.request(key, EmbedRequest(text="boom"), EmbedReply, timeout=1)
    c = {i.name: i for i in s.book.report().inputs}["vl_embed"]
    assert (c.received, c.processed, c.rejected) == (2, 1, 1)


def test_close_closes_the_endpoints_not_the_bus():
    bus = InProcessBus()
    s = Echo(bus)
    s.close()
    s.close()
    pub = bus.publisher(Topics("robot0").frame_ack, FrameAck)
    pub.put(FrameAck(frame_index=0, service="fusion"))
    assert bus.drain() == 0 and s.seen == []
    with pytest.raises(BusError, match="no queryable"):
        bus.request(Topics("robot0").vl_embed, EmbedRequest(text="x"), EmbedReply, timeout=1)


def test_ticker_ticks_until_stopped_and_survives_a_failing_tick():
    ticks: list[float] = []
    done = threading.Event()

    def tick(now: float) -> None:
        ticks.append(now)
        if len(ticks) == 1:
            raise RuntimeError("first tick fails")
        if len(ticks) >= 3:
            done.set()

    t = Ticker(tick, 0.01, name="test:tick")
    assert done.wait(5)
    t.stop()
    n = len(ticks)
    assert n >= 3 and ticks == sorted(ticks)
    done.wait(0.05)
    assert len(ticks) == n


def test_fair_lock_is_reentrant_and_first_come_first_served():
    from shared.runtime.session import FairLock

    lock = FairLock()
    order: list[int] = []
    with lock, lock:  # reentrant
        threads = []
        for i in range(4):
            t = threading.Thread(target=lambda i=i: (lock.acquire(), order.append(i), lock.release()))
            t.start()
            threads.append(t)
            while len(lock._waiting) < i + 1:  # each has asked before the next starts
                threading.Event().wait(0.001)
    for t in threads:
        t.join(5)
    assert order == [0, 1, 2, 3]
    with pytest.raises(RuntimeError, match="does not hold"):
        lock.release()


def test_an_inbox_orders_queued_inputs_across_keys_and_counts_what_waits():
    from shared.runtime.session import Inbox

    class Two(Session):
        service = "fusion"

        def __init__(self, bus, inbox) -> None:
            super().__init__(bus, inbox=inbox)
            self.seen: list[tuple[str, int]] = []
            self.gate = threading.Event()
            self.subscribe("tracks_frame", FrameAck, lambda m: self.on("frame", m), queued=True)
            self.subscribe("tracks_end", FrameAck, lambda m: self.on("end", m), queued=True)
            self.subscribe("frame_ack", FrameAck, lambda m: self.seen.append(("direct", m.frame_index)))

        def on(self, what: str, msg: FrameAck) -> None:
            self.gate.wait(5)
            self.seen.append((what, msg.frame_index))

    bus = InProcessBus()
    inbox = Inbox(8, name="test:inbox")
    s = Two(bus, inbox)
    t = Topics("robot0")
    frames, end, ack = (bus.publisher(k, FrameAck) for k in (t.tracks_frame, t.tracks_end, t.frame_ack))
    frames.put(FrameAck(frame_index=0, service="fusion"))
    end.put(FrameAck(frame_index=1, service="fusion"))
    frames.put(FrameAck(frame_index=2, service="fusion"))
    ack.put(FrameAck(frame_index=9, service="fusion"))
    bus.drain()  # queued ones wait behind the gate on the inbox's thread; the direct one is done
    assert s.seen == [("direct", 9)]
    assert s.queued("tracks_frame") + s.queued("tracks_end") >= 2  # one may be in hand already
    s.gate.set()
    deadline = time.monotonic() + 5
    while len(s.seen) < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert s.seen == [("direct", 9), ("frame", 0), ("end", 1), ("frame", 2)]
    assert s.queued() == 0
    report = {c.name: c for c in s.book.report().inputs}
    assert report["tracks_frame"].processed == 2 and report["tracks_end"].processed == 1
    s.close()
