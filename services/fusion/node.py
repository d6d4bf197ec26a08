"""fusion node: ``tracks/frame`` and ``tracks/features`` in; ``graph/delta`` out; the
``graph/snapshot`` queryable; periodic and final snapshots on disk; resume on start.

Both inputs go through one ordered queue and one worker, so the core sees frames and
feature updates in the order they arrived, as the in-process pipeline feeds them.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path

from services.fusion.core import FusionCore
from services.fusion.store import MapStore, StoreError
from shared.config.root import TrackGraphConfig
from shared.messages.base import Envelope
from shared.messages.frames import EndOfSequence, TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, SnapshotRequest
from shared.messages.keyframes import TrackFeatures
from shared.topics import Topics
from shared.transport import (
    TypedPublisher,
    TypedQueryable,
    TypedSubscriber,
    declare_alive,
    open_session,
)

log = logging.getLogger(__name__)


class FusionNode:
    """Wires a :class:`FusionCore` to Zenoh and to its map folder ``out``."""

    def __init__(self, cfg: TrackGraphConfig, out: Path, *, resume: bool = False, session=None) -> None:
        self.cfg = cfg
        self.out = Path(out)
        self.core = FusionCore(cfg.fusion, device=cfg.tracker.device)
        self.store = MapStore(self.out / "graph", robot_id=cfg.robot_id)
        self.resumed_from: str | None = None
        if resume and self.store.latest_name() is not None:
            state = self.store.load()
            self.core.load_state_dict(state.extra, state.snapshot)
            self.resumed_from = str(state.path)
            log.info("resumed from %s at frame %d (graph %d)", state.path, self.core.last_frame_index, self.core.graph.graph_seq)
        self.topics = Topics(cfg.robot_id)
        self._own_session = session is None
        self.session = session or open_session(cfg.transport)
        codec = cfg.transport.codec
        self._inbox: queue.Queue = queue.Queue(maxsize=256)
        self._lock = threading.Lock()
        """Held while the core changes, so a snapshot query never sees a half-applied frame."""
        self._stop = threading.Event()
        self.finished = threading.Event()
        self.end_index: int | None = None
        self.frames = 0
        self.errors = 0
        self._last_save = time.monotonic()
        self.deltas = TypedPublisher(self.session, self.topics.graph_delta, GraphDelta, robot_id=cfg.robot_id, codec=codec)
        if self.core.graph.graph_seq:
            self.deltas.seq = self.core.graph.graph_seq
        self.snapshots = TypedQueryable(
            self.session, self.topics.graph_snapshot, SnapshotRequest, GraphSnapshot, self._on_snapshot,
            robot_id=cfg.robot_id, codec=codec, workers=1,
        )  # fmt: skip
        self._worker = threading.Thread(target=self._run, name="fusion:worker", daemon=True)
        self._worker.start()
        self.subs = [
            TypedSubscriber(self.session, self.topics.tracks_frame, TrackedFrame, codec=codec, capacity=16, callback=self._inbox.put),
            TypedSubscriber(self.session, self.topics.tracks_features, TrackFeatures, codec=codec, capacity=64, callback=self._inbox.put),
            TypedSubscriber(self.session, self.topics.end_of_sequence, EndOfSequence, codec=codec, capacity=4, callback=self._inbox.put),
        ]
        self.token = declare_alive(self.session, self.topics.alive("fusion"))

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                env: Envelope = self._inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                with self._lock:
                    self._handle(env.body)
            except Exception:  # noqa: BLE001 - one bad message must not stop the map
                self.errors += 1
                log.exception("fusion failed on a %s", type(env.body).__name__)

    def _handle(self, body) -> None:
        if isinstance(body, TrackFeatures):
            self.core.add_track_features(body)
            return
        if isinstance(body, EndOfSequence):
            self.end_index = body.last_frame_index
        elif body.frame.frame_index <= self.core.last_frame_index and self.resumed_from:
            return  # already in the resumed map
        else:
            delta = self.core.add_frame(body)
            self.frames += 1
            if delta is not None:
                self.deltas.put(delta)
            if time.monotonic() - self._last_save >= self.cfg.fusion.snapshot_interval_s:
                self.save()
        if self.end_index is not None and self.core.last_frame_index >= self.end_index and not self.finished.is_set():
            self.deltas.put(self.core.finish())
            self.save(export=True)
            self.finished.set()
            log.info("sequence finished at frame %d: %d segments", self.end_index, len(self.core.segments.segments))

    def save(self, export: bool = False) -> None:
        """A snapshot on disk (atomic, checksummed); with ``export`` also the mesh and the
        OpenLex3D files of ``trackgraph map``."""
        from services.mapping import export_map

        try:
            self.store.save(self.core.snapshot(with_mesh=True), extra_state=self.core.state_dict())
            if export:
                export_map(self.out, self.core)
        except (StoreError, OSError) as exc:
            log.error("snapshot not written: %s", exc)
        self._last_save = time.monotonic()

    def _on_snapshot(self, env: Envelope[SnapshotRequest]) -> GraphSnapshot:
        with self._lock:
            return self.core.snapshot(with_mesh=env.body.with_mesh)

    def stats(self) -> dict:
        return {"frames": self.frames, "errors": self.errors, "graph_seq": self.core.graph.graph_seq, "pending": self._inbox.qsize()}

    def close(self, save: bool = True) -> None:
        for s in self.subs:
            s.close()
        self._stop.set()
        self._worker.join(timeout=30)
        if save and self.frames:
            with self._lock:
                self.save()
        self.snapshots.close()
        self.token.undeclare()
        self.deltas.close()
        if self._own_session:
            self.session.close()
