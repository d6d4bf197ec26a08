"""fusion node: a :class:`~services.fusion.session.FusionSession` on Zenoh, keeping its map
in the folder ``out`` (snapshots, resume, the final export).

The session holds fusion's coordination (duplicates, acks, end of sequence with its grace,
snapshots); this adapter opens the bus, runs the worker that hands the session its inputs in
arrival order, ticks the session and announces the service.
"""

from __future__ import annotations

import logging
from pathlib import Path

from services.fusion.core import FusionCore
from services.fusion.session import FusionSession
from shared.config.base import save_resolved
from shared.config.root import TrackGraphConfig
from shared.graph.store import MapStore
from shared.runtime.session import Inbox, Ticker
from shared.topics import Topics
from shared.transport import ZenohBus

log = logging.getLogger(__name__)

__all__ = ["FusionNode"]

TICK_S = 0.2
"""How often the end of the sequence and the snapshot interval are looked at."""


class FusionNode:
    """Wires a :class:`FusionCore` to Zenoh and to its map folder ``out``; ``session`` may be
    an open zenoh session to share (not closed here)."""

    def __init__(self, cfg: TrackGraphConfig, out: Path, *, resume: bool = False, session=None) -> None:
        self.cfg = cfg
        self.out = Path(out)
        self.store = MapStore(self.out / "graph", robot_id=cfg.robot_id)
        core = FusionCore(cfg.fusion, device=cfg.tracker.device)
        self.out.mkdir(parents=True, exist_ok=True)
        save_resolved(cfg, self.out / "config.yaml")  # what built the map, e.g. for offline queries
        self.bus = ZenohBus(session, cfg.robot_id, cfg.transport.codec) if session is not None else ZenohBus.open(cfg.transport, cfg.robot_id)
        self.inbox = Inbox(256, name="fusion:worker")
        try:
            self.session = FusionSession(self.bus, cfg, core, store=self.store, out=self.out, resume=resume, inbox=self.inbox)
        except BaseException:
            self.inbox.stop()
            self.bus.close()
            raise
        self.core = core
        self.book = self.session.book
        self.finished = self.session.finished
        self.snapshots = self.session.snapshots
        self.subs = [self.session.inputs[n] for n in ("tracks_frame", "tracks_features", "tracks_end")]
        self._ticker = Ticker(self.session.tick, TICK_S, name="fusion:tick")
        self.token = self.bus.declare_alive(Topics(cfg.robot_id).alive("fusion"))
        self.book.set_state("running")
        self._closed = False

    @property
    def errors(self) -> int:
        return self.book.errors

    @property
    def frames(self) -> int:
        return self.session.frames

    @property
    def duplicates(self) -> int:
        return self.session.duplicates

    @property
    def resumed_from(self) -> str | None:
        return self.session.resumed_from

    def save(self, export: bool = False) -> None:
        self.session.save(export=export)

    def delivery(self) -> dict:
        return self.session.delivery()

    def stats(self) -> dict:
        s = self.session
        return {"frames": s.frames, "frames_in_map": self.core.frames, "duplicates": s.duplicates, "errors": self.book.errors,
                "input_dropped": sum(sub.stats.dropped for sub in self.subs), "input_rejected": sum(sub.stats.rejected for sub in self.subs),
                "graph_seq": self.core.graph.graph_seq, "pending": s.queued("tracks_frame", "tracks_features", "tracks_end")}  # fmt: skip

    def close(self, keep_bus: bool = False, save: bool = True) -> None:
        if self._closed:
            return
        self._closed = True
        self._ticker.stop()
        self.session.close(save=save)
        self.token.undeclare()
        if not keep_bus:
            self.bus.close()


def build(cfg, *, out=None, resume: bool = False) -> FusionNode:
    """``trackgraph serve fusion --out MAP_DIR [--resume]``."""
    return FusionNode(cfg, out, resume=resume)
