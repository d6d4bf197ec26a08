"""The tracker session over the in-process bus with a fake core and a fake clock: keyframe
life (requested, masks, features, expired), wait_for_masks holding and releasing frames,
the end of the sequence only once everything announced is out, acks, bad messages."""

from __future__ import annotations

import numpy as np
import pytest

from services.tracker.session import TrackerSession
from shared.config import TrackGraphConfig
from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame
from shared.messages.keyframes import (
    KeyframeMasks,
    KeyframeRequest,
    MaskFeatures,
    TrackFeature,
    TrackFeatures,
)
from shared.runtime.bus import InProcessBus
from shared.topics import Topics

TIMEOUT = 5.0


class FakeTracker:
    """The tracker core's call protocol: a keyframe request every ``k`` frames, track 0 on
    every pixel once a keyframe's masks are in, a TrackFeatures after masks and features."""

    takes_masks = True

    def __init__(self, k: int = 3, bad: tuple[int, ...] = ()) -> None:
        self.k, self.bad = k, set(bad)
        self.count = 0
        self.calls: list[tuple[str, int]] = []
        self.frame: Frame | None = None
        self.masked: set[int] = set()
        self.changed = False

    def begin_frame(self, frame: Frame) -> KeyframeRequest | None:
        if frame.frame_index in self.bad:
            raise ValueError(f"frame {frame.frame_index} is bad")
        self.calls.append(("begin", frame.frame_index))
        self.frame, c = frame, self.count
        self.count += 1
        return KeyframeRequest(frame_index=frame.frame_index, rgb=frame.rgb) if c % self.k == 0 else None

    def end_frame(self) -> TrackedFrame:
        fr = self.frame
        assert fr is not None
        self.calls.append(("end", fr.frame_index))
        ids = np.full(fr.depth.shape, 0 if self.masked else -1, np.int32)
        return TrackedFrame(frame=fr, track_ids=ids, tracks=[])

    def apply_masks(self, frame_index: int, masks) -> bool:
        if len(masks) and masks.masks.shape[1:] != (4, 4):
            raise ValueError(f"masks of {masks.masks.shape[1:]} for a 4x4 frame")
        self.calls.append(("masks", frame_index))
        self.masked.add(frame_index)
        self.changed = True
        return True

    def apply_features(self, frame_index: int, features) -> None:
        self.calls.append(("features", frame_index))
        self.changed = True

    def take_track_features(self, frame_index: int) -> TrackFeatures | None:
        if not self.changed:
            return None
        self.changed = False
        return TrackFeatures(frame_index=frame_index, tracks=[TrackFeature(track_id=0, dino=np.ones(4, np.float32))])


class Rig:
    """A tracker session on an in-process bus, with publishers for its inputs and every output collected."""

    def __init__(self, clock, *, wait_for_masks: bool = False, mode: str = "lossless", core: FakeTracker | None = None) -> None:
        cfg = TrackGraphConfig.model_validate({"tracker": {"keyframe_timeout_s": TIMEOUT}, "source": {"mode": mode}})
        self.clock = clock
        self.bus = InProcessBus("robot0", clock=clock)
        self.core = core or FakeTracker()
        self.session = TrackerSession(self.bus, cfg, self.core, wait_for_masks=wait_for_masks, clock=clock)
        t = Topics("robot0")
        self.got: dict[str, list] = {name: [] for name in ("keyframe_request", "tracks_frame", "tracks_features", "tracks_end", "frame_ack")}
        for name, typ in (("keyframe_request", KeyframeRequest), ("tracks_frame", TrackedFrame), ("tracks_features", TrackFeatures),
                          ("tracks_end", EndOfSequence), ("frame_ack", FrameAck)):  # fmt: skip
            self.bus.subscribe(getattr(t, name), typ, lambda env, n=name: self.got[n].append(env.body))
        self.frames = self.bus.publisher(t.frames, Frame)
        self.masks = self.bus.publisher(t.keyframe_masks, KeyframeMasks)
        self.features = self.bus.publisher(t.keyframe_features, MaskFeatures)
        self.end = self.bus.publisher(t.end_of_sequence, EndOfSequence)

    def send(self, pub, body) -> None:
        pub.put(body)
        self.bus.drain()

    def tick(self, dt: float) -> None:
        """Time passes; what the tick publishes is delivered."""
        self.session.tick(self.clock.advance(dt))
        self.bus.drain()

    def tracked(self) -> list[int]:
        return [tf.frame.frame_index for tf in self.got["tracks_frame"]]

    def acked(self) -> list[int]:
        return [a.frame_index for a in self.got["frame_ack"]]


