"""The tracker's coordination, without Zenoh: ``frames`` in; ``keyframe/request`` out and
``keyframe/masks`` / ``keyframe/features`` back; ``tracks/frame`` and ``tracks/features`` out;
``frames/ack`` for every frame tracked or failed; the source's ``frames/end`` passed on as
``tracks/end`` once everything for the sequence is out, the CLIP features of the last
keyframes included (they arrive after its last frame).

Each keyframe lives through: requested (``pending``), masks in (``awaiting_features``),
features in, or expired after ``tracker.keyframe_timeout_s`` (counted in the
:class:`~services.tracker.pace.KeyframeLedger`). Masks and CLIP features are applied as soon
as they arrive, past the frames still queued: masks may come late (a remote GPU) and the core
corrects at that keyframe and re-propagates; in lossless replay the frame queue runs far
ahead, and behind it the features would reach the core after their keyframe left its history.
If keyframe_vl is down, requests time out, are counted, and the tracker propagates on; it
recovers when masks come back.

With ``wait_for_masks`` a keyframe is not ended until its masks are in or it expired: the
frames after it are held here meanwhile (never waited for), and released in order.

What goes to fusion is kept until fusion acknowledges it (:mod:`services.tracker.resend`) and
sent again to a restarted fusion, the end of the sequence after it; feature messages carry a
``serial`` so fusion applies each once, and both kinds an ``order`` (numbered together, in
this tracker's ``stream``) so fusion applies them in the order they went out.

A keyframe's view (``MaskFeatures.view``, its whole-image embedding) goes on to fusion in
the TrackFeatures sent for that keyframe's features, one without tracks if none changed.
"""

from __future__ import annotations

import collections
import logging
import secrets
import time
from collections.abc import Callable
from typing import cast

from services.tracker.pace import KeyframeLedger
from services.tracker.protocol import FrameTracker, MaskTracker
from services.tracker.resend import Unacked
from shared.config.root import TrackGraphConfig
from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures, TrackFeatures
from shared.perception import Masks
from shared.runtime.bus import Bus
from shared.runtime.session import LATER, Inbox, Session

log = logging.getLogger(__name__)


