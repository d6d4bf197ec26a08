"""fusion node: a :class:`~services.fusion.session.FusionSession` on Zenoh, keeping its map
in the folder ``out`` (snapshots, resume, the final export).

The session holds fusion's coordination (duplicates, acks, end of sequence with its grace,
snapshots); the node adapter opens the bus, runs the worker that hands the session its inputs
in arrival order, ticks the session and announces the service.
"""

from __future__ import annotations

import logging
from pathlib import Path

from services.fusion.core import FusionCore
from services.fusion.session import FusionSession
from shared.config.base import save_resolved
from shared.config.root import TrackGraphConfig
from shared.graph.store import MapStore
from shared.runtime.adapter import SessionNode, open_bus, session_attr

log = logging.getLogger(__name__)

__all__ = ["FusionNode"]

TICK_S = 0.2
"""How often the end of the sequence and the snapshot interval are looked at."""


class FusionNode(SessionNode):
    """Wires a :class:`FusionCore` to Zenoh and to its map folder ``out``; ``session`` may be
    an open zenoh session to share (not closed here)."""

    finished = session_attr("finished")
    snapshots = session_attr("snapshots")
    frames = session_attr("frames")
    duplicates = session_attr("duplicates")
    resumed_from = session_attr("resumed_from")

    def __init__(self, cfg: TrackGraphConfig, out: Path, *, resume: bool = False, session=None) -> None:
        self.cfg = cfg
        self.out = Path(out)
        self.store = MapStore(self.out / "graph", robot_id=cfg.robot_id)
        self.core = FusionCore(cfg.fusion, device=cfg.tracker.device)
        self.out.mkdir(parents=True, exist_ok=True)
        save_resolved(cfg, self.out / "config.yaml")  # what built the map, e.g. for offline queries

        def make(bus) -> FusionSession:
            return FusionSession(bus, cfg, self.core, store=self.store, out=self.out, resume=resume, inbox=self.inbox)

        super().__init__(open_bus(cfg, session), make, name="fusion", tick_s=TICK_S, inbox=256, alive="fusion")
        self.subs = [self.session.inputs[n] for n in ("tracks_frame", "tracks_features", "tracks_end")]

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
        """Close as every node does; with ``save`` the session saves the map first."""
        super().close(keep_bus, save=save)


def build(cfg, *, out=None, resume: bool = False) -> FusionNode:
    """``trackgraph serve fusion --out MAP_DIR [--resume]``."""
    return FusionNode(cfg, out, resume=resume)
