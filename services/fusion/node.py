"""fusion node: ``tracks/frame`` and ``tracks/features`` in; ``graph/delta`` out; the
``graph/snapshot`` queryable; periodic and final snapshots on disk; resume on start. The
map is finished when the tracker's ``tracks/end`` has come and every frame and feature
message it announces is in (or ``END_GRACE_S`` after it, with a warning).

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
from shared.config.base import save_resolved
from shared.config.root import TrackGraphConfig
from shared.graph.store import MapStore, StoreError
from shared.messages.base import Envelope
from shared.messages.frames import EndOfSequence, FrameAck, TrackedFrame
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

END_GRACE_S = 15.0
"""After ``tracks/end``, how long fusion waits for announced messages still on their way."""


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
        self.out.mkdir(parents=True, exist_ok=True)
        save_resolved(cfg, self.out / "config.yaml")  # what built the map, e.g. for offline queries
        self.topics = Topics(cfg.robot_id)
        self._own_session = session is None
        self.session = session or open_session(cfg.transport)
        codec = cfg.transport.codec
        self._inbox: queue.Queue = queue.Queue(maxsize=256)
        self._lock = threading.Lock()
        """Held while the core changes, so a snapshot query never sees a half-applied frame."""
        self._stop = threading.Event()
        self.finished = threading.Event()
        self.end: EndOfSequence | None = None
        self._end_at = 0.0
        self.features_in = 0
        self.frames = 0
        """Frames this process fused (``core.frames`` counts those of the whole map)."""
        self.duplicates = 0
        self.errors = 0
        self._first_frame_at: float | None = None
        self._last_frame_at: float | None = None
        self._last_save = time.monotonic()
        self.deltas = TypedPublisher(self.session, self.topics.graph_delta, GraphDelta, robot_id=cfg.robot_id, codec=codec)
        self.acks = TypedPublisher(self.session, self.topics.frame_ack, FrameAck, robot_id=cfg.robot_id, codec=codec)
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
            TypedSubscriber(self.session, self.topics.tracks_end, EndOfSequence, codec=codec, capacity=4, callback=self._inbox.put),
        ]
        self.token = declare_alive(self.session, self.topics.alive("fusion"))

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                env: Envelope = self._inbox.get(timeout=0.2)
            except queue.Empty:
                with self._lock:
                    self._check_end()
                continue
            try:
                with self._lock:
                    self._handle(env.body)
                    self._check_end()
            except Exception:  # noqa: BLE001 - one bad message must not stop the map
                self.errors += 1
                log.exception("fusion failed on a %s", type(env.body).__name__)
            finally:
                if isinstance(env.body, TrackedFrame):
                    # fused, already in the map, or failed: a lossless source waits for it
                    self.acks.put(FrameAck(frame_index=env.body.frame.frame_index, service="fusion"))

    def _handle(self, body) -> None:
        if isinstance(body, TrackFeatures):
            self.core.add_track_features(body)
            self.features_in += 1
            return
        if isinstance(body, EndOfSequence):
            self.end, self._end_at = body, time.monotonic()
        elif body.frame.frame_index <= self.core.last_frame_index:
            # already in the map (resumed from a snapshot past it, or delivered twice)
            self.duplicates += 1
            return
        else:
            if self._first_frame_at is None:
                self._first_frame_at = time.monotonic()
            delta = self.core.add_frame(body)
            self.frames += 1
            self._last_frame_at = time.monotonic()
            if delta is not None:
                self.deltas.put(delta)
            if time.monotonic() - self._last_save >= self.cfg.fusion.snapshot_interval_s:
                self.save()

    def _check_end(self) -> None:
        """Finish the map once everything ``tracks/end`` announced is in."""
        end = self.end
        if end is None or self.finished.is_set():
            return
        frames_in = self.core.last_frame_index >= end.last_frame_index
        feats_in = end.track_features_published is None or self.features_in >= end.track_features_published
        if not (frames_in and feats_in) and self._inbox.empty():
            if time.monotonic() - self._end_at < END_GRACE_S:
                return
            log.warning(
                "finishing without everything the tracker announced: frames up to %d (have %d), %s feature messages (have %d)",
                end.last_frame_index, self.core.last_frame_index, end.track_features_published, self.features_in,
            )  # fmt: skip
        elif not self._inbox.empty():
            return
        self.deltas.put(self.core.finish())
        self.save(export=True)
        self.finished.set()
        log.info("sequence finished at frame %d: %d segments", self.core.last_frame_index, len(self.core.segments.segments))

    def save(self, export: bool = False) -> None:
        """A snapshot on disk (atomic, checksummed); with ``export`` also the mesh, the
        OpenLex3D files and ``run.json`` of ``trackgraph map``."""
        import json

        from services.mapping import export_map, run_summary
        from shared.io import atomic_write_text

        try:
            snapshot = self.core.snapshot(with_mesh=True, whole_map=export)
            self.store.save(snapshot, extra_state=self.core.state_dict())
            if export:
                export_map(self.out, self.core)
                seconds = time.monotonic() - (self._first_frame_at or time.monotonic())
                summary = run_summary(self.cfg, self.core, snapshot, frames=self.frames, seconds=seconds, sequence=None)
                summary["service"] = "fusion"
                # From the first frame fused to the last, without the final save: what a live
                # source's rate is compared with (``trackgraph bench run``).
                summary["fused_seconds"] = round((self._last_frame_at or 0.0) - (self._first_frame_at or 0.0), 3)
                summary.update(self.delivery())
                atomic_write_text(self.out / "run.json", json.dumps(summary, indent=2))
        except (StoreError, OSError) as exc:
            log.error("snapshot not written: %s", exc)
        self._last_save = time.monotonic()

    def delivery(self) -> dict:
        """Frames in the map against those the source announced: a fusion crash loses the
        frames after its last snapshot, and a router restart the ones in flight."""
        announced = None if self.end is None else self.end.frames_published
        lost = None if announced is None else max(announced - self.core.frames, 0)
        if lost:
            log.warning("%d of %d announced frames are not in the map (lost in a crash or on the link)", lost, announced)
        return {
            "frames_in_map": self.core.frames,
            "frames_announced": announced,
            "frames_lost": lost,
            "frames_duplicate": self.duplicates,
            "resumed_from": self.resumed_from,
        }

    def _on_snapshot(self, env: Envelope[SnapshotRequest]) -> GraphSnapshot:
        with self._lock:
            return self.core.snapshot(with_mesh=env.body.with_mesh)

    def stats(self) -> dict:
        return {"frames": self.frames, "frames_in_map": self.core.frames, "duplicates": self.duplicates, "errors": self.errors,
                "input_dropped": sum(s.stats.dropped for s in self.subs), "input_rejected": sum(s.stats.rejected for s in self.subs),
                "graph_seq": self.core.graph.graph_seq, "pending": self._inbox.qsize()}  # fmt: skip

    def close(self, save: bool = True) -> None:
        for s in self.subs:
            s.close()
        self._stop.set()
        self._worker.join(timeout=30)
        # A finished map was saved whole at its end; saving again would replace that snapshot
        # with one whose mesh is only the active window.
        if save and self.frames and not self.finished.is_set():
            with self._lock:
                self.save()
        self.snapshots.close()
        self.token.undeclare()
        self.deltas.close()
        self.acks.close()
        if self._own_session:
            self.session.close()
