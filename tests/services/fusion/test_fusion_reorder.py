"""The tracker's frames and feature messages applied in the order it sent them (``order``):
what overtakes waits, what comes twice is dropped, a gap that never fills is given up after
``fusion.reorder_wait_s``, a new tracker stream starts the numbering again, and a restarted
fusion that sees a new frame before the ones sent again fuses them all, in order."""

from __future__ import annotations

import numpy as np

from services.fusion.durability.reorder import InOrder
from shared.messages.frames import EndOfSequence, TrackedFrame
from shared.messages.keyframes import TrackFeature, TrackFeatures
from tests.services.fusion.test_fusion_journal import stored_rig, tracked
from tests.services.fusion.test_fusion_session import FakeFusion

S = 7  # a tracker's stream


def test_messages_come_out_in_their_order():
    q = InOrder(wait_s=10.0, capacity=8)
    assert q.admit("frame", "a", S, 0, 0.0) == ([("frame", "a")], False)
    assert q.admit("frame", "c", S, 2, 0.0) == ([], False)  # overtook b: held
    assert q.admit("features", "d", S, 3, 0.0) == ([], False)
    assert len(q) == 2 and q.held_most == 2
    assert q.admit("features", "b", S, 1, 0.0) == ([("features", "b"), ("frame", "c"), ("features", "d")], False)
    assert q.admit("frame", "a", S, 0, 1.0) == ([], True)  # sent again: already applied
    assert q.admit("frame", "x", None, None, 1.0) == ([("frame", "x")], False)  # unnumbered: as it comes
    assert len(q) == 0 and q.next == 4 and q.skipped == 0


def test_a_gap_that_never_fills_is_given_up_after_the_wait():
    q = InOrder(wait_s=10.0, capacity=8)
    q.admit("frame", "a", S, 0, 0.0)
    q.admit("frame", "d", S, 3, 1.0)
    q.admit("frame", "e", S, 4, 2.0)
    assert q.expire(10.5) == []  # the oldest held has waited 9.5 s
    assert q.expire(11.5) == [("frame", "d"), ("frame", "e")]
    assert q.skipped == 2 and q.next == 5 and len(q) == 0
    assert q.admit("frame", "b", S, 1, 12.0) == ([], True)  # too late: its turn passed


def test_more_held_than_the_capacity_gives_the_gap_up():
    q = InOrder(wait_s=100.0, capacity=2)
    q.admit("frame", "a", S, 0, 0.0)
    assert q.admit("frame", "c", S, 2, 0.0)[0] == []
    assert q.admit("frame", "d", S, 3, 0.0)[0] == []
    assert q.admit("frame", "e", S, 4, 0.0)[0] == [("frame", "c"), ("frame", "d"), ("frame", "e")]
    assert q.skipped == 1


def test_a_new_tracker_stream_starts_the_numbering_again():
    q = InOrder(wait_s=10.0, capacity=8)
    for k in range(3):
        q.admit("frame", k, S, k, 0.0)
        q.applied(k)
    q.admit("frame", "held", S, 5, 0.0)
    assert q.admit("frame", "new", S + 1, 0, 1.0) == ([("frame", "new")], False)
    assert q.streams == 1 and q.dropped == 1 and len(q) == 0 and q.stream == S + 1


def test_a_snapshot_keeps_what_was_applied_not_what_was_released():
    q = InOrder(wait_s=10.0, capacity=8)
    q.admit("frame", "a", S, 0, 0.0)
    q.applied(0)
    q.admit("frame", "c", S, 2, 0.0)
    ready, _ = q.admit("frame", "b", S, 1, 0.0)
    assert len(ready) == 2
    q.applied(1)  # a snapshot now, before c is applied: c must be taken again at resume
    again = InOrder(wait_s=10.0, capacity=8)
    again.load(q.state())
    assert again.stream == S and again.next == 2
    assert again.admit("frame", "c", S, 2, 0.0) == ([("frame", "c")], False)


class OrderLog(FakeFusion):
    """The fake core, noting what it was given in which order."""

    def __init__(self) -> None:
        super().__init__()
        self.log: list[tuple[str, int]] = []

    def add_frame(self, tf: TrackedFrame):
        self.log.append(("frame", tf.frame.frame_index))
        return super().add_frame(tf)

    def add_track_features(self, msg: TrackFeatures) -> None:
        self.log.append(("features", msg.frame_index))
        super().add_track_features(msg)


def stream(n: int) -> list[TrackedFrame | TrackFeatures]:
    """What a tracker sends: frames, with a feature message after every third, numbered together."""
    out: list = []
    serial = 0
    for i in range(n):
        out.append(tracked(i))
        if i % 3 == 2:
            out.append(TrackFeatures(frame_index=i, tracks=[TrackFeature(track_id=i, dino=np.full(4, i, np.float32))], serial=serial))
            serial += 1
    return [m.model_copy(update={"order": k, "stream": S}) for k, m in enumerate(out)]


def send(rig, msg) -> None:
    (rig.frames if isinstance(msg, TrackedFrame) else rig.features).put(msg)
    rig.bus.drain()


def test_a_restarted_fusion_waits_for_what_is_sent_again(clock, tmp_path, monkeypatch):
    monkeypatch.setattr("services.fusion.export.export_map", lambda out, core: None)
    monkeypatch.setattr("services.fusion.export.run_summary", lambda *a, **kw: {})
    msgs = stream(12)  # 16 messages
    want = [("frame" if isinstance(m, TrackedFrame) else "features", m.frame.frame_index if isinstance(m, TrackedFrame) else m.frame_index) for m in msgs]
    rig = stored_rig(clock, tmp_path, core=OrderLog())
    for m in msgs[:5]:
        send(rig, m)
    rig.tick(11.0)  # a snapshot after 5 messages
    for m in msgs[5:8]:
        send(rig, m)  # journaled after it
    # SIGKILL; messages 8 and 9 were on their way and are lost with it

    again = stored_rig(clock, tmp_path, core=OrderLog(), resume=True)
    s = again.session
    assert again.core.log == want[5:8] and s.in_order.next == 8
    # new messages overtake the tracker's resend of 6..9 (it kept what was not acknowledged)
    for m in msgs[10:12]:
        send(again, m)
    assert len(s.in_order) == 2 and again.core.log == want[5:8]
    for m in msgs[6:10]:
        send(again, m)
    for m in msgs[12:]:
        send(again, m)
    again.end.put(EndOfSequence(frames_published=12, frames_dropped=0, last_frame_index=11, track_features_published=4))
    again.bus.drain()
    assert again.core.log == want[5:], "every message once, in the order sent"
    assert s.duplicates == 1 and s.features.duplicate == 1  # 6 and 7 were in the journal
    assert s.finished.is_set() and s.delivery()["reorder"]["skipped"] == 0
    s.close()
