"""tracker node: ``frames`` in; ``keyframe/request`` out and ``keyframe/masks`` /
``keyframe/features`` back; ``tracks/frame`` and ``tracks/features`` out; the source's
``frames/end`` passed on as ``tracks/end`` once everything for the sequence is out, the CLIP
features of the last keyframes included (they arrive after its last frame).

Frames, masks and features go through one ordered queue and one worker, so the core sees
them in arrival order. Masks may arrive late (a remote GPU): the core corrects at that
keyframe and re-propagates. If keyframe_vl is down, requests time out, are counted, and the
tracker keeps propagating; it recovers when masks come back.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

from services.tracker.pace import KeyframeLedger
from shared.config.root import TrackGraphConfig
from shared.messages.base import Envelope
from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures, TrackFeatures
from shared.perception import Masks
from shared.topics import Topics
from shared.transport import TypedPublisher, TypedSubscriber, declare_alive, open_session

log = logging.getLogger(__name__)


class TrackerNode:
    """Wires a tracker core to Zenoh."""

    def __init__(self, cfg: TrackGraphConfig, tracker=None, session=None) -> None:
        from services.mapping import build_tracker

        self.cfg = cfg
        self.core = tracker if tracker is not None else build_tracker(cfg, with_keyframes=False)[0]
        self.topics = Topics(cfg.robot_id)
        self._own_session = session is None
        self.session = session or open_session(cfg.transport)
        codec = cfg.transport.codec
        rid = cfg.robot_id
        self.requests = TypedPublisher(self.session, self.topics.keyframe_request, KeyframeRequest, robot_id=rid, codec=codec)
        self.tracked = TypedPublisher(self.session, self.topics.tracks_frame, TrackedFrame, robot_id=rid, codec=codec)
        self.features = TypedPublisher(self.session, self.topics.tracks_features, TrackFeatures, robot_id=rid, codec=codec)
        self.ends = TypedPublisher(self.session, self.topics.tracks_end, EndOfSequence, robot_id=rid, codec=codec)
        self.acks = TypedPublisher(self.session, self.topics.frame_ack, FrameAck, robot_id=rid, codec=codec)
        live = cfg.source.mode == "live"
        # Live, a frame waits behind at most one other here and the subscriber's newest-two
        # ring drops the rest, counted: a deeper queue would let the tracker fall seconds
        # behind a live camera before it dropped anything.
        self._inbox: queue.Queue = queue.Queue(maxsize=1 if live else 64)
        self._masks: dict[int, KeyframeMasks] = {}
        self._features: list[MaskFeatures] = []
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self.pending: dict[int, float] = {}
        """Keyframes asked for and not answered: frame index -> time asked."""
        self.awaiting_features: dict[int, float] = {}
        """Keyframes whose masks are in and CLIP features not yet: frame index -> since when."""
        self._end: EndOfSequence | None = None
        self._end_at = 0.0
        self._last_index = -1
        self.keyframes = KeyframeLedger()
        self.frames = 0
        self.errors = 0
        self._worker = threading.Thread(target=self._run, name="tracker:worker", daemon=True)
        self._worker.start()
        self.subs = [
            # Lossless: the source is paced to source.window_frames ahead; room for more.
            TypedSubscriber(self.session, self.topics.frames, Frame, codec=codec, policy="latest" if live else "fifo",
                            capacity=2 if live else 4 * cfg.source.window_frames, callback=self._inbox.put),
            TypedSubscriber(self.session, self.topics.keyframe_masks, KeyframeMasks, codec=codec, capacity=16, callback=self._on_masks),
            TypedSubscriber(self.session, self.topics.keyframe_features, MaskFeatures, codec=codec, capacity=16, callback=self._on_features_msg),
            TypedSubscriber(self.session, self.topics.end_of_sequence, EndOfSequence, codec=codec, capacity=4, callback=self._inbox.put),
        ]
        self.token = declare_alive(self.session, self.topics.alive("tracker"))

    def _on_masks(self, env: Envelope[KeyframeMasks]) -> None:
        # Masks bypass the frame queue so a keyframe the worker is holding can be released.
        with self._cv:
            self._masks[env.body.frame_index] = env.body
            self._cv.notify_all()

    def _on_features_msg(self, env: Envelope[MaskFeatures]) -> None:
        # CLIP features bypass it too: in lossless replay the frame queue runs far ahead, and
        # behind it the features would reach the core after their keyframe left its history.
        with self._cv:
            self._features.append(env.body)
            self._cv.notify_all()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                env = self._inbox.get(timeout=0.1)
            except queue.Empty:
                self._apply_arrived()
                self._maybe_end()
                continue
            try:
                if isinstance(env.body, Frame):
                    self._on_frame(env.body)
                else:
                    self._end, self._end_at = env.body, time.monotonic()
                self._apply_arrived()
                self._maybe_end()
            except Exception:  # noqa: BLE001 - one bad message must not stop tracking
                self.errors += 1
                log.exception("tracker failed on a %s", type(env.body).__name__)
            finally:
                if isinstance(env.body, Frame):
                    # tracked or failed: a lossless source waits for it
                    self.acks.put(FrameAck(frame_index=env.body.frame_index, service="tracker"))

    def _on_frame(self, frame: Frame) -> None:
        self._apply_arrived()
        req = self.core.begin_frame(frame)
        if req is not None:
            self.requests.put(req)
            self.pending[frame.frame_index] = time.monotonic()
            self.keyframes.request(frame.frame_index, self.pending[frame.frame_index])
            if self.cfg.tracker.wait_for_masks:
                self._wait_masks(frame.frame_index)
        self._expire()
        tracked = self.core.end_frame()
        feats = self.core.take_track_features(frame.frame_index)
        if feats is not None:
            self.features.put(feats)
        self.tracked.put(tracked)
        self.frames += 1
        self._last_index = frame.frame_index

    def _wait_masks(self, frame_index: int) -> None:
        deadline = time.monotonic() + self.cfg.tracker.keyframe_timeout_s
        with self._cv:
            while frame_index not in self._masks and not self._stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cv.wait(left)
        self._apply_arrived()

    def _apply_arrived(self) -> None:
        """Masks, then CLIP features, that came since the last call (features of a keyframe
        always follow its masks)."""
        with self._cv:
            arrived = sorted(self._masks.items())
            self._masks.clear()
            features, self._features = self._features, []
        for k, msg in arrived:
            self.pending.pop(k, None)
            if msg.error:
                self.keyframes.failed += 1
                log.warning("keyframe %d: keyframe_vl failed (%s); propagating on", k, msg.error)
                continue
            if hasattr(self.core, "apply_masks") and self.core.apply_masks(k, Masks(msg.masks, msg.boxes, msg.scores)):
                self.awaiting_features[k] = time.monotonic()
                self.keyframes.masks(k, self.awaiting_features[k])
            elif hasattr(self.core, "apply_masks"):
                self.keyframes.stale += 1
        for f in features:
            self._on_features(f)

    def _on_features(self, msg: MaskFeatures) -> None:
        self.awaiting_features.pop(msg.frame_index, None)
        if msg.error is not None:
            self.keyframes.failed += 1
            log.warning("keyframe %d: no CLIP features (%s)", msg.frame_index, msg.error)
        elif hasattr(self.core, "apply_features"):
            self.core.apply_features(msg.frame_index, msg.features)
            self.keyframes.features(msg.frame_index, time.monotonic())
            # At once, not with the next frame: after the last keyframe there is none.
            feats = self.core.take_track_features(msg.frame_index)
            if feats is not None:
                self.features.put(feats)

    def _maybe_end(self) -> None:
        """Pass the end of the sequence on once its last frame is out and no keyframe still
        waits for masks or CLIP features (each waits at most ``keyframe_timeout_s``); a
        live stream's last frames may never come (dropped), so give them that long too."""
        if self._end is None:
            return
        now, timeout = time.monotonic(), self.cfg.tracker.keyframe_timeout_s
        for k, t in list(self.awaiting_features.items()):
            if now - t > timeout:
                del self.awaiting_features[k]
                log.warning("keyframe %d: no CLIP features after %.1f s; ending without them", k, timeout)
        self._expire()
        caught_up = self._last_index >= self._end.last_frame_index or now - self._end_at > timeout
        if not caught_up or self.pending or self.awaiting_features or not self._inbox.empty():
            return
        end = self._end.model_copy(update={"last_frame_index": self._last_index, "track_features_published": self.features.seq})
        self.ends.put(end)
        log.info("sequence ended: %d frames tracked, last %d, %d feature messages", self.frames, self._last_index, self.features.seq)
        self._end = None

    def _expire(self) -> None:
        now = time.monotonic()
        for k, t in list(self.pending.items()):
            if now - t > self.cfg.tracker.keyframe_timeout_s:
                del self.pending[k]
                self.keyframes.timed_out += 1
                log.warning("keyframe %d: no masks after %.1f s (is keyframe_vl running?); propagating on", k, self.cfg.tracker.keyframe_timeout_s)

    def stats(self) -> dict:
        return {
            "frames": self.frames, "errors": self.errors, "timeouts": self.keyframes.timed_out, "pending_keyframes": len(self.pending),
            "frames_in": self.subs[0].stats.as_dict(), "keyframes": self.keyframes.as_dict(),
        }  # fmt: skip

    def close(self) -> None:
        for s in self.subs:
            s.close()
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        self._worker.join(timeout=30)
        self.token.undeclare()
        for p in (self.requests, self.tracked, self.features, self.ends, self.acks):
            p.close()
        if self._own_session:
            self.session.close()
