"""The query service as a session: ``graph/delta`` in, the ``query`` queryable answered,
``graph/snapshot`` asked on a gap or a late join, queries embedded through ``vl/embed`` (or
a local encoder). No Zenoh: everything goes through the :class:`~shared.runtime.bus.Bus` it
is given, so the same object runs over Zenoh (``services.query.node``) and in one process.

The replica (a :class:`~shared.graph.sync.ReplicaFollower`, the viewer's too) is changed on
the delta handler's thread; after each change a new :class:`QueryIndex` is built and swapped
in whole, so the queryable's worker threads answer from whole graph versions without
locking. Snapshot requests, and their retries with backoff while fusion is not there, happen
in :meth:`QuerySession.tick`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from services.keyframe_vl.embedder import Embedder, TextCache
from services.query.core import QueryEngine, QueryError, QueryIndex
from shared.config.root import TrackGraphConfig
from shared.graph.scene import GraphReplica
from shared.graph.sync import ReplicaFollower
from shared.messages.base import Envelope
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryReply, QueryRequest
from shared.runtime.bus import Bus, BusError
from shared.runtime.status import StatusBook
from shared.topics import Topics

log = logging.getLogger(__name__)


class QuerySession:
    """Answers queries from a replica of fusion's graph kept in step over ``bus``.

    ``sync_wait_s`` (default ``cfg.query.sync_wait_s``) is how long a query that arrives
    while the replica is out of sync waits for it before it is refused; in one process,
    where nothing else can bring the snapshot meanwhile, pass 0. ``embedder`` replaces the
    one ``cfg.query.embed: local`` would build.
    """

    def __init__(
        self,
        cfg: TrackGraphConfig,
        bus: Bus,
        *,
        embedder: Embedder | None = None,
        sync_wait_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        self.bus = bus
        self.topics = Topics(cfg.robot_id)
        self.sync_wait_s = cfg.query.sync_wait_s if sync_wait_s is None else float(sync_wait_s)
        self.book = StatusBook("query", clock=clock)
        self._clock = clock
        self._embedder = embedder
        if self._embedder is None and cfg.query.embed == "local":
            from services.keyframe_vl.encoders import make_vl_encoder

            self._embedder = Embedder(make_vl_encoder(cfg.keyframe_vl.vl), cfg.keyframe_vl.embed_cache_size)
        self.engine = QueryEngine(cfg.query, self._embed)
        self._text_cache = TextCache(0 if self._embedder is not None else cfg.query.embed_cache_size)
        """Remote embeddings only: the local Embedder keeps its own cache."""
        self.index = QueryIndex.empty()
        self.queries = 0
        self.refused = 0
        self._count_lock = threading.Lock()
        self._closed = False

        book = self.book
        book.figure("segments", lambda: len(self.index))
        book.figure("queries", lambda: self.queries)
        book.figure("refused", lambda: self.refused)
        self.graph = ReplicaFollower(
            bus, self.topics, book, with_mesh=False, timeout_s=cfg.transport.query_timeout_s, on_change=self._rebuild,
            capacity=256, name="query:delta",
        )  # fmt: skip
        self.sync = self.graph.sync
        self.deltas = self.graph.deltas
        try:
            self.queryable = bus.serve(self.topics.query, QueryRequest, QueryReply, self.on_query, workers=cfg.query.workers)
        except BaseException:
            self.graph.close()
            raise
        # TypedQueryable has no queue-depth probe; the in-process one has.
        book.declare_input("query", getattr(self.queryable, "pending", None))
        self.token = bus.declare_alive(self.topics.alive("query"))
        book.set_state("running")

    # ------------------------------------------------------------------ graph

    def tick(self, now: float) -> bool | None:
        """Ask fusion for a snapshot if the replica needs one and the backoff allows it
        (:meth:`ReplicaFollower.tick`)."""
        return self.graph.tick(now)

    def _rebuild(self, replica: GraphReplica, _mesh_changed: bool) -> None:
        try:
            self.index = QueryIndex.build(
                replica.graph_seq, replica.segments.values(), replica.rooms,
                min_view_share=self.cfg.query.min_view_share, previous=self.index,
            )  # fmt: skip
        except QueryError as exc:
            self.book.error()
            log.error("graph version %d not indexed: %s", replica.graph_seq, exc)

    # ------------------------------------------------------------------ queries

    def _embed(self, req: EmbedRequest) -> np.ndarray:
        # Clients repeat prompts; a remembered text embedding saves the vl/embed round trip.
        if req.text is not None:
            return self._text_cache.get(req.text, lambda: self._embed_uncached(req))
        return self._embed_uncached(req)

    def _embed_uncached(self, req: EmbedRequest) -> np.ndarray:
        if self._embedder is not None:
            reply = self._embedder.embed(req)
        else:
            self.book.published("vl_embed")
            try:
                reply = self.bus.request(self.topics.vl_embed, req, EmbedReply, timeout=self.cfg.transport.query_timeout_s)
            except BusError as exc:
                raise QueryError(f"cannot embed the query: {exc}") from None
        if reply.error is not None or reply.embedding is None:
            raise QueryError(f"cannot embed the query: {reply.error or 'no embedding returned'}")
        return reply.embedding

    def on_query(self, env: Envelope[QueryRequest]) -> QueryReply:
        """One query's reply: refused (with the reason) while the replica is out of sync."""
        t0 = self._clock()
        self.book.count("query", "received")
        self._count("queries")
        try:
            if not self.sync.wait_synced(self.sync_wait_s):
                seq = self.sync.graph_seq
                what = "no graph yet: fusion has not answered" if seq == 0 else f"graph resynchronising (at version {seq}, fusion is ahead)"
                reply = QueryReply(graph_seq=seq, error=f"{what}; try again shortly")
            else:
                reply = self.engine.answer(self.index, env.body)
        except Exception:
            # The queryable answers the caller with an error reply; here it is counted.
            self.book.count("query", "rejected")
            self.book.error()
            raise
        if reply.error is not None:
            self._count("refused")
        self.book.count("query", "processed")
        self.book.work_done(self._clock() - t0)
        return reply

    def _count(self, name: str) -> None:
        with self._count_lock:  # several worker threads answer at once
            setattr(self, name, getattr(self, name) + 1)

    # ------------------------------------------------------------------ lifecycle

    def stats(self) -> dict:
        return self.book.report().figures

    def close(self) -> None:
        """Stop answering and receiving; the bus stays open (its owner closes it)."""
        if self._closed:
            return
        self._closed = True
        for what in (self.graph, self.queryable):
            try:
                what.close()
            except Exception:  # noqa: BLE001 - keep closing the rest
                log.exception("query: closing an endpoint")
        self.token.undeclare()
        log.debug("query session closed after %d queries", self.queries)
