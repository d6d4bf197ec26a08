"""The tracker keeps what fusion has not acknowledged and sends it again, in order, to a
restarted fusion (a new epoch in its acks) or after ``resend_after_s``; feature messages
carry serials; the store is bounded."""

from __future__ import annotations

import numpy as np

from services.tracker.resend import Unacked
from shared.messages.frames import EndOfSequence, FrameAck, TrackedFrame
from shared.messages.keyframes import TrackFeature, TrackFeatures
from tests.services.conftest import tiny_frame
from tests.services.tracker.test_tracker_session import FakeTracker, Rig, features_for, masks_for


def tf(i: int) -> TrackedFrame:
    fr = tiny_frame(i)
    return TrackedFrame(frame=fr, track_ids=np.zeros(fr.depth.shape, np.int32), tracks=[])


def feats(serial: int | None) -> TrackFeatures:
    return TrackFeatures(frame_index=0, tracks=[TrackFeature(track_id=0, dino=np.ones(2, np.float32))], serial=serial)


def fusion_ack(k: int, epoch: int, through: int | None = None) -> FrameAck:
    return FrameAck(frame_index=k, service="fusion", epoch=epoch, features_through=through)


def test_acks_let_go_what_fusion_has_and_a_new_epoch_asks_for_the_rest():
    u = Unacked(capacity_frames=8, resend_after_s=5.0)
    for i in range(4):
        u.sent(feats(i), 0.0)
        u.sent(tf(i), 0.0)
    u.sent(feats(None), 0.0)  # no serial: cannot be told apart, not kept
    assert len(u) == 8 and u.frames == 4
    assert u.ack(fusion_ack(1, epoch=5, through=2)) is False  # the first epoch heard
    assert [type(b).__name__ for b in u.pending(1.0)] == ["TrackFeatures", "TrackedFrame", "TrackFeatures", "TrackedFrame"]
    assert u.ack(fusion_ack(1, epoch=5, through=3)) is False and len(u) == 3
    assert u.ack(fusion_ack(1, epoch=6)) is True and u.restarts == 1  # restarted: send the rest again
    assert [getattr(b, "serial", None) for b in u.pending(2.0)] == [None, 3, None] and u.resent == 7


def test_the_store_is_bounded_and_counts_what_it_let_go():
    u = Unacked(capacity_frames=2, resend_after_s=5.0)
    for i in range(5):
        u.sent(feats(i), 0.0)
        u.sent(tf(i), 0.0)
    assert u.frames == 2 and len(u) == 4  # features 3, frame 3, features 4, frame 4
    assert u.let_go == 6
    none = Unacked(capacity_frames=0, resend_after_s=5.0)
    none.sent(tf(0), 0.0)
    assert len(none) == 0


def test_time_out_only_once_fusion_was_heard_and_only_in_lossless():
    u = Unacked(capacity_frames=8, resend_after_s=5.0)
    u.sent(tf(0), 0.0)
    assert not u.due(10.0)  # nobody to send it to
    u.ack(fusion_ack(0, epoch=1))
    u.sent(tf(1), 10.0)
    assert not u.due(14.0) and u.due(15.5)
    live = Unacked(capacity_frames=8, resend_after_s=5.0, on_timeout=False)
    live.ack(fusion_ack(0, epoch=1))
    live.sent(tf(1), 0.0)
    assert not live.due(100.0)


def test_the_tracker_sends_again_to_a_restarted_fusion(clock, make_frame):
    rig = Rig(clock, core=FakeTracker(k=100))
    rig.send(rig.frames, make_frame(0))  # a keyframe: requested, propagated on (no wait)
    rig.send(rig.masks, masks_for(0))
    rig.send(rig.features, features_for(0))
    for i in range(1, 4):
        rig.send(rig.frames, make_frame(i))
    assert rig.tracked() == [0, 1, 2, 3]
    assert [f.serial for f in rig.got["tracks_features"]] == [0]  # once the keyframe's features were in
    acks = rig.bus.publisher(rig.session.topics.frame_ack, FrameAck)
    rig.send(acks, FrameAck(frame_index=3, service="tracker"))  # not fusion's: changes nothing
    rig.send(acks, fusion_ack(1, epoch=7, through=0))
    assert rig.session.unacked.frames == 2 and len(rig.session.unacked) == 3
    rig.send(rig.end, EndOfSequence(frames_published=4, frames_dropped=0, last_frame_index=3))
    assert [e.track_features_published for e in rig.got["tracks_end"]] == [1]
    rig.send(acks, fusion_ack(1, epoch=8, through=0))  # fusion restarted, its journal up to frame 1
    assert rig.tracked() == [0, 1, 2, 3, 2, 3]
    assert [f.serial for f in rig.got["tracks_features"]] == [0, 0]
    # frames and feature messages numbered together in one stream; sent again with their numbers
    frames, feats = rig.got["tracks_frame"], rig.got["tracks_features"]
    assert {m.stream for m in frames + feats} == {rig.session.stream}
    assert sorted(m.order for m in frames[:4] + feats[:1]) == [0, 1, 2, 3, 4]
    assert [m.order for m in frames[4:]] == [m.order for m in frames[2:4]] and feats[1].order == feats[0].order
    assert len(rig.got["tracks_end"]) == 2  # the end again, after what it announces
    figures = rig.session.book.report().figures["unacked"]
    assert figures["resent"] == 3 and figures["fusion_restarts"] == 1
    rig.send(acks, fusion_ack(3, epoch=8, through=1))
    assert len(rig.session.unacked) == 0
    rig.tick(60.0)
    assert rig.tracked() == [0, 1, 2, 3, 2, 3]  # nothing left to send


def test_unacknowledged_frames_go_again_after_the_time_out(clock, make_frame):
    rig = Rig(clock, core=FakeTracker(k=100))
    acks = rig.bus.publisher(rig.session.topics.frame_ack, FrameAck)
    rig.send(rig.frames, make_frame(0))
    rig.send(acks, fusion_ack(0, epoch=3))
    rig.send(rig.frames, make_frame(1))  # lost on the link, say
    rig.tick(4.0)
    assert rig.tracked() == [0, 1]
    rig.tick(2.0)
    assert rig.tracked() == [0, 1, 1]
    live = Rig(clock, core=FakeTracker(k=100), mode="live")
    acks = live.bus.publisher(live.session.topics.frame_ack, FrameAck)
    live.send(live.frames, make_frame(0))
    live.send(acks, fusion_ack(0, epoch=3))
    live.send(live.frames, make_frame(1))
    live.tick(30.0)
    assert live.tracked() == [0, 1]  # live: a late frame is not worth sending again
