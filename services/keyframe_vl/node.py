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
import time

from services.keyframe_vl.core import KeyframeVLCore
from services.keyframe_vl.session import ClipJob, KeyframeVLSession
from shared.config.root import TrackGraphConfig
from shared.runtime.status import StatusBook
from shared.topics import Topics
from shared.transport import ZenohBus

log = logging.getLogger(__name__)

CLIP_QUEUE = 8
"""Keyframes whose masks are out and whose CLIP features wait for the CLIP thread."""


class KeyframeVLNode:
    """Wires a :class:`KeyframeVLCore` to Zenoh; ``close()`` undeclares everything.

    The node is alive (liveliness token, status ``running``) only once its models are loaded
    and their text path has run once (:meth:`start`): ``vl/embed`` is declared then too, so a
    query service's warm-up, and the first novel text after it, never wait for a model load.
    With ``start=False`` the caller calls :meth:`start` itself, after it has begun publishing
    ``book``'s reports (``trackgraph serve``: state ``starting`` while the models load).
    """

    def __init__(self, cfg: TrackGraphConfig, core: KeyframeVLCore | None = None, session=None, *, start: bool = True) -> None:
        self.cfg = cfg
        self.core = core
        self.bus = ZenohBus(session, cfg.robot_id, cfg.transport.codec) if session is not None else ZenohBus.open(cfg.transport, cfg.robot_id)
        self.book = StatusBook("keyframe_vl")
        """State ``starting`` until :meth:`start` is done; the session counts in it after."""
        self._clip_jobs: queue.Queue[ClipJob] = queue.Queue(maxsize=CLIP_QUEUE)
        self._stop = threading.Event()
        self.session: KeyframeVLSession | None = None
        self.token = None
        self._clip_thread: threading.Thread | None = None
        self._closed = False
        if start:
            try:
                self.start()
            except BaseException:
                self.close()
                raise

    def start(self) -> None:
        """Load the models (unless a core was given), warm the text path up, then serve and
        declare the node alive. Raises what the models' loading raises."""
        from services.keyframe_vl.build import build_keyframe_vl

        t0 = time.monotonic()
        core = self.core or build_keyframe_vl(self.cfg)
        warm = getattr(core, "warm_up", None)  # a stand-in core may have none
        if warm is not None:
            warm()
        self.core = core
        self.book.figure("startup_s", round(time.monotonic() - t0, 3))
        self.session = KeyframeVLSession(self.bus, core, defer_clip=self._defer_clip, book=self.book)
        self.requests = self.session.requests
        self.embed = self.session.embed
        self._clip_thread = threading.Thread(target=self._clip_loop, name="keyframe_vl:clip", daemon=True)
        self._clip_thread.start()
        self.token = self.bus.declare_alive(Topics(self.cfg.robot_id).alive("keyframe_vl"))
        self.book.set_state("running")
        log.info("keyframe_vl ready in %.1f s (models loaded, text path warm)", time.monotonic() - t0)

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
        return self.session.processed if self.session is not None else 0

    @property
    def failed(self) -> int:
        return self.session.failed if self.session is not None else 0

    def stats(self) -> dict:
        if self.session is None:
            return {"state": self.book.state}
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
        if self.session is not None:
            self.session.close()
        if self._clip_thread is not None:
            self._clip_thread.join(timeout=10)
        if self.token is not None:
            self.token.undeclare()
        if not keep_bus:
            self.bus.close()


def build(cfg, *, out=None, resume: bool = False) -> KeyframeVLNode:
    """``trackgraph serve keyframe_vl``: models load in start(), once the status reports (state
    ``starting``) go out."""
    return KeyframeVLNode(cfg, start=False)
