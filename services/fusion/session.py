"""fusion's coordination, without Zenoh: ``tracks/frame`` and ``tracks/features`` in;
``graph/delta`` out; ``frames/ack`` for every tracked frame fused, already in the map, or
failed; the ``graph/snapshot`` queryable. The map is finished when the tracker's
``tracks/end`` has come and every frame and feature message it announces is in (or
``fusion.end_grace_s`` after it, with a warning).

With a :class:`~shared.graph.store.MapStore` and a map folder it also keeps the map on disk:
resumes from the newest snapshot, saves one every ``fusion.snapshot_interval_s``, and at the
end saves the whole map with the mesh, the OpenLex3D files and ``run.json``. Without
(``trackgraph map``), the caller writes the map.

On disk, every frame, feature message and end of sequence it accepts goes to the write-ahead
:class:`~services.fusion.journal.Journal` before it is applied and acknowledged; a snapshot
cuts the journal, and a resume replays it after the snapshot through the same handlers, so
a killed fusion comes back with everything it acknowledged. Acks carry fusion's ``epoch`` (a
number drawn at start) and ``features_through``; the tracker keeps what is not acknowledged
and sends it again to a new epoch. Feature messages are applied once per ``serial``, and
both kinds in the tracker's ``order`` (:mod:`services.fusion.reorder`): a new frame that
overtakes the resent ones waits for them.
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.fusion.journal import FIRST, Journal, JournalError, Record
from services.fusion.observations import FILE_NAME as OBSERVATIONS_FILE
from services.fusion.observations import ObservationLog
from services.fusion.poses import CorrectionError
from services.fusion.reorder import InOrder
from shared.config.root import TrackGraphConfig
from shared.config.transport import CodecConfig
from shared.graph.store import MapStore, StoreError
from shared.messages.frames import EndOfSequence, FrameAck, TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, MeshChunk, SnapshotRequest
from shared.messages.keyframes import TrackFeatures
from shared.messages.poses import PoseCorrection, parse_correction
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

ROOM_LABELS_TIMEOUT_S = 2.0
"""Time-out of each ``vl/embed`` request for a room label."""
ROOM_LABELS_RETRY_S = (2.0, 60.0)
"""First wait after a failed fetch of the room labels, and the cap it doubles up to."""

WATERMARK_S = 1.0
"""How often fusion repeats its newest ack while nothing new comes: a restarted fusion
announces its epoch even while the source waits, and late feature messages get acknowledged."""


def refuse_wanted(cfg: TrackGraphConfig) -> bool:
    """``fusion.refuse``: ``on``, or ``auto`` with corrections configured for this run."""
    mode = cfg.fusion.refuse
    return mode == "on" or (mode == "auto" and (bool(cfg.source.corrections) or cfg.ros2.input.corrections != "none"))


class FusionSession(Session):
    """A :class:`~services.fusion.core.FusionCore` on a bus, and optionally on disk in ``out``."""

    service = "fusion"

    def __init__(
        self, bus: Bus, cfg: TrackGraphConfig, core, *, store: MapStore | None = None, out: Path | None = None,
        observations: Path | None = None,
        resume: bool = False, clock: Callable[[], float] = time.monotonic, inbox: Inbox | None = None,
        epoch: int | None = None,
    ) -> None:  # fmt: skip
        super().__init__(bus, clock=clock, inbox=inbox)
        if store is not None and out is None:
            raise ValueError("a fusion session with a store needs its map folder (out) for the final export")
        self.cfg = cfg
        self.core = core
        self.store = store
        self.out = None if out is None else Path(out)
        self.epoch = secrets.randbits(62) if epoch is None else int(epoch)
        """Drawn at start: in every ack, so the tracker sees a restart."""
        self.resumed_from: str | None = None
        self.finished = threading.Event()
        self.end: EndOfSequence | None = None
        self._end_at = 0.0
        self.features_in = 0
        """Feature messages in the map (across restarts: saved with each snapshot)."""
        self.features_next = 0
        """One past the highest feature ``serial`` applied: lower ones are duplicates."""
        self.features_duplicate = 0
        self.in_order = InOrder(cfg.fusion.reorder_wait_s, cfg.fusion.reorder_capacity)
        """The tracker's frames and feature messages put back in the order it sent them."""
        self.pending_corrections: list[PoseCorrection] = []
        """Pose corrections received and not applied yet (waiting for their
        ``apply_after_frame``), in arrival order."""
        self.correction_error: str | None = None
        """Why the newest refused correction was refused."""
        self.replayed: dict[str, int] = {}
        """Journal records replayed at resume, per kind."""
        self.journal_torn = 0
        """Journal records dropped at resume (torn by a crash mid-write, or damaged)."""
        self._replaying = False
        self._last_ack_at = -1e9
        self._labels_at = 0.0
        self._labels_wait = ROOM_LABELS_RETRY_S[0]
        self.room_label_tries = 0
        """Fetches of the room labels' embeddings tried (``fetch_room_labels``)."""
        jcfg = cfg.fusion.journal
        self.journal = Journal(store.root / "journal", jcfg, clock=clock) if store is not None and jcfg.enabled else None
        base: str | None = None
        if resume and store is not None and store.latest_name() is not None:
            state = store.load()
            core.load_state_dict(state.extra, state.snapshot)
            self._load_session_state(state.extra.get("fusion_session"))
            self.resumed_from = str(state.path)
            base = state.path.name
            log.info("resumed from %s at frame %d (graph %d)", state.path, core.last_frame_index, core.graph.graph_seq)
        if refuse_wanted(cfg):
            path = store.root / OBSERVATIONS_FILE if store is not None else observations
            core.observations = ObservationLog(path, cfg.fusion.journal.zstd_level, fresh=not (resume and self.resumed_from))
        self.frames = 0
        """Frames this process fused (``core.frames`` counts those of the whole map)."""
        self.duplicates = 0
        self._first_frame_at: float | None = None
        self._last_frame_at: float | None = None
        self._last_save = clock()
        self._saved_frames = 0
        self.deltas = self.output("graph_delta", GraphDelta)
        self.acks = self.output("frame_ack", FrameAck)
        if core.graph.graph_seq:
            # a resumed map goes on numbering its deltas where the snapshot left off
            self.deltas.seq = core.graph.graph_seq
        self.snapshots = self.serve("graph_snapshot", SnapshotRequest, GraphSnapshot, self._on_snapshot)
        # All three in one order (the node's inbox): the core sees frames and feature updates
        # as they arrived, as the in-process pipeline feeds them.
        self.subscribe("tracks_frame", TrackedFrame, self._on_frame, capacity=16, queued=True)
        self.subscribe("tracks_features", TrackFeatures, self._on_features, capacity=64, queued=True)
        self.subscribe("tracks_end", EndOfSequence, self._on_end, capacity=4, queued=True)
        self.subscribe("poses_correction", PoseCorrection, self._on_correction, capacity=16, queued=True)
        if self.journal is not None:
            if resume:
                self._replay(base)
            else:
                self.journal.reset()
        self._refresh()

    # ---------------------------------------------------------------- journal

    def _replay(self, base: str | None) -> None:
        """What the journal holds after snapshot ``base`` (None: from the empty map), through
        the live handlers; then appends go on in the newest file."""
        assert self.journal is not None
        records, stats = self.journal.replay(base)
        self.journal_torn = stats.torn
        self._replaying = True
        try:
            with self.lock:
                for rec in records:
                    self._apply_record(rec)
        finally:
            self._replaying = False
        files = [n for n in self.journal.files() if base is None or int(n) >= int(base)]
        self.journal.open(files[-1] if files else (base or FIRST))
        if records or stats.torn:
            log.info(
                "journal: replayed %d frames, %d feature messages, %d ends from %d files after %s; %d torn or damaged records dropped (%d bytes)",
                self.replayed.get("frame", 0), self.replayed.get("features", 0), self.replayed.get("end", 0), stats.files,
                base or "the empty map", stats.torn, stats.torn_bytes,
            )  # fmt: skip
        self._watermark(self.clock())

    def _apply_record(self, rec: Record) -> None:
        self.replayed[rec.kind] = self.replayed.get(rec.kind, 0) + 1
        if rec.kind == "frame":
            self._on_frame(rec.body)
        elif rec.kind == "features":
            self._on_features(rec.body)
        elif rec.kind == "correction":
            self._on_correction(rec.body)
        else:
            self._on_end(rec.body)

    def _journal(self, kind: str, body) -> None:
        """Write-ahead: on disk (with the OS) before it is applied and acknowledged. Not
        while replaying what the journal already holds."""
        if self.journal is None or self._replaying:
            return
        try:
            self.journal.append(kind, body)
        except JournalError as exc:
            # the map goes on; what comes now is only as safe as the next snapshot
            self.book.error()
            log.error("%s", exc)

    def _session_state(self) -> dict:
        # corrections still waiting for their frame: the journal is cut at this snapshot
        pending = "\n".join(c.to_json() for c in self.pending_corrections).encode()
        return {"features": np.asarray([self.features_in, self.features_next], np.int64), "order": np.asarray(self.in_order.state(), np.int64),
                "pending_corrections": np.frombuffer(pending, np.uint8).copy()}  # fmt: skip

    def _load_session_state(self, state: dict | None) -> None:
        if state is None:  # a snapshot from before the journal
            return
        self.features_in, self.features_next = (int(x) for x in np.asarray(state["features"]))
        if "order" in state:
            self.in_order.load(np.asarray(state["order"]).tolist())
        text = bytes(np.asarray(state.get("pending_corrections", np.zeros(0, np.uint8)), np.uint8)).decode()
        self.pending_corrections = [parse_correction(json.loads(line)) for line in text.splitlines() if line.strip()]

    def _ack(self, frame_index: int, now: float) -> None:
        if self._replaying:
            return
        self._last_ack_at = now
        self.acks.put(FrameAck(frame_index=frame_index, service="fusion", epoch=self.epoch, features_through=self.features_next))

    def _watermark(self, now: float) -> None:
        """The newest ack again, with the epoch and ``features_through`` as they are now."""
        if self.core.last_frame_index >= 0:
            self._ack(self.core.last_frame_index, now)

    # ---------------------------------------------------------------- inputs

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
                self.features_duplicate += 1
            self._check_end(self.clock())
            self._refresh()
            return
        if not ready:
            self._refresh()  # held for its turn
        self._apply_ready(ready)

    def _apply_ready(self, ready: list) -> None:
        for kind, body in ready:
            if kind == "frame":
                self._apply_frame(body)
            else:
                self._apply_features(body)

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
                self._journal("frame", tf)
                delta = self.core.add_frame(tf)
                self.in_order.applied(tf.order)
                self.frames += 1
                self._last_frame_at = self.clock()
                if delta is not None:
                    self.deltas.put(delta)
                self._apply_corrections()
                self.book.work_done(max(self._last_frame_at - t0, 0.0))
                if not self._replaying:
                    self._maybe_save(self._last_frame_at)
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
            if msg.serial is not None and msg.serial < self.features_next:
                self.features_duplicate += 1  # sent again after a restart, and already in
                return
            self._journal("features", msg)
            self.core.add_track_features(msg)
            self.in_order.applied(msg.order)
            self.features_in += 1
            if msg.serial is not None:
                self.features_next = msg.serial + 1
        finally:
            self.in_order.applied(msg.order)
            self._check_end(self.clock())
            self._refresh()

    def _on_end(self, msg: EndOfSequence) -> None:
        if self.end == msg:
            return  # sent again after a restart (or replayed): already waited for
        self._journal("end", msg)
        self.end, self._end_at = msg, self.clock()
        self.book.progress(expected=msg.frames_published)
        self._check_end(self._end_at)
        self._refresh()

    def _on_correction(self, c: PoseCorrection) -> object:
        """Held until fusion has fused its ``apply_after_frame`` (at once without one), then
        applied: the map moves and a delta goes out. Journaled on arrival, so a resumed
        fusion holds and applies it at the same frame."""
        self._journal("correction", c)
        self.pending_corrections.append(c)
        self._apply_corrections()
        self._refresh()
        return LATER  # counted when applied or refused

    def _apply_corrections(self, final: bool = False) -> None:
        """Every pending correction that is due (``final``: all of them, at the map's end)."""
        last = self.core.last_frame_index
        due = [c for c in self.pending_corrections if final or c.apply_after_frame is None or last >= c.apply_after_frame]
        # by identity: models holding arrays do not compare with ==
        self.pending_corrections = [c for c in self.pending_corrections if all(c is not d for d in due)]
        for c in due:
            try:
                out = self.core.apply_correction(c)
            except CorrectionError as exc:
                self.correction_error = f"correction {c.correction_id} refused: {exc}"
                self.book.count("poses_correction", "rejected")
                self.book.error()
                log.error("fusion: %s", self.correction_error)
                continue
            except Exception:  # noqa: BLE001 - one bad correction must not stop the map
                self.book.count("poses_correction", "rejected")
                self.book.error()
                log.exception("fusion failed on PoseCorrection %d", c.correction_id)
                continue
            self.book.count("poses_correction", "processed")
            if out.delta is not None:
                self.deltas.put(out.delta)

    def _on_snapshot(self, req: SnapshotRequest) -> GraphSnapshot:
        # under the lock: a snapshot never sees a half-applied frame
        with self.lock:
            snap = self.core.snapshot(with_mesh=req.with_mesh or req.whole_map, whole_map=req.whole_map)
        if req.whole_map and snap.mesh is not None:
            why = mesh_over_limits(snap.mesh, self.cfg.transport.codec)
            if why is not None:
                log.warning("graph/snapshot: whole-map mesh left out: %s", why)
                return snap.model_copy(update={"mesh": None, "error": f"SnapshotRequest.whole_map: {why}"})
        return snap

    # ---------------------------------------------------------------- end, saves

    def _check_end(self, now: float) -> None:
        """Finish the map once everything ``tracks/end`` announced is in."""
        end = self.end
        if end is None or self.finished.is_set():
            return
        if self._replaying or len(self.in_order) or self.queued("tracks_frame", "tracks_features"):
            return
        frames_in = self.core.last_frame_index >= end.last_frame_index
        feats_in = end.track_features_published is None or self.features_in >= end.track_features_published
        if not (frames_in and feats_in):
            if now - self._end_at < self.cfg.fusion.end_grace_s:
                return
            log.warning(
                "finishing without everything the tracker announced: frames up to %d (have %d), %s feature messages (have %d)",
                end.last_frame_index, self.core.last_frame_index, end.track_features_published, self.features_in,
            )  # fmt: skip
        self.finish()

    def finish(self) -> None:
        """The final graph update out; with a store the whole map saved and exported."""
        if self.finished.is_set():
            return
        self._apply_corrections(final=True)
        self.deltas.put(self.core.finish())
        if self.store is not None:
            self.save(export=True)
        self._watermark(self.clock())  # the last feature messages acknowledged too
        self.finished.set()
        self.book.set_state("finished")
        log.info("sequence finished at frame %d: %d segments", self.core.last_frame_index, len(self.core.segments.segments))

    def _maybe_save(self, now: float) -> None:
        if self.store is None or self.frames <= self._saved_frames:
            return
        full = self.journal is not None and self.journal.bytes > self.cfg.fusion.journal.max_bytes
        if full:
            log.info("journal past fusion.journal.max_bytes (%d bytes): a snapshot now", self.journal.bytes)
        if full or now - self._last_save >= self.cfg.fusion.snapshot_interval_s:
            self.save()

    def save(self, export: bool = False) -> None:
        """A snapshot on disk (atomic, checksummed); with ``export`` also the mesh, the
        OpenLex3D files and ``run.json`` of ``trackgraph map``."""
        from services.fusion.export import export_map, run_summary
        from shared.io import atomic_write_text

        if self.store is None or self.out is None:
            raise RuntimeError("this fusion session keeps no map on disk")
        with self.lock:
            try:
                snapshot = self.core.snapshot(with_mesh=True, whole_map=export)
                folder = self.store.save(snapshot, extra_state={**self.core.state_dict(), "fusion_session": self._session_state()})
                if self.journal is not None:
                    # everything appended so far is in the snapshot: later records go to its file
                    names = self.store.names()
                    self.journal.cut(folder.name, names[0] if names else None)
                if export:
                    export_map(self.out, self.core)
                    seconds = self.clock() - (self._first_frame_at or self.clock())
                    summary = run_summary(self.cfg, self.core, snapshot, frames=self.frames, seconds=seconds, sequence=None)
                    summary["service"] = "fusion"
                    # From the first frame fused to the last, without the final save: what a live
                    # source's rate is compared with (``trackgraph bench run``).
                    summary["fused_seconds"] = round((self._last_frame_at or 0.0) - (self._first_frame_at or 0.0), 3)
                    summary.update(self.delivery())
                    atomic_write_text(self.out / "run.json", json.dumps(summary, indent=2))
            except (StoreError, OSError, JournalError) as exc:
                self.book.error()
                log.error("snapshot not written: %s", exc)
            self._last_save = self.clock()
            self._saved_frames = self.frames

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
            "features_in_map": self.features_in,
            "features_duplicate": self.features_duplicate,
            "journal_replayed": dict(self.replayed),
            "journal_torn": self.journal_torn,
            "reorder": self.in_order.as_dict(),
            "journal": None if self.journal is None else self.journal.stats(),
        }

    # ---------------------------------------------------------------- time, status, close

    # ---------------------------------------------------------------- room labels

    def fetch_room_labels(self, timeout: float = ROOM_LABELS_TIMEOUT_S) -> bool:
        """Embed ``fusion.graph.room_labels`` through keyframe_vl's ``vl/embed`` (the map's own
        VL encoder) and hand them to the core, which names rooms from then on. True when the
        core has them (or there are none to fetch); False, logged, when keyframe_vl did not
        answer them all: :meth:`tick` tries again, waiting twice as long each time."""
        labels = list(self.cfg.fusion.graph.room_labels)
        if not labels or self._has_room_labels() or not hasattr(self.core, "set_room_vocabulary"):
            return True
        from shared.messages.rpc import EmbedReply, EmbedRequest

        self.room_label_tries += 1
        rows = []
        try:
            for text in labels:
                reply = self.bus.request(self.topics.vl_embed, EmbedRequest(text=text), EmbedReply, timeout=timeout)
                if reply.error is not None or reply.embedding is None:
                    raise ValueError(f"vl/embed refused {text!r}: {reply.error or 'no embedding'}")
                rows.append(np.asarray(reply.embedding, np.float32))
            if len({r.shape for r in rows}) != 1:
                raise ValueError(f"vl/embed gave the room labels embeddings of {sorted({r.shape[0] for r in rows})} dimensions")
        except Exception as exc:  # noqa: BLE001 - keyframe_vl may not be up yet: rooms stay unnamed until it is
            level = logging.INFO if self.room_label_tries == 1 else logging.DEBUG
            log.log(level, "fusion: room labels not embedded yet (%s); rooms are named once vl/embed answers", exc)
            return False
        with self.lock:
            self.core.set_room_vocabulary(labels, np.stack(rows))
        log.info("fusion: %d room labels embedded (%d-d); rooms are named from the next update", len(labels), rows[0].shape[0])
        return True

    def _has_room_labels(self) -> bool:
        # (a core without rooms, as some tests give, has none to name)
        return getattr(self.core, "room_vocabulary", None) is not None

    def _maybe_fetch_room_labels(self, now: float) -> None:
        if self._has_room_labels() or not self.cfg.fusion.graph.room_labels or now < self._labels_at:
            return
        if not self.fetch_room_labels():
            self._labels_at = now + self._labels_wait
            self._labels_wait = min(2 * self._labels_wait, ROOM_LABELS_RETRY_S[1])

    def tick(self, now: float) -> None:
        """The end of the sequence once its grace is over; a snapshot when one is due; the
        room labels' embeddings until they are fetched (outside the lock: the round trip must
        not hold frames up)."""
        try:
            self._maybe_fetch_room_labels(now)
        except Exception:  # noqa: BLE001 - the next tick tries again
            log.exception("fusion: fetching the room labels failed")
        with self.lock:
            try:
                self._apply_ready(self.in_order.expire(now))
                self._check_end(now)
                self._maybe_save(now)
                if self.journal is not None and self.journal.due(now):
                    self.journal.sync(now)
                if now - self._last_ack_at >= WATERMARK_S and not self.finished.is_set():
                    self._watermark(now)
            except Exception:  # noqa: BLE001 - the next tick tries again
                self.book.error()
                log.exception("fusion: tick failed")
            self._refresh()

    def _refresh(self) -> None:
        book = self.book
        book.progress(done=self.core.frames)
        book.figure("frames", self.frames)
        book.figure("frames_in_map", self.core.frames)
        book.figure("duplicates", self.duplicates)
        book.figure("reorder", self.in_order.as_dict())
        book.figure("graph_seq", self.core.graph.graph_seq)
        book.figure("finished", self.finished.is_set())
        book.figure("room_labels", self._has_room_labels())
        if hasattr(self.core, "corrections"):
            book.figure("corrections", {**self.core.corrections.as_dict(), "pending": len(self.pending_corrections), "last_error": self.correction_error})
        if self.journal is not None:
            book.figure("journal", {"records": self.journal.appended, "bytes": self.journal.bytes, "torn_at_resume": self.journal_torn})

    def close(self, save: bool = True) -> None:
        """Close the endpoints; with ``save``, keep what was fused since the last snapshot. A
        finished map was saved whole at its end: saving again would replace that snapshot
        with one whose mesh is only the active window."""
        super().close()
        if save and self.store is not None and self.frames and not self.finished.is_set():
            self.save()
        if self.journal is not None:
            self.journal.close()
        observations = getattr(self.core, "observations", None)  # test doubles of the core have none
        if observations is not None:
            observations.close()
