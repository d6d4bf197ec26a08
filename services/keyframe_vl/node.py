"""keyframe_vl node: a :class:`~services.keyframe_vl.session.KeyframeVLSession` on Zenoh.

CLIP runs on this node's own thread behind a bounded queue, so the next keyframe's masks
never wait for the previous keyframe's features; when CLIP falls 8 keyframes behind, the
request subscription waits for room (its queue then drops, counted) rather than letting
the backlog grow.
"""

from __future__ import annotations

import logging
import queue
import threading

from services.keyframe_vl.core import KeyframeVLCore
from services.keyframe_vl.session import ClipJob, KeyframeVLSession
from shared.config.root import TrackGraphConfig
from shared.topics import Topics
from shared.transport import ZenohBus

log = logging.getLogger(__name__)

CLIP_QUEUE = 8
"""Keyframes whose masks are out and whose CLIP features wait for the CLIP thread."""


class KeyframeVLNode:
    """Wires a :class:`KeyframeVLCore` to Zenoh; ``close()`` undeclares everything."""

    def __init__(self, cfg: TrackGraphConfig, core: KeyframeVLCore | None = None, session=None) -> None:
        from services.keyframe_vl.build import build_keyframe_vl

        self.cfg = cfg
        self.core = core or build_keyframe_vl(cfg)
        self.bus = ZenohBus(session, cfg.robot_id, cfg.transport.codec) if session is not None else ZenohBus.open(cfg.transport, cfg.robot_id)
        self._clip_jobs: queue.Queue[ClipJob] = queue.Queue(maxsize=CLIP_QUEUE)
        self._stop = threading.Event()
        self.session = KeyframeVLSession(self.bus, self.core, defer_clip=self._defer_clip)
        self.book = self.session.book
        self.requests = self.session.requests
        self.embed = self.session.embed
        self._clip_thread = threading.Thread(target=self._clip_loop, name="keyframe_vl:clip", daemon=True)
        self._clip_thread.start()
        self.token = self.bus.declare_alive(Topics(cfg.robot_id).alive("keyframe_vl"))
        self.book.set_state("running")
        self._closed = False

    def _defer_clip(self, job: ClipJob) -> None:
        # On the request subscription's thread: waiting here is the backpressure.
        while not self._stop.is_set():
            try:
                self._clip_jobs.put(job, timeout=0.2)
                return
            except queue.Full:
                continue

    def _clip_loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self._clip_jobs.get(timeout=0.2)
            except queue.Empty:
                continue
            self.session.run_clip(job)

    @property
    def processed(self) -> int:
        return self.session.processed

    @property
    def failed(self) -> int:
        return self.session.failed

    def stats(self) -> dict:
        return {
            "processed": self.session.processed,
            "failed": self.session.failed,
            "requests": self.requests.stats.as_dict(),
            "embed": self.embed.stats.as_dict(),
        }

    def close(self, keep_bus: bool = False) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self.session.close()
        self._clip_thread.join(timeout=10)
        self.token.undeclare()
        if not keep_bus:
            self.bus.close()