def masks_for(k: int, n: int = 1, error: str | None = None, size: int = 4) -> KeyframeMasks:
    return KeyframeMasks(
        frame_index=k, masks=np.ones((n, size, size), bool), boxes=np.zeros((n, 4), np.float32), scores=np.ones(n, np.float32), error=error,
    )  # fmt: skip


def features_for(k: int, n: int = 1) -> MaskFeatures:
    return MaskFeatures(frame_index=k, features=np.ones((n, 8), np.float32), model="fake")


def test_keyframe_requested_masks_then_features_then_answered(clock, make_frame):
    rig = Rig(clock)
    s = rig.session
    for i in range(2):
        rig.send(rig.frames, make_frame(i))
    assert [r.frame_index for r in rig.got["keyframe_request"]] == [0]
    assert rig.tracked() == [0, 1] and rig.acked() == [0, 1]  # live propagation never waits
    assert s.pending == {0: clock.t}
    clock.advance(0.5)
    rig.send(rig.masks, masks_for(0))
    assert not s.pending and s.awaiting_features == {0: clock.t}
    assert len(rig.got["tracks_features"]) == 0  # changes go out with the next frame, or with the features
    clock.advance(0.5)
    rig.send(rig.features, features_for(0))
    assert not s.awaiting_features and len(rig.got["tracks_features"]) == 1
    kf = s.keyframes.as_dict()
    assert kf["requested"] == kf["masks"] == kf["answered"] == 1 and kf["latency_max_s"] == pytest.approx(1.0)
    report = s.book.report()
    assert report.figures["keyframes"] == kf and report.figures["frames"] == 2 and report.frames_done == 2
    counts = {c.name: c for c in report.inputs}
    assert counts["frames"].processed == 2 and counts["keyframe_masks"].processed == 1 and counts["keyframe_features"].processed == 1
    assert report.published == {"keyframe_request": 1, "tracks_frame": 2, "frame_ack": 2, "tracks_features": 1}


def test_features_that_overtake_their_masks_wait_for_them(clock, make_frame):
    rig = Rig(clock)
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.features, features_for(0))  # over Zenoh, another key: no order with the masks
    assert rig.core.calls == [("begin", 0), ("end", 0)] and 0 in rig.session.early
    rig.send(rig.masks, masks_for(0))
    assert rig.core.calls[-2:] == [("masks", 0), ("features", 0)]
    assert not rig.session.awaiting_features and rig.session.keyframes.as_dict()["answered"] == 1


def test_a_keyframe_without_masks_expires_on_tick(clock, make_frame):
    rig = Rig(clock)
    rig.send(rig.frames, make_frame(0))
    rig.tick(TIMEOUT - 0.1)
    assert rig.session.pending
    rig.tick(0.2)
    assert not rig.session.pending and rig.session.keyframes.timed_out == 1
    assert rig.session.book.report().figures["timeouts"] == 1
    # masks that come after all are still applied (the core decides whether they are stale)
    rig.send(rig.masks, masks_for(0))
    assert ("masks", 0) in rig.core.calls


def test_wait_for_masks_holds_later_frames_until_the_masks_arrive(clock, make_frame):
    rig = Rig(clock, wait_for_masks=True)
    for i in range(3):
        rig.send(rig.frames, make_frame(i))
    assert rig.tracked() == [] and rig.acked() == []  # frame 0 waits for its masks, 1 and 2 behind it
    assert rig.core.calls == [("begin", 0)] and len(rig.session.held) == 2
    rig.send(rig.masks, masks_for(0))
    # masks applied before the keyframe ends; then the held frames, in order
    assert rig.core.calls == [("begin", 0), ("masks", 0), ("end", 0), ("begin", 1), ("end", 1), ("begin", 2), ("end", 2)]
    assert rig.tracked() == [0, 1, 2] and rig.acked() == [0, 1, 2]
    assert (rig.got["tracks_frame"][0].track_ids == 0).all()
    counts = {c.name: c for c in rig.session.book.report().inputs}["frames"]
    assert counts.received == 3 and counts.processed == 3


def test_wait_for_masks_releases_on_timeout_and_holds_again_at_the_next_keyframe(clock, make_frame):
    rig = Rig(clock, wait_for_masks=True)
    for i in range(5):
        rig.send(rig.frames, make_frame(i))
    rig.tick(TIMEOUT / 2)
    assert rig.tracked() == []
    rig.tick(TIMEOUT)
    # 0 expired and ended on propagation, 1 and 2 follow, 3 is the next keyframe and waits
    assert rig.tracked() == [0, 1, 2] and rig.session.keyframes.timed_out == 1
    assert list(rig.session.pending) == [3] and [f.frame_index for f in rig.session.held] == [4]
    rig.send(rig.masks, masks_for(3, error="segmenter down"))
    assert rig.tracked() == [0, 1, 2, 3, 4] and rig.session.keyframes.failed == 1


