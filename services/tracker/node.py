"""tracker node: a :class:`~services.tracker.session.TrackerSession` on Zenoh.

The session holds the tracker's coordination (keyframe life, ``wait_for_masks``, end of
sequence, acks); this adapter opens the bus, runs the worker that hands the session its
frames in order (masks and CLIP features bypass it, on their subscriptions' threads), ticks
the session for its time-outs and announces the service with a liveliness token.
"""

from __future__ import annotations

import logging

from services.tracker.session import TrackerSession
from shared.config.root import TrackGraphConfig
from shared.runtime.session import Inbox, Ticker
from shared.topics import Topics
from shared.transport import ZenohBus

log = logging.getLogger(__name__)

TICK_S = 0.1
"""How often keyframe time-outs and the end of the sequence are looked at."""


class TrackerNode:
    """Wires a tracker core to Zenoh; ``session`` may be an open zenoh session to share (not closed here)."""

    def __init__(self, cfg: TrackGraphConfig, tracker=None, session=None) -> None:
        from services.tracker.build import build_tracker

        self.cfg = cfg
        self.core = tracker if tracker is not None else build_tracker(cfg)
        self.bus = ZenohBus(session, cfg.robot_id, cfg.transport.codec) if session is not None else ZenohBus.open(cfg.transport, cfg.robot_id)
        # Live, a frame waits behind at most one other here; lossless, the source's window and more.
        self.inbox = Inbox(1 if cfg.source.mode == "live" else 64, name="tracker:worker")
        self.session = TrackerSession(self.bus, cfg, self.core, inbox=self.inbox)
        self.book = self.session.book
        self.subs = [self.session.inputs[n] for n in ("frames", "keyframe_masks", "keyframe_features", "end_of_sequence")]
        self._ticker = Ticker(self.session.tick, TICK_S, name="tracker:tick")
        self.token = self.bus.declare_alive(Topics(cfg.robot_id).alive("tracker"))
        self.book.set_state("running")
        self._closed = False

    @property
    def keyframes(self):
        return self.session.keyframes

    @property
    def errors(self) -> int:
        return self.book.errors

    def stats(self) -> dict:
        s = self.session
        with s.lock:
            return {
                "frames": s.frames, "errors": self.book.errors, "timeouts": s.keyframes.timed_out, "pending_keyframes": len(s.pending),
                "frames_in": self.book.counts("frames"), "keyframes": s.keyframes.as_dict(),
            }  # fmt: skip

    def close(self, keep_bus: bool = False) -> None:
        if self._closed:
            return
        self._closed = True
        self.session.close()
        self._ticker.stop()
        self.token.undeclare()
        if not keep_bus:
            self.bus.close()


def build(cfg, *, out=None, resume: bool = False) -> TrackerNode:
    """``trackgraph serve tracker`` (services registry, services/tracker/__init__.py)."""
    return TrackerNode(cfg)
