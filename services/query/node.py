"""query node: ``graph/delta`` in, the ``query`` queryable out; ``graph/snapshot`` asked on a
gap or a late join; queries embedded through ``vl/embed`` (or a local encoder).

The replica (``shared.graph.sync``) is kept on the delta subscriber's thread; after each
consistent change a new :class:`QueryIndex` is built and swapped in, so the queryable's
worker threads answer from whole graph versions without locking. Snapshot requests run on
a thread of their own, retried with backoff while fusion is not there.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from services.keyframe_vl.embedder import Embedder, TextCache
from services.query.core import QueryEngine, QueryError, QueryIndex
from shared.config.root import TrackGraphConfig
from shared.graph.scene import GraphReplica
from shared.graph.sync import ReplicaSync
from shared.messages.base import Envelope
from shared.messages.graph import GraphDelta, GraphSnapshot, SnapshotRequest
from shared.messages.rpc import EmbedReply, EmbedRequest, QueryReply, QueryRequest
from shared.topics import Topics
from shared.transport import (
    TransportError,
    TypedQueryable,
    TypedSubscriber,
    declare_alive,
    open_session,
    request,
)

log = logging.getLogger(__name__)

RETRY_MIN_S, RETRY_MAX_S = 0.2, 5.0
"""Backoff between snapshot requests while fusion does not answer."""


class QueryNode:
    """Wires a :class:`QueryEngine` to Zenoh."""

    def __init__(self, cfg: TrackGraphConfig, *, session=None) -> None:
        self.cfg = cfg
        self.topics = Topics(cfg.robot_id)
        self._own_session = session is None
        self.session = session or open_session(cfg.transport)
        codec = cfg.transport.codec
        self._embedder = None
        if cfg.query.embed == "local":
            from services.keyframe_vl.encoders import make_vl_encoder

            self._embedder = Embedder(make_vl_encoder(cfg.keyframe_vl.vl), cfg.keyframe_vl.embed_cache_size)
        self.engine = QueryEngine(cfg.query, self._embed)
        self._text_cache = TextCache(0 if self._embedder is not None else cfg.query.embed_cache_size)
        """Remote embeddings only: the local Embedder keeps its own cache."""
        self.index = QueryIndex.empty()
        self.sync = ReplicaSync(on_change=self._rebuild)
        self.queries = 0
        self.refused = 0
        self.errors = 0
        self._count_lock = threading.Lock()
        self._stop = threading.Event()
        self._want_snapshot = threading.Event()
        self._want_snapshot.set()  # a late joiner asks at once; fusion may already be mapping
        self._snapshots = threading.Thread(target=self._snapshot_loop, name="query:snapshot", daemon=True)
        self.deltas = TypedSubscriber(
            self.session, self.topics.graph_delta, GraphDelta, codec=codec, capacity=256, callback=self._on_delta
        )
        self.queryable = TypedQueryable(
            self.session, self.topics.query, QueryRequest, QueryReply, self._on_query,
            robot_id=cfg.robot_id, codec=codec, workers=cfg.query.workers,
        )  # fmt: skip
        self._snapshots.start()
        self.token = declare_alive(self.session, self.topics.alive("query"))

    # ------------------------------------------------------------------ graph

    def _on_delta(self, env: Envelope[GraphDelta]) -> None:
        if self.sync.on_delta(env.body):
            self._want_snapshot.set()

    def _snapshot_loop(self) -> None:
        wait = RETRY_MIN_S
        while not self._stop.is_set():
            if not self._want_snapshot.wait(0.2):
                continue
            if self.sync.synced and self.sync.graph_seq > 0:
                self._want_snapshot.clear()
                continue
            try:
                snap = request(
                    self.session, self.topics.graph_snapshot, SnapshotRequest(with_mesh=False), GraphSnapshot,
                    robot_id=self.cfg.robot_id, timeout=self.cfg.transport.query_timeout_s, codec=self.cfg.transport.codec,
                ).body  # fmt: skip
            except TransportError as exc:
                log.debug("no graph snapshot yet (%s); retrying in %.1f s", exc, wait)
                self._stop.wait(wait)
                wait = min(2 * wait, RETRY_MAX_S)
                continue
            wait = RETRY_MIN_S
            if self.sync.on_snapshot(snap):
                self._want_snapshot.clear()

    def _rebuild(self, replica: GraphReplica) -> None:
        try:
            self.index = QueryIndex.build(
                replica.graph_seq, replica.segments.values(), replica.rooms,
                min_view_share=self.cfg.query.min_view_share, previous=self.index,
            )  # fmt: skip
        except QueryError as exc:
            self.errors += 1
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
            try:
                reply = request(
                    self.session, self.topics.vl_embed, req, EmbedReply,
                    robot_id=self.cfg.robot_id, timeout=self.cfg.transport.query_timeout_s, codec=self.cfg.transport.codec,
                ).body  # fmt: skip
            except TransportError as exc:
                raise QueryError(f"cannot embed the query: {exc}") from None
        if reply.error is not None or reply.embedding is None:
            raise QueryError(f"cannot embed the query: {reply.error or 'no embedding returned'}")
        return reply.embedding

    def _on_query(self, env: Envelope[QueryRequest]) -> QueryReply:
        self._count("queries")
        if not self.sync.wait_synced(self.cfg.query.sync_wait_s):
            self._count("refused")
            what = "no graph yet: fusion has not answered" if self.sync.graph_seq == 0 else (
                f"graph resynchronising (at version {self.sync.graph_seq}, fusion is ahead)"
            )
            return QueryReply(graph_seq=self.sync.graph_seq, error=f"{what}; try again shortly")
        reply = self.engine.answer(self.index, env.body)
        if reply.error is not None:
            self._count("refused")
        return reply

    def _count(self, name: str) -> None:
        with self._count_lock:  # several worker threads answer at once
            setattr(self, name, getattr(self, name) + 1)

    # ------------------------------------------------------------------ lifecycle

    def stats(self) -> dict:
        return {
            "graph_seq": self.sync.graph_seq,
            "synced": self.sync.synced,
            "segments": len(self.index),
            "deltas": self.sync.deltas,
            "snapshots": self.sync.snapshots,
            "gaps": self.sync.gaps,
            "queries": self.queries,
            "refused": self.refused,
            "errors": self.errors,
            "query_link": self.queryable.stats.as_dict(),
            "delta_link": self.deltas.stats.as_dict(),
        }

    def close(self) -> None:
        self._stop.set()
        self.deltas.close()
        self.queryable.close()
        self._snapshots.join(timeout=self.cfg.transport.query_timeout_s + 1)
        self.token.undeclare()
        if self._own_session:
            self.session.close()
        log.debug("query node closed after %d queries", self.queries)