def test_live_keeps_at_most_one_frame_waiting_and_counts_the_drops(clock, make_frame):
    rig = Rig(clock, wait_for_masks=True, mode="live")
    for i in range(4):
        rig.send(rig.frames, make_frame(i))
    assert [f.frame_index for f in rig.session.held] == [3]  # the newest
    counts = {c.name: c for c in rig.session.book.report().inputs}["frames"]
    assert counts.dropped == 2 and counts.received == 4
    rig.send(rig.masks, masks_for(0))
    assert rig.tracked() == [0, 3]


def test_end_of_sequence_only_after_the_announced_features(clock, make_frame):
    rig = Rig(clock)
    for i in range(4):
        rig.send(rig.frames, make_frame(i))  # keyframes 0 and 3
    rig.send(rig.masks, masks_for(0))
    rig.send(rig.features, features_for(0))
    rig.send(rig.end, EndOfSequence(frames_published=4, frames_dropped=0, last_frame_index=3))
    assert rig.got["tracks_end"] == []  # keyframe 3 has no masks yet
    assert rig.session.book.report().frames_expected == 4
    rig.send(rig.masks, masks_for(3))
    assert rig.got["tracks_end"] == []  # nor features
    rig.send(rig.features, features_for(3))
    (end,) = rig.got["tracks_end"]
    assert end.last_frame_index == 3 and end.frames_published == 4
    assert end.track_features_published == len(rig.got["tracks_features"]) == 2
    assert rig.session.book.state == "finished"
    rig.send(rig.frames, make_frame(10))  # the next sequence
    assert rig.session.book.state == "running"


def test_end_of_sequence_waits_for_missing_features_at_most_the_timeout(clock, make_frame):
    rig = Rig(clock)
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.masks, masks_for(0))
    rig.send(rig.end, EndOfSequence(frames_published=1, frames_dropped=0, last_frame_index=0))
    rig.tick(1.0)
    assert rig.got["tracks_end"] == []
    rig.tick(TIMEOUT)
    (end,) = rig.got["tracks_end"]
    assert end.last_frame_index == 0


def test_end_of_sequence_before_its_last_frames_waits_for_them(clock, make_frame):
    rig = Rig(clock, core=FakeTracker(k=100))
    rig.send(rig.frames, make_frame(0))
    rig.session.pending.clear()  # no keyframe business here
    rig.send(rig.end, EndOfSequence(frames_published=3, frames_dropped=0, last_frame_index=2))
    assert rig.got["tracks_end"] == []
    rig.send(rig.frames, make_frame(1))
    rig.send(rig.frames, make_frame(2))
    (end,) = rig.got["tracks_end"]
    assert end.last_frame_index == 2


def test_a_failing_frame_is_counted_acked_and_not_fatal(clock, make_frame):
    rig = Rig(clock, core=FakeTracker(bad=(1,)))
    for i in range(3):
        rig.send(rig.frames, make_frame(i))
    assert rig.tracked() == [0, 2] and rig.acked() == [0, 1, 2]
    report = rig.session.book.report()
    frames = {c.name: c for c in report.inputs}["frames"]
    assert frames.rejected == 1 and frames.processed == 2 and report.errors == 1
    # the end of the sequence is not held up by the frame that failed
    rig.send(rig.masks, masks_for(0))
    rig.send(rig.features, features_for(0))
    rig.send(rig.end, EndOfSequence(frames_published=3, frames_dropped=0, last_frame_index=2))
    assert len(rig.got["tracks_end"]) == 1


def test_bad_masks_are_counted_and_the_held_keyframe_still_goes(clock, make_frame):
    rig = Rig(clock, wait_for_masks=True)
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.frames, make_frame(1))
    rig.send(rig.masks, masks_for(0, size=8))  # valid message, wrong size for its frame
    masks = {c.name: c for c in rig.session.book.report().inputs}["keyframe_masks"]
    assert masks.rejected == 1 and rig.session.book.errors == 1
    assert rig.tracked() == [0, 1]  # its keyframe is no longer waited for
    rig.send(rig.frames, make_frame(2))
    assert rig.tracked() == [0, 1, 2]


class Oracle:
    """The ground-truth tracker's protocol: frames only, no keyframe requests, no masks."""

    takes_masks = False

    def __init__(self) -> None:
        self.frame: Frame | None = None

    def begin_frame(self, frame: Frame) -> None:
        self.frame = frame

    def end_frame(self) -> TrackedFrame:
        assert self.frame is not None
        return TrackedFrame(frame=self.frame, track_ids=np.zeros(self.frame.depth.shape, np.int32), tracks=[])

    def take_track_features(self, frame_index: int) -> None:
        return None


