"""A fusion session's map on disk: resume from the newest snapshot, the write-ahead journal
(every accepted message written before it is acknowledged, replayed after the snapshot on
resume), a snapshot every ``fusion.snapshot_interval_s`` (or when the journal grows past
``fusion.journal.max_bytes``), and at the end the whole map with ``run.json``.

Without a store (``trackgraph map``) it keeps nothing and every call is a no-op. The
session's own state (feature serials, the reorder buffer, waiting corrections) goes into
each snapshot as ``fusion_session`` (:func:`pack_session`), and comes back with it."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np

from services.fusion.corrections.observations import FILE_NAME as OBSERVATIONS_FILE
from services.fusion.corrections.observations import ObservationLog, refuse_wanted
from services.fusion.durability.journal import FIRST, Journal, JournalError, Record, ReplayStats
from shared.graph.store import MapStore, StoreError

if TYPE_CHECKING:
    from pydantic import BaseModel

    from services.fusion.corrections.pending import PendingCorrections
    from services.fusion.durability.delivery import FeatureSerials
    from services.fusion.durability.reorder import InOrder
    from services.fusion.protocol import FusionCoreLike
    from shared.config.root import TrackGraphConfig
    from shared.messages.graph import GraphSnapshot
    from shared.runtime.session import FairLock
    from shared.runtime.status import StatusBook

log = logging.getLogger(__name__)


def pack_session(features_in: int, features_next: int, order: list[int], pending: Annotated[np.ndarray, "(B,) uint8"]) -> dict[str, np.ndarray]:
    """The session's part of a snapshot: feature messages in the map and the next serial,
    the reorder buffer's state, the waiting corrections (JSON lines; the journal is cut at
    this snapshot, so they would be lost otherwise)."""
    return {"features": np.asarray([features_in, features_next], np.int64), "order": np.asarray(order, np.int64), "pending_corrections": pending}


def unpack_session(state: dict[str, Any]) -> tuple[int, int, list[int] | None, Annotated[np.ndarray, "(B,) uint8"]]:
    """Back from :func:`pack_session`; the order is None in a snapshot from before the reorder
    buffer, and the corrections empty from before them."""
    features_in, features_next = (int(x) for x in np.asarray(state["features"]))
    order = np.asarray(state["order"]).tolist() if "order" in state else None
    return features_in, features_next, order, np.asarray(state.get("pending_corrections", np.zeros(0, np.uint8)), np.uint8)


class MapKeeper:
    """``core``'s map in ``store`` (None: nothing on disk) and the map folder ``out`` for the
    final export; write errors are counted in ``book`` and logged, and the map goes on.
    ``features``, ``order`` and ``corrections`` are the session's parts saved with each snapshot."""

    def __init__(
        self, cfg: TrackGraphConfig, core: FusionCoreLike, store: MapStore | None, out: Path | None, book: StatusBook, *,
        features: FeatureSerials, order: InOrder, corrections: PendingCorrections, clock: Callable[[], float] = time.monotonic,
    ) -> None:  # fmt: skip
        if store is not None and out is None:
            raise ValueError("a fusion session with a store needs its map folder (out) for the final export")
        self.cfg, self.core, self.store, self.out, self.book, self.clock = cfg, core, store, out, book, clock
        self.features, self.order, self.corrections = features, order, corrections
        jcfg = cfg.fusion.journal
        self.journal = Journal(store.root / "journal", jcfg, clock=clock) if store is not None and jcfg.enabled else None
        self.resumed_from: str | None = None
        """The snapshot folder the map resumed from."""
        self.replay = ReplayStats()
        """What the journal replayed at resume (records per kind, torn ones dropped)."""
        self.replaying = False
        """While the journal's records go through the session's handlers: no appends, acks or saves."""
        self._base: str | None = None
        self._last_save = clock()
        self._saved_frames = 0

    def load(self, resume: bool, observations: Path | None = None) -> None:
        """With ``resume`` and a snapshot in the store, the core and the session's parts from
        the newest good one. With ``fusion.refuse`` wanted, the core keeps the frames it fuses
        in a file beside the snapshots (reopened on a resume), or in ``observations`` without
        a store."""
        core = self.core
        if resume and self.store is not None and self.store.latest_name() is not None:
            state = self.store.load()
            core.load_state_dict(state.extra, state.snapshot)
            self._load_session(state.extra.get("fusion_session"))
            self.resumed_from = str(state.path)
            self._base = state.path.name
            log.info("resumed from %s at frame %d (graph %d)", state.path, core.last_frame_index, core.graph.graph_seq)
        if refuse_wanted(self.cfg):
            path = self.store.root / OBSERVATIONS_FILE if self.store is not None else observations
            core.observations = ObservationLog(path, self.cfg.fusion.journal.zstd_level, fresh=not (resume and self.resumed_from))
        self._last_save = self.clock()

    def _load_session(self, state: dict[str, Any] | None) -> None:
        if state is None:  # a snapshot from before the journal
            return
        self.features.in_map, self.features.next, order, pending = unpack_session(state)
        if order is not None:
            self.order.load(order)
        self.corrections.load(pending)

    def start(self, resume: bool, apply: Callable[[Record], None], lock: FairLock) -> bool:
        """With ``resume``, every journal record after the snapshot through ``apply`` (under
        ``lock``), then appends go on in the newest file; otherwise a fresh journal. True when
        it replayed."""
        if self.journal is None:
            return False
        if not resume:
            self.journal.reset()
            return False
        records, self.replay = self.journal.replay(self._base)
        self.replaying = True
        try:
            with lock:
                for rec in records:
                    apply(rec)
        finally:
            self.replaying = False
        base = self._base
        files = [n for n in self.journal.files() if base is None or int(n) >= int(base)]
        self.journal.open(files[-1] if files else (base or FIRST))
        stats = self.replay
        if records or stats.torn:
            log.info(
                "journal: replayed %d frames, %d feature messages, %d ends from %d files after %s; %d torn or damaged records dropped (%d bytes)",
                stats.records.get("frame", 0), stats.records.get("features", 0), stats.records.get("end", 0), stats.files,
                base or "the empty map", stats.torn, stats.torn_bytes,
            )  # fmt: skip
        return True

    def append(self, kind: str, body: BaseModel) -> None:
        """Write-ahead: on disk (with the OS) before it is applied and acknowledged. Not
        while replaying what the journal already holds."""
        self.finish(self.begin(kind, body))

    def begin(self, kind: str, body: BaseModel) -> Future | None:
        """Write-ahead, started: the record is encoded and written on the journal's thread
        while the caller applies ``body`` (which must not change meanwhile); :meth:`finish`
        waits for it, before the ack. None when nothing is journaled (no journal, a replay)."""
        if self.journal is None or self.replaying:
            return None
        return self.journal.submit(kind, body)

    @contextmanager
    def writing(self, kind: str, body: BaseModel) -> Iterator[None]:
        """Write-ahead for ``body`` while the block applies it: the record is compressed and
        written on the journal's thread meanwhile, and with the OS when the block ends, before
        the caller acknowledges it (a fusion killed before then is sent the message again)."""
        pending = self.begin(kind, body)
        try:
            yield
        finally:
            self.finish(pending)

    def finish(self, pending: Future | None) -> None:
        """Wait for a record :meth:`begin` started to be with the operating system."""
        if pending is None:
            return
        try:
            pending.result()
        except JournalError as exc:
            # the map goes on; what comes now is only as safe as the next snapshot
            self.book.error()
            log.error("%s", exc)

    def due(self, frames: int, now: float) -> bool:
        """Whether a snapshot is due: frames fused since the last, and the interval up or the
        journal past ``fusion.journal.max_bytes``."""
        if self.store is None or frames <= self._saved_frames:
            return False
        full = self.journal is not None and self.journal.bytes > self.cfg.fusion.journal.max_bytes
        if full:
            log.info("journal past fusion.journal.max_bytes (%d bytes): a snapshot now", self.journal.bytes)
        return full or now - self._last_save >= self.cfg.fusion.snapshot_interval_s

    def save(self, frames: int, summary: Callable[[GraphSnapshot], dict[str, Any]] | None = None) -> None:
        """A snapshot (atomic, checksummed) with the session's parts; with ``summary`` the whole
        map, the mesh and OpenLex3D files, and ``run.json`` from ``summary(snapshot)``."""
        from services.fusion.export import export_map
        from shared.io import atomic_write_text

        if self.store is None or self.out is None:
            raise RuntimeError("this fusion session keeps no map on disk")
        core = self.core
        try:
            snapshot = core.snapshot(with_mesh=True, whole_map=summary is not None)
            session = pack_session(self.features.in_map, self.features.next, self.order.state(), self.corrections.state())
            folder = self.store.save(snapshot, extra_state={**core.state_dict(), "fusion_session": session})
            if self.journal is not None:
                # everything appended so far is in the snapshot: later records go to its file
                names = self.store.names()
                self.journal.cut(folder.name, names[0] if names else None)
            if summary is not None:
                export_map(self.out, core)
                atomic_write_text(self.out / "run.json", json.dumps(summary(snapshot), indent=2))
        except (StoreError, OSError, JournalError) as exc:
            self.book.error()
            log.error("snapshot not written: %s", exc)
        self._last_save = self.clock()
        self._saved_frames = frames

    def sync(self, now: float) -> None:
        """The journal's fsync when one is owed."""
        if self.journal is not None and self.journal.due(now):
            self.journal.sync(now)

    def figure(self) -> dict[str, int] | None:
        """The ``journal`` status figure (None without a journal)."""
        if self.journal is None:
            return None
        return {"records": self.journal.appended, "bytes": self.journal.bytes, "torn_at_resume": self.replay.torn}

    def journal_stats(self) -> dict[str, Any] | None:
        """The journal's figures for ``run.json`` (None without a journal)."""
        return None if self.journal is None else self.journal.stats()

    def close(self) -> None:
        """The journal and the core's kept frames closed (what was written stays)."""
        if self.journal is not None:
            self.journal.close()
        if self.core.observations is not None:
            self.core.observations.close()