class TrackerSession(Session):
    """A tracker core (``TrackerCore`` or the ground-truth tracker, see
    :mod:`services.tracker.protocol`) on a bus.

    ``wait_for_masks`` overrides ``cfg.tracker.wait_for_masks`` (``trackgraph map`` always
    waits: its keyframe_vl answers within the same delivery round).
    """

    service = "tracker"

    def __init__(
        self, bus: Bus, cfg: TrackGraphConfig, core: FrameTracker, *, wait_for_masks: bool | None = None,
        clock: Callable[[], float] = time.monotonic, inbox: Inbox | None = None,
    ) -> None:  # fmt: skip
        super().__init__(bus, clock=clock, inbox=inbox)
        self.core = core
        self._mask_tracker: MaskTracker | None = cast(MaskTracker, core) if core.takes_masks else None
        """The core, when keyframe_vl's masks and CLIP features are applied to it."""
        self.timeout_s = cfg.tracker.keyframe_timeout_s
        self.wait_for_masks = cfg.tracker.wait_for_masks if wait_for_masks is None else wait_for_masks
        live = cfg.source.mode == "live"
        # Lossless: the source is paced to source.window_frames ahead; room for more. Live, the
        # subscription keeps the newest two and at most one more frame waits behind the one
        # being tracked (the node's inbox, or here behind a keyframe): a deeper queue would let
        # the tracker fall seconds behind a live camera before it dropped anything.
        capacity = 2 if live else 4 * cfg.source.window_frames
        self.hold_capacity = 1 if live else capacity
        self.live = live
        self.keyframes = KeyframeLedger()
        self.unacked = Unacked(cfg.tracker.resend_frames, cfg.tracker.resend_after_s, on_timeout=not live)
        """Sent to fusion and not acknowledged: sent again after a fusion restart."""
        self._serial = 0
        """The next feature message's ``serial``: how many distinct ones went out."""
        self.stream = secrets.randbits(62)
        """This tracker's epoch, in every message to fusion with its ``order``."""
        self._order = 0
        """The next message's ``order``: frames and feature messages to fusion, numbered together."""
        self._sent_end: EndOfSequence | None = None
        """The ``tracks/end`` sent, to send again behind a resend."""
        self.pending: dict[int, float] = {}
        """Keyframes asked for and not answered: frame index -> time asked."""
        self.awaiting_features: dict[int, float] = {}
        """Keyframes whose masks are in and CLIP features not yet: frame index -> since when."""
        self.frames = 0
        """Frames tracked."""
        self.early: dict[int, MaskFeatures] = {}
        """CLIP features that overtook their keyframe's masks (another key, another thread):
        applied right after the masks, or when the keyframe expires."""
        self.held: collections.deque[Frame] = collections.deque()
        """Frames waiting behind a keyframe whose masks are awaited (``wait_for_masks``)."""
        self._open: tuple[Frame, float] | None = None
        """The keyframe begun and not yet ended because its masks are awaited, and since when."""
        self._end: EndOfSequence | None = None
        self._end_at = 0.0
        self._last_index = -1
        """Last frame tracked."""
        self._last_handled = -1
        """Last frame tracked, failed or dropped here: the stream has reached it."""
        self.requests = self.output("keyframe_request", KeyframeRequest)
        self.tracked = self.output("tracks_frame", TrackedFrame)
        self.features = self.output("tracks_features", TrackFeatures)
        self.ends = self.output("tracks_end", EndOfSequence)
        self.acks = self.output("frame_ack", FrameAck)
        # Frames and the end of the sequence in their order; masks and features past them.
        self.subscribe("frames", Frame, self._on_frame, policy="latest" if live else "fifo", capacity=capacity, queued=True)
        self.subscribe("keyframe_masks", KeyframeMasks, self._on_masks, capacity=16)
        self.subscribe("keyframe_features", MaskFeatures, self._on_features, capacity=16)
        self.subscribe("end_of_sequence", EndOfSequence, self._on_end, capacity=4, queued=True)
        self.subscribe("frame_ack", FrameAck, self._on_ack, capacity=256)
        self._refresh()

    # ---------------------------------------------------------------- to fusion, kept until acknowledged

    def _send_features(self, feats: TrackFeatures) -> None:
        feats = feats.model_copy(update={"serial": self._serial, "order": self._order, "stream": self.stream})
        self._serial += 1
        self._order += 1
        self.features.put(feats)
        self.unacked.sent(feats, self.clock())

    def _send_tracked(self, tracked: TrackedFrame) -> None:
        tracked = tracked.model_copy(update={"order": self._order, "stream": self.stream})
        self._order += 1
        self.tracked.put(tracked)
        self.unacked.sent(tracked, self.clock())

    def _on_ack(self, msg: FrameAck) -> None:
        if msg.service != "fusion":
            return None  # the tracker's own, and other stages'
        if self.unacked.ack(msg):
            log.info("fusion restarted (epoch %d): sending again the %d messages it has not acknowledged", msg.epoch, len(self.unacked))
            self._resend(self.clock())
        self._refresh()

    def _resend(self, now: float) -> None:
        for body in self.unacked.pending(now):
            if isinstance(body, TrackedFrame):
                self.tracked.put(body)
            else:
                self.features.put(body)
        if self._sent_end is not None:
            self.ends.put(self._sent_end)

    # ---------------------------------------------------------------- frames

    def _on_frame(self, frame: Frame) -> object:
        if self.book.state == "finished":
            self.book.set_state("running")  # the next sequence
            self._sent_end = None
        if self._open is not None or self.held:
            self._hold(frame)
        else:
            self._begin(frame, self.clock())
        self._maybe_end(self.clock())
        self._refresh()
        return LATER  # counted when tracked, failed or dropped

    def _hold(self, frame: Frame) -> None:
        if len(self.held) < self.hold_capacity:
            self.held.append(frame)
            return
        if self.live:
            # the newest frame matters: the oldest waiting one goes
            lost = self.held.popleft()
            self.held.append(frame)
        else:
            # full, as a full subscription: the new one is lost (a source that paces on acks
            # never gets this far ahead)
            lost = frame
            log.warning("frame %d dropped: %d frames already wait for keyframe masks", frame.frame_index, len(self.held))
        self.book.count("frames", "dropped")
        self._last_handled = max(self._last_handled, lost.frame_index)

    def _begin(self, frame: Frame, t0: float) -> None:
        try:
            req = self.core.begin_frame(frame)
            if req is not None:
                self.requests.put(req)
                now = self.clock()
                self.pending[frame.frame_index] = now
                self.keyframes.request(frame.frame_index, now)
                if self.wait_for_masks:
                    self._open = (frame, t0)
                    return
            self._finish(frame, t0)
        except Exception:  # noqa: BLE001 - one bad frame must not stop tracking
            self._failed(frame)

    def _finish(self, frame: Frame, t0: float) -> None:
        """End a begun frame: its TrackedFrame and changed track features out, then its ack."""
        try:
            self._expire(self.clock())
            tracked = self.core.end_frame()
            feats = self.core.take_track_features(frame.frame_index)
            if feats is not None:
                self._send_features(feats)
            self._send_tracked(tracked)
        except Exception:  # noqa: BLE001
            self._failed(frame)
            return
        self.frames += 1
        self._last_index = frame.frame_index
        self._last_handled = max(self._last_handled, frame.frame_index)
        self.book.count("frames", "processed")
        self.book.work_done(max(self.clock() - t0, 0.0))
        self._ack(frame.frame_index)

    def _failed(self, frame: Frame) -> None:
        log.exception("tracker failed on a Frame (frame %d)", frame.frame_index)
        self.book.count("frames", "rejected")
        self.book.error()
        self._last_handled = max(self._last_handled, frame.frame_index)
        self._ack(frame.frame_index)

    def _ack(self, frame_index: int) -> None:
        # tracked or failed: a lossless source waits for it
        try:
            self.acks.put(FrameAck(frame_index=frame_index, service="tracker"))
        except Exception:  # noqa: BLE001 - the link may be going; the source's pacing copes
            log.warning("frame %d: ack not sent", frame_index, exc_info=True)

    def _release(self) -> None:
        """End the open keyframe once its masks are in (or it expired), then begin the held
        frames in order, until one is a keyframe that waits again."""
        while True:
            if self._open is not None:
                frame, t0 = self._open
                if frame.frame_index in self.pending:
                    return
                self._open = None
                self._finish(frame, t0)
            if not self.held:
                return
            self._begin(self.held.popleft(), self.clock())

    # ---------------------------------------------------------------- keyframes

    def _on_masks(self, msg: KeyframeMasks) -> None:
        k = msg.frame_index
        now = self.clock()
        try:
            self.pending.pop(k, None)
            if msg.error:
                self.keyframes.failed += 1
                log.warning("keyframe %d: keyframe_vl failed (%s); propagating on", k, msg.error)
            elif self._mask_tracker is not None:
                if self._mask_tracker.apply_masks(k, Masks(msg.masks, msg.boxes, msg.scores)):
                    self.awaiting_features[k] = now
                    self.keyframes.masks(k, now)
                else:
                    self.keyframes.stale += 1
        finally:
            self._apply_early(k)
            self._release()
            self._maybe_end(now)
            self._refresh()

    def _on_features(self, msg: MaskFeatures) -> None:
        try:
            if msg.frame_index in self.pending:
                self.early[msg.frame_index] = msg  # the masks are still on their way
            else:
                self._apply_features(msg)
        finally:
            self._maybe_end(self.clock())
            self._refresh()

    def _apply_early(self, k: int) -> None:
        early = self.early.pop(k, None)
        if early is not None:
            self._apply_features(early)

    def _apply_features(self, msg: MaskFeatures) -> None:
        k = msg.frame_index
        self.awaiting_features.pop(k, None)
        feats: TrackFeatures | None = None
        if msg.error is not None:
            self.keyframes.failed += 1
            log.warning("keyframe %d: no CLIP features (%s)", k, msg.error)
        elif self._mask_tracker is not None:
            self._mask_tracker.apply_features(k, msg.features)
            self.keyframes.features(k, self.clock())
            # At once, not with the next frame: after the last keyframe there is none.
            feats = self.core.take_track_features(k)
        if msg.view is not None:
            # The keyframe's view goes to fusion with frame k's message even when no track
            # changed (fusion places it by frame_index), on the same numbered, resent path.
            if feats is None:
                feats = TrackFeatures(frame_index=k, tracks=[], view=msg.view)
            else:
                feats = feats.model_copy(update={"view": msg.view})
        if feats is not None:
            self._send_features(feats)

    def _expire(self, now: float) -> None:
        for k, t in list(self.pending.items()):
            if now - t > self.timeout_s:
                del self.pending[k]
                self.keyframes.timed_out += 1
                log.warning("keyframe %d: no masks after %.1f s (is keyframe_vl running?); propagating on", k, self.timeout_s)
                # features without their masks: the core keeps them for masks that come late
                self._apply_early(k)

    # ---------------------------------------------------------------- end of sequence

    def _on_end(self, msg: EndOfSequence) -> None:
        self._end, self._end_at = msg, self.clock()
        self.book.progress(expected=msg.frames_published)
        self._maybe_end(self._end_at)
        self._refresh()

    def _maybe_end(self, now: float) -> None:
        """Pass the end of the sequence on once its last frame is out and no keyframe still
        waits for masks or CLIP features (each waits at most ``keyframe_timeout_s``); a
        live stream's last frames may never come (dropped), so give them that long too."""
        if self._end is None:
            return
        for k, t in list(self.awaiting_features.items()):
            if now - t > self.timeout_s:
                del self.awaiting_features[k]
                log.warning("keyframe %d: no CLIP features after %.1f s; ending without them", k, self.timeout_s)
        self._expire(now)
        self._release()
        caught_up = self._last_handled >= self._end.last_frame_index or now - self._end_at > self.timeout_s
        if not caught_up or self.pending or self.awaiting_features or self._open is not None or self.held or self.queued("frames"):
            return
        end = self._end.model_copy(update={"last_frame_index": self._last_index, "track_features_published": self._serial})
        # finished before the end is out: whoever acts on tracks/end must read a finished status
        self.book.set_state("finished")
        self._sent_end = end
        self._end = None
        self.ends.put(end)
        log.info("sequence ended: %d frames tracked, last %d, %d feature messages", self.frames, self._last_index, self._serial)

    # ---------------------------------------------------------------- time, status

    def tick(self, now: float) -> None:
        """Expire keyframes whose masks are overdue (releasing what waits for them) and pass
        the end of the sequence on when it is due."""
        with self.lock:
            with self.recovering("tick"):
                self._expire(now)
                self._release()
                self._maybe_end(now)
                if self.unacked.due(now):
                    log.warning("fusion has not acknowledged frames for %.1f s: sending again the %d messages it has not", self.unacked.resend_after_s, len(self.unacked))
                    self._resend(now)
            self._refresh()

    def _refresh(self) -> None:
        """Figures as plain values, taken under the lock (the reporter reads them from its own thread)."""
        book = self.book
        book.progress(done=self.frames)
        book.figure("frames", self.frames)
        book.figure("timeouts", self.keyframes.timed_out)
        book.figure("pending_keyframes", len(self.pending))
        book.figure("keyframes", self.keyframes.as_dict())
        book.figure("held", len(self.held) + (self._open is not None))
        book.figure("unacked", self.unacked.as_dict())