def test_the_ground_truth_tracker_needs_no_keyframe_answers(clock, make_frame):
    rig = Rig(clock, core=Oracle())
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.masks, masks_for(0))  # a stray answer is harmless
    rig.send(rig.end, EndOfSequence(frames_published=1, frames_dropped=0, last_frame_index=0))
    assert rig.tracked() == [0] and len(rig.got["tracks_end"]) == 1


# ---------------------------------------------------------------- keyframe views on to fusion


class QuietTracker(FakeTracker):
    """Its CLIP features change no track (a keyframe whose masks all went to no track)."""

    def apply_features(self, frame_index: int, features) -> None:
        self.calls.append(("features", frame_index))


def view_of(k: int) -> np.ndarray:
    v = np.random.default_rng(k).standard_normal(8).astype(np.float32)
    return v / np.linalg.norm(v)


def with_view(msg: MaskFeatures, view: np.ndarray) -> MaskFeatures:
    return msg.model_copy(update={"view": view})


def test_a_keyframe_view_rides_with_its_track_features(clock, make_frame):
    rig = Rig(clock)
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.masks, masks_for(0))
    rig.send(rig.features, with_view(features_for(0), view_of(0)))
    (feats,) = rig.got["tracks_features"]
    assert feats.frame_index == 0 and [t.track_id for t in feats.tracks] == [0]
    np.testing.assert_array_equal(feats.view, view_of(0))
    # numbered as every message to fusion: after frame 0's TrackedFrame
    assert (feats.serial, feats.order, feats.stream) == (0, 1, rig.session.stream)


def test_a_keyframe_view_goes_out_when_no_track_changed(clock, make_frame):
    rig = Rig(clock, core=QuietTracker())
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.masks, masks_for(0))
    rig.send(rig.frames, make_frame(1))  # takes the masks' changes
    assert len(rig.got["tracks_features"]) == 1
    rig.send(rig.features, features_for(0))  # nothing changed, no view: nothing to send
    assert len(rig.got["tracks_features"]) == 1
    rig.send(rig.frames, make_frame(2))
    rig.send(rig.frames, make_frame(3))
    rig.send(rig.masks, masks_for(3))
    rig.send(rig.frames, make_frame(4))
    rig.send(rig.features, with_view(features_for(3), view_of(3)))
    feats = rig.got["tracks_features"][-1]
    assert len(rig.got["tracks_features"]) == 3
    assert feats.frame_index == 3 and feats.tracks == [] and feats.retired == []
    np.testing.assert_array_equal(feats.view, view_of(3))
    assert feats.serial == 2 and feats.order == 7  # after frames 0-4 and two feature messages (orders 0-6)


def test_a_view_is_passed_on_from_a_keyframe_whose_crops_failed(clock, make_frame):
    rig = Rig(clock)
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.masks, masks_for(0))
    failed = MaskFeatures(frame_index=0, features=np.zeros((0, 8), np.float32), model="fake", error="CLIP out of memory")
    rig.send(rig.features, with_view(failed, view_of(0)))
    (feats,) = rig.got["tracks_features"]
    assert feats.tracks == [] and ("features", 0) not in rig.core.calls
    np.testing.assert_array_equal(feats.view, view_of(0))
    assert rig.session.keyframes.failed == 1


def test_a_view_that_overtook_its_masks_goes_out_after_them(clock, make_frame):
    rig = Rig(clock, core=QuietTracker())
    rig.send(rig.frames, make_frame(0))
    rig.send(rig.features, with_view(features_for(0), view_of(0)))
    assert rig.got["tracks_features"] == []
    rig.send(rig.masks, masks_for(0))
    (feats,) = rig.got["tracks_features"]  # the masks' changes and the view in one message
    assert feats.frame_index == 0 and [t.track_id for t in feats.tracks] == [0]
    np.testing.assert_array_equal(feats.view, view_of(0))


def test_a_view_is_sent_again_to_a_restarted_fusion(clock, make_frame):
    rig = Rig(clock, core=QuietTracker())
    acks = rig.bus.publisher(Topics("robot0").frame_ack, FrameAck)
    rig.send(rig.frames, make_frame(0))
    rig.send(acks, FrameAck(frame_index=0, service="fusion", epoch=1, features_through=0))
    rig.send(rig.masks, masks_for(0))
    rig.send(rig.features, with_view(features_for(0), view_of(0)))
    (first,) = rig.got["tracks_features"]
    rig.send(acks, FrameAck(frame_index=0, service="fusion", epoch=2, features_through=0))  # a new fusion
    again = rig.got["tracks_features"][1:]
    assert [(f.serial, f.order) for f in again] == [(first.serial, first.order)]
    np.testing.assert_array_equal(again[0].view, view_of(0))
