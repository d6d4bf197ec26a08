"""tracker node: ``frames`` in; ``keyframe/request`` out and ``keyframe/masks`` /
``keyframe/features`` back; ``tracks/frame`` and ``tracks/features`` out.

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

from services.keyframe_vl.types import Masks
from shared.config.root import TrackGraphConfig
from shared.messages.base import Envelope
from shared.messages.frames import Frame, TrackedFrame
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures, TrackFeatures
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
        self._inbox: queue.Queue = queue.Queue(maxsize=64)
        self._masks: dict[int, KeyframeMasks] = {}
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self.pending: dict[int, float] = {}
        """Keyframes asked for and not answered: frame index -> time asked."""
        self.timeouts = 0
        self.frames = 0
        self.errors = 0
        self._worker = threading.Thread(target=self._run, name="tracker:worker", daemon=True)
        self._worker.start()
        live = cfg.source.mode == "live"
        self.subs = [
            TypedSubscriber(self.session, self.topics.frames, Frame, codec=codec, policy="latest" if live else "fifo", capacity=2 if live else 8, callback=self._inbox.put),
            TypedSubscriber(self.session, self.topics.keyframe_masks, KeyframeMasks, codec=codec, capacity=16, callback=self._on_masks),
            TypedSubscriber(self.session, self.topics.keyframe_features, MaskFeatures, codec=codec, capacity=16, callback=self._inbox.put),
        ]
        self.token = declare_alive(self.session, self.topics.alive("tracker"))

    def _on_masks(self, env: Envelope[KeyframeMasks]) -> None:
        # Masks bypass the frame queue so a keyframe the worker is holding can be released.
        with self._cv:
            self._masks[env.body.frame_index] = env.body
            self._cv.notify_all()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                env = self._inbox.get(timeout=0.1)
            except queue.Empty:
                self._apply_arrived_masks()
                continue
            try:
                if isinstance(env.body, Frame):
                    self._on_frame(env.body)
                else:
                    self._apply_arrived_masks()
                    self._on_features(env.body)
            except Exception:  # noqa: BLE001 - one bad message must not stop tracking
                self.errors += 1
                log.exception("tracker failed on a %s", type(env.body).__name__)

    def _on_frame(self, frame: Frame) -> None:
        self._apply_arrived_masks()
        req = self.core.begin_frame(frame)
        if req is not None:
            self.requests.put(req)
            self.pending[frame.frame_index] = time.monotonic()
            if self.cfg.tracker.wait_for_masks:
                self._wait_masks(frame.frame_index)
        self._expire()
        tracked = self.core.end_frame()
        feats = self.core.take_track_features(frame.frame_index)
        if feats is not None:
            self.features.put(feats)
        self.tracked.put(tracked)
        self.frames += 1

    def _wait_masks(self, frame_index: int) -> None:
        deadline = time.monotonic() + self.cfg.tracker.keyframe_timeout_s
        with self._cv:
            while frame_index not in self._masks and not self._stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cv.wait(left)
        self._apply_arrived_masks()

    def _apply_arrived_masks(self) -> None:
        with self._cv:
            arrived = sorted(self._masks.items())
            self._masks.clear()
        for k, msg in arrived:
            self.pending.pop(k, None)
            if msg.error:
                log.warning("keyframe %d: keyframe_vl failed (%s); propagating on", k, msg.error)
                continue
            if hasattr(self.core, "apply_masks"):
                self.core.apply_masks(k, Masks(msg.masks, msg.boxes, msg.scores))

    def _on_features(self, msg: MaskFeatures) -> None:
        if msg.error is None and hasattr(self.core, "apply_features"):
            self.core.apply_features(msg.frame_index, msg.features)

    def _expire(self) -> None:
        now = time.monotonic()
        for k, t in list(self.pending.items()):
            if now - t > self.cfg.tracker.keyframe_timeout_s:
                del self.pending[k]
                self.timeouts += 1
                log.warning("keyframe %d: no masks after %.1f s (is keyframe_vl running?); propagating on", k, self.cfg.tracker.keyframe_timeout_s)

    def stats(self) -> dict:
        return {"frames": self.frames, "errors": self.errors, "timeouts": self.timeouts, "pending_keyframes": len(self.pending), "frames_in": self.subs[0].stats.as_dict()}

    def close(self) -> None:
        for s in self.subs:
            s.close()
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        self._worker.join(timeout=30)
        self.token.undeclare()
        for p in (self.requests, self.tracked, self.features):
            p.close()
        if self._own_session:
            self.session.close()
