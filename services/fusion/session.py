"""fusion's coordination, without Zenoh: ``tracks/frame`` and ``tracks/features`` in;
``graph/delta`` out; ``frames/ack`` for every tracked frame fused, already in the map, or
failed; the ``graph/snapshot`` queryable. The map is finished when the tracker's
``tracks/end`` has come and every frame and feature message it announces is in (or
``fusion.end_grace_s`` after it, with a warning).

The session wires; the work is done by its parts. The map on disk
(:class:`~services.fusion.durability.keeper.MapKeeper`, with a
:class:`~shared.graph.store.MapStore` and a map folder): resume from the newest snapshot, the
write-ahead :class:`~services.fusion.durability.journal.Journal` (every frame, feature
message, correction and end of sequence accepted goes there before it is acknowledged, a
frame's record written while the frame is fused, and a resume replays it through the same
handlers, so a killed fusion comes
back with everything it acknowledged), a snapshot every ``fusion.snapshot_interval_s``, and
at the end the whole map with the mesh, the OpenLex3D files and ``run.json``. Without a store
(``trackgraph map``) the caller writes the map. Pose corrections wait in
:class:`~services.fusion.corrections.pending.PendingCorrections`; the room labels'
embeddings come through :class:`~services.fusion.layers.roomlabels.RoomLabelFetch`.

Acks carry fusion's ``epoch`` (a number drawn at start) and ``features_through``; the tracker
keeps what is not acknowledged and sends it again to a new epoch. Feature messages are
applied once per ``serial``, and both kinds in the tracker's ``order``
(:mod:`services.fusion.durability.reorder`): a new frame that overtakes the resent ones
waits for them.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from services.fusion.corrections.pending import PendingCorrections
from services.fusion.durability.delivery import EndWatch, FeatureSerials
from services.fusion.durability.keeper import MapKeeper
from services.fusion.durability.reorder import InOrder
from services.fusion.layers.roomlabels import ROOM_LABELS_TIMEOUT_S, RoomLabelFetch
from services.fusion.mappath import MapPath, resolve_map_path
from services.fusion.protocol import FusionCoreLike
from shared.config.root import TrackGraphConfig
from shared.config.transport import CodecConfig
from shared.graph.store import MapStore
from shared.messages.frames import EndOfSequence, FrameAck, TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, MeshChunk, SnapshotRequest
from shared.messages.keyframes import TrackFeatures
from shared.messages.poses import PoseCorrection
from shared.runtime.bus import Bus
from shared.runtime.session import LATER, Inbox, Session

log = logging.getLogger(__name__)


def mesh_over_limits(mesh: MeshChunk, codec: CodecConfig) -> str | None:
    """Why ``mesh`` could not travel under ``codec``'s decode limits (every array within
    ``max_array_bytes``, all of them within the total and the payload limit), or None. A reply
    over them would be refused by every receiver with the same limits, after fusion spent the
    time to encode and send it: better a graph without the mesh and the reason."""
    arrays = {"vertices": mesh.vertices, "colors": mesh.colors, "faces": mesh.faces, "segment_ids": mesh.segment_ids}
    for name, arr in arrays.items():
        if arr.nbytes > codec.max_array_bytes:
            return (f"the whole map's mesh has {len(mesh.vertices)} vertices; its {name} are {arr.nbytes} bytes, "
                    f"over transport.codec.max_array_bytes {codec.max_array_bytes} (ask with_mesh for the active window)")  # fmt: skip
    total = sum(a.nbytes for a in arrays.values())
    limit = min(codec.total_array_limit, codec.max_payload_bytes)
    if total > limit:
        return (f"the whole map's mesh is {total} bytes, over the codec's limit of {limit} bytes for one reply "
                f"(transport.codec.max_total_array_bytes, max_payload_bytes; ask with_mesh for the active window)")  # fmt: skip
    return None


def trim_whole_map(snap: GraphSnapshot, codec: CodecConfig) -> GraphSnapshot:
    """``snap`` without its whole-map mesh when that could not travel under ``codec``
    (:func:`mesh_over_limits`), and the reason in its ``error``."""
    why = None if snap.mesh is None else mesh_over_limits(snap.mesh, codec)
    if why is None:
        return snap
    log.warning("graph/snapshot: whole-map mesh left out: %s", why)
    return snap.model_copy(update={"mesh": None, "error": f"SnapshotRequest.whole_map: {why}"})


WATERMARK_S = 1.0
"""How often fusion repeats its newest ack while nothing new comes: a restarted fusion
announces its epoch even while the source waits, and late feature messages get acknowledged."""


class FusionSession(Session):
    """A fusion core on a bus, and optionally on disk in ``out``."""

    service = "fusion"

    def __init__(
        self, bus: Bus, cfg: TrackGraphConfig, core: FusionCoreLike, *, store: MapStore | None = None, out: Path | None = None,
        observations: Path | None = None, resume: bool = False, clock: Callable[[], float] = time.monotonic,
        inbox: Inbox | None = None, epoch: int | None = None,
    ) -> None:  # fmt: skip
        super().__init__(bus, clock=clock, inbox=inbox)
        self.cfg, self.core, self.store = cfg, core, store
        self.out = None if out is None else Path(out)
        self.features = FeatureSerials()
        self.in_order = InOrder(cfg.fusion.reorder_wait_s, cfg.fusion.reorder_capacity)
        """The tracker's frames and feature messages put back in the order it sent them."""
        self.corrections = PendingCorrections(core, self.book)
        self.map_path = MapPath(core, resolve_map_path(cfg), cfg.fusion.mesh_every_n_frames)
        """Where graph updates run (``fusion.map_path``)."""
        self.disk = MapKeeper(cfg, core, store, self.out, self.book, features=self.features, order=self.in_order, corrections=self.corrections, clock=clock)
        """Resume, journal, snapshots and the final export (nothing without a store)."""
        self.epoch = secrets.randbits(62) if epoch is None else int(epoch)
        """Drawn at start: in every ack, so the tracker sees a restart."""
        self.finished = threading.Event()
        self.ending = EndWatch(cfg.fusion.end_grace_s)
        self.room_labels = RoomLabelFetch(cfg.fusion.graph.room_labels, bus, self.topics.vl_embed, core, self.lock)
        self._last_ack_at = -1e9
        self.disk.load(resume, observations)
        self.frames = 0
        """Frames this process fused (``core.frames`` counts those of the whole map)."""
        self.duplicates = 0
        self._first_frame_at: float | None = None
        self._last_frame_at: float | None = None
        self.deltas = self.output("graph_delta", GraphDelta)
        self.acks = self.output("frame_ack", FrameAck)
        if core.graph.graph_seq:
            # a resumed map goes on numbering its deltas where the snapshot left off
            self.deltas.seq = core.graph.graph_seq
        self.snapshots = self.serve("graph_snapshot", SnapshotRequest, GraphSnapshot, self._on_snapshot)
        # All of them in one order (the node's inbox): the core sees frames and feature updates
        # as they arrived, as the in-process pipeline feeds them.
        self.subscribe("tracks_frame", TrackedFrame, self._on_frame, capacity=16, queued=True)
        self.subscribe("tracks_features", TrackFeatures, self._on_features, capacity=64, queued=True)
        self.subscribe("tracks_end", EndOfSequence, self._on_end, capacity=4, queued=True)
        self.subscribe("poses_correction", PoseCorrection, self._on_correction, capacity=16, queued=True)
        handlers = {"frame": self._on_frame, "features": self._on_features, "correction": self._on_correction, "end": self._on_end}
        if self.disk.start(resume, lambda rec: handlers[rec.kind](rec.body), self.lock):
            self._watermark(self.clock())
        self._refresh()

    @property
    def resumed_from(self) -> str | None:
        """The snapshot folder the map resumed from (None: a fresh map, or the journal alone)."""
        return self.disk.resumed_from

    def _ack(self, frame_index: int, now: float) -> None:
        if self.disk.replaying:
            return
        self._last_ack_at = now
        self.acks.put(FrameAck(frame_index=frame_index, service="fusion", epoch=self.epoch, features_through=self.features.next))

    def _watermark(self, now: float) -> None:
        """The newest ack again, with the epoch and ``features_through`` as they are now."""
        if self.core.last_frame_index >= 0:
            self._ack(self.core.last_frame_index, now)

    def _on_frame(self, tf: TrackedFrame) -> object:
        self._arrive("frame", tf, tf.stream, tf.order)
        return LATER  # counted when applied

    def _on_features(self, msg: TrackFeatures) -> None:
        self._arrive("features", msg, msg.stream, msg.order)

    def _arrive(self, kind: str, body: TrackedFrame | TrackFeatures, stream: int | None, order: int | None) -> None:
        """In the tracker's order: applied now with any held ones it lets through, held until
        its turn, or dropped as already applied (sent again)."""
        ready, duplicate = self.in_order.admit(kind, body, stream, order, self.clock())
        if duplicate:
            if kind == "frame":
                self.duplicates += 1
                self.book.count("tracks_frame", "processed")
                self._ack(body.frame.frame_index, self.clock())
            else:
                self.features.duplicate += 1
            self._check_end(self.clock())
            self._refresh()
            return
        if not ready:
            self._refresh()  # held for its turn
        self._apply_ready(ready)

    def _apply_ready(self, ready: list) -> None:
        for kind, body in ready:
            (self._apply_frame if kind == "frame" else self._apply_features)(body)

    def _apply_frame(self, tf: TrackedFrame) -> None:
        k = tf.frame.frame_index
        t0 = self.clock()
        try:
            if k <= self.core.last_frame_index:
                # already in the map (resumed from a snapshot past it, or delivered twice)
                self.duplicates += 1
            else:
                if self._first_frame_at is None:
                    self._first_frame_at = t0
                with self.disk.writing("frame", tf):  # journaled while fused, on disk before the ack
                    delta = self.core.add_frame(tf)
                self.in_order.applied(tf.order)
                self.frames += 1
                self._last_frame_at = self.clock()
                if delta is not None:
                    self.deltas.put(delta)
                self.map_path.after_frame()
                self._publish_map_path()
                self.corrections.apply_due(self.deltas.put, before=self._settle)
                self.book.work_done(max(self._last_frame_at - t0, 0.0))
                if not self.disk.replaying and self.disk.due(self.frames, self._last_frame_at):
                    self.save()
            self.book.count("tracks_frame", "processed")
        except Exception:  # noqa: BLE001 - one bad frame must not stop the map
            self.book.count("tracks_frame", "rejected")
            self.book.error()
            log.exception("fusion failed on a TrackedFrame (frame %d)", k)
        finally:
            # fused, already in the map, or failed: a lossless source waits for it
            self.in_order.applied(tf.order)
            try:
                self._ack(k, self.clock())
            finally:
                self._check_end(self.clock())
                self._refresh()

    def _apply_features(self, msg: TrackFeatures) -> None:
        try:
            if self.features.seen(msg):
                return
            self.disk.append("features", msg)
            self.core.add_track_features(msg)
            self.in_order.applied(msg.order)
            self.features.took(msg)
        finally:
            self.in_order.applied(msg.order)
            self._check_end(self.clock())
            self._refresh()

    def _on_end(self, msg: EndOfSequence) -> None:
        if self.ending.end == msg:
            return  # sent again after a restart (or replayed): already waited for
        self.disk.append("end", msg)
        self.ending.arrive(msg, self.clock())
        self.book.progress(expected=msg.frames_published)
        self._check_end(self.ending.at)
        self._refresh()

    def _on_correction(self, c: PoseCorrection) -> object:
        """Held until fusion has fused its ``apply_after_frame`` (at once without one), then
        applied: the map moves and a delta goes out. Journaled on arrival, so a resumed
        fusion holds and applies it at the same frame."""
        self.disk.append("correction", c)
        self.corrections.pending.append(c)
        self.corrections.apply_due(self.deltas.put, before=self._settle)
        self._refresh()
        return LATER  # counted when applied or refused

    def _on_snapshot(self, req: SnapshotRequest) -> GraphSnapshot:
        # under the lock: a snapshot never sees a half-applied frame (nor a half-built update)
        with self.lock:
            self._settle()
            snap = self.core.snapshot(with_mesh=req.with_mesh or req.whole_map, whole_map=req.whole_map)
        return trim_whole_map(snap, self.cfg.transport.codec) if req.whole_map else snap

    def _check_end(self, now: float) -> None:
        """Finish the map once everything ``tracks/end`` announced is in."""
        busy = self.finished.is_set() or self.disk.replaying or len(self.in_order) or self.queued("tracks_frame", "tracks_features")
        if not busy and self.ending.complete(now, self.core.last_frame_index, self.features.in_map):
            self.finish()

    def finish(self) -> None:
        """The final graph update out; with a store the whole map saved and exported."""
        if self.finished.is_set():
            return
        self._settle()
        self.corrections.apply_due(self.deltas.put, final=True)
        self.deltas.put(self.core.finish())
        if self.store is not None:
            self.save(export=True)
        self._watermark(self.clock())  # the last feature messages acknowledged too
        self.book.set_state("finished")  # before the event: a waiter reads a finished status
        self.finished.set()
        log.info("sequence finished at frame %d: %d segments", self.core.last_frame_index, len(self.core.segments.segments))

    def save(self, export: bool = False) -> None:
        """A snapshot on disk (atomic, checksummed); with ``export`` also the mesh, the
        OpenLex3D files and ``run.json`` of ``trackgraph map``."""
        with self.lock:
            self._settle()
            self.disk.save(self.frames, summary=self._summary if export else None)

    def _publish_map_path(self) -> None:
        """The map path's finished deltas out, in order; its failed updates counted."""
        deltas, failed = self.map_path.take()
        for delta in deltas:
            self.deltas.put(delta)
        for _ in range(failed):
            self.book.error()

    def _settle(self) -> None:
        """Wait for the map path's running update and publish it: before anything else
        reads or moves the graph."""
        self.map_path.join()
        self._publish_map_path()

    def _summary(self, snapshot: GraphSnapshot) -> dict[str, Any]:
        from services.fusion.export import service_summary

        return service_summary(self.cfg, self.core, snapshot, frames=self.frames, first_at=self._first_frame_at,
                               last_at=self._last_frame_at, now=self.clock(), delivery=self.delivery())  # fmt: skip

    def delivery(self) -> dict[str, Any]:
        """Frames in the map against those the source announced: a fusion crash loses the
        frames after its last snapshot, and a router restart the ones in flight."""
        announced, lost = self.ending.lost(self.core.frames)
        return {
            "frames_in_map": self.core.frames, "frames_announced": announced, "frames_lost": lost, "frames_duplicate": self.duplicates,
            "resumed_from": self.resumed_from, "features_in_map": self.features.in_map, "features_duplicate": self.features.duplicate,
            "journal_replayed": dict(self.disk.replay.records), "journal_torn": self.disk.replay.torn, "reorder": self.in_order.as_dict(),
            "journal": self.disk.journal_stats(),
        }  # fmt: skip

    def fetch_room_labels(self, timeout: float = ROOM_LABELS_TIMEOUT_S) -> bool:
        """The room labels' embeddings from ``vl/embed`` for the core (see :class:`RoomLabelFetch`)."""
        return self.room_labels.fetch(timeout)

    def tick(self, now: float) -> None:
        """The end of the sequence once its grace is over; a snapshot when one is due; the
        room labels' embeddings until they are fetched (outside the lock: the round trip must
        not hold frames up)."""
        self.room_labels.maybe_fetch(now)
        with self.lock:
            try:
                self._apply_ready(self.in_order.expire(now))
                self._publish_map_path()
                self._check_end(now)
                if self.disk.due(self.frames, now):
                    self.save()
                self.disk.sync(now)
                if now - self._last_ack_at >= WATERMARK_S and not self.finished.is_set():
                    self._watermark(now)
            except Exception:  # noqa: BLE001 - the next tick tries again
                self.book.error()
                log.exception("fusion: tick failed")
            self._refresh()

    def _refresh(self) -> None:
        book = self.book
        book.progress(done=self.core.frames)
        for name, value in (("frames", self.frames), ("frames_in_map", self.core.frames), ("duplicates", self.duplicates),
                            ("reorder", self.in_order.as_dict()), ("graph_seq", self.core.graph.graph_seq),
                            ("finished", self.finished.is_set()), ("room_labels", self.room_labels.ready),
                            ("corrections", self.corrections.figure()), ("journal", self.disk.figure()), ("map_path", self.map_path.figure())):  # fmt: skip
            if value is not None:
                book.figure(name, value)

    def close(self, save: bool = True) -> None:
        """Close the endpoints; with ``save``, keep what was fused since the last snapshot. A
        finished map was saved whole at its end: saving again would replace that snapshot
        with one whose mesh is only the active window."""
        super().close()
        if save and self.store is not None and self.frames and not self.finished.is_set():
            self.save()
        self.map_path.close()
        self.disk.close()
