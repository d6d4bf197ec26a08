"""tracker node: a :class:`~services.tracker.session.TrackerSession` on Zenoh.

The session holds the tracker's coordination (keyframe life, ``wait_for_masks``, end of
sequence, acks); the node adapter opens the bus, runs the worker that hands the session its
frames in order (masks and CLIP features bypass it, on their subscriptions' threads), ticks
the session for its time-outs and announces the service with a liveliness token.
"""

from __future__ import annotations

from services.tracker.session import TrackerSession
from shared.config.root import TrackGraphConfig
from shared.runtime.adapter import SessionNode, open_bus, session_attr

TICK_S = 0.1
"""How often keyframe time-outs and the end of the sequence are looked at."""


class TrackerNode(SessionNode):
    """Wires a tracker core to Zenoh; ``session`` may be an open zenoh session to share (not closed here)."""

    keyframes = session_attr("keyframes")

    def __init__(self, cfg: TrackGraphConfig, tracker=None, session=None) -> None:
        from services.tracker.build import build_tracker

        self.cfg = cfg
        self.core = tracker if tracker is not None else build_tracker(cfg)
        super().__init__(
            open_bus(cfg, session), lambda bus: TrackerSession(bus, cfg, self.core, inbox=self.inbox), name="tracker", tick_s=TICK_S,
            # Live, a frame waits behind at most one other here; lossless, the source's window and more.
            inbox=1 if cfg.source.mode == "live" else 64, alive="tracker",
        )  # fmt: skip
        self.subs = [self.session.inputs[n] for n in ("frames", "keyframe_masks", "keyframe_features", "end_of_sequence")]

    def stats(self) -> dict:
        s = self.session
        with s.lock:
            return {
                "frames": s.frames, "errors": self.book.errors, "timeouts": s.keyframes.timed_out, "pending_keyframes": len(s.pending),
                "frames_in": self.book.counts("frames"), "keyframes": s.keyframes.as_dict(),
            }  # fmt: skip


def build(cfg, *, out=None, resume: bool = False) -> TrackerNode:
    """``trackgraph serve tracker`` (services registry, services/tracker/__init__.py)."""
    return TrackerNode(cfg)
