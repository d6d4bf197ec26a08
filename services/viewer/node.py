"""viewer node: the :class:`~services.viewer.session.ViewerSession` over a Zenoh bus.

The session keeps the replica and writes the recording; this adapter opens the bus and
ticks the session on a thread of its own, where snapshot requests (a late join, a gap) and
their retries with backoff happen, off the subscribers' threads.
"""

from __future__ import annotations

from pathlib import Path

from services.viewer.session import ViewerSession
from shared.config.root import TrackGraphConfig
from shared.runtime.adapter import SessionNode, open_bus

TICK_S = 0.05
"""How often the session is ticked."""


class ViewerNode(SessionNode):
    """Records the live map to ``out_rrd``; open it with ``rerun out.rrd``."""

    def __init__(self, cfg: TrackGraphConfig, out_rrd: Path, *, session=None, frame_every: int = 10) -> None:
        self.cfg = cfg
        super().__init__(
            open_bus(cfg, session), lambda b: ViewerSession(cfg, b, out_rrd, frame_every=frame_every),
            name="viewer", tick_s=TICK_S, stop_timeout_s=cfg.transport.query_timeout_s + 1,
        )  # fmt: skip

    @property
    def replica(self):
        return self.session.sync.replica

    @property
    def subs(self) -> list:
        """The delta and frame subscribers (their link counters, for fault tests)."""
        return [self.session.deltas, self.session.frames]

    def stats(self) -> dict:
        report = self.book.report()
        return {**report.figures, "errors": report.errors, "links": {s.key: s.stats.as_dict() for s in self.subs}}

    def __enter__(self) -> ViewerNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def build(cfg, *, out=None, resume: bool = False) -> ViewerNode:
    """``trackgraph serve viewer --out FILE.rrd``."""
    return ViewerNode(cfg, out)
