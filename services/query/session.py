"""The query service as a session: ``graph/delta`` in, the ``query`` queryable answered,
``graph/snapshot`` asked on a gap or a late join, queries embedded through ``vl/embed`` (or
a local encoder). No Zenoh: everything goes through the :class:`~shared.runtime.bus.Bus` it
is given, so the same object runs over Zenoh (``services.query.node``) and in one process.

The replica (a :class:`~shared.graph.sync.ReplicaFollower`, the viewer's too) is changed on
the delta handler's thread; after each change a new :class:`QueryIndex` is built and swapped
in whole, so the queryable's worker threads answer from whole graph versions without
locking. Snapshot requests, and their retries with backoff while fusion is not there, happen
in :meth:`QuerySession.tick`.

Readiness and load (docs/architecture.md, "Query (paper III-F, eq. 10)"):

- The session declares itself alive (liveliness token, status ``running``) only once its
  text-embedding path has answered one warm-up request (``vl/embed``, or the local encoder
  loaded and run once), tried from :meth:`QuerySession.tick` every ``query.warmup_retry_s``.
  Until then its state is ``starting``; queries that come meanwhile are still answered as
  well as they can be.
- ``query.workers`` requests are worked on at once and at most ``query.queue_size`` more
  wait for one of them (the queryable's threads are as many as both, and it keeps none
  waiting of its own); one more is answered "overloaded: ..." at once by the queryable, and
  counted (``overloaded``, and as dropped on the ``query`` input).
- A request's ``deadline_s`` counts from its receipt (``Envelope.received``). One that waits
  for a worker until its budget runs out is answered "deadline exceeded: ..." then, without
  being worked on; the ``vl/embed`` round trip and the wait for a resync are cut to what is
  left of it.
- Text embeddings from ``vl/embed`` are kept in a bounded LRU (``query.embed_cache_size``);
  a request's ``room_text`` is embedded through the same path (deadline and cache) as its text.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from services.keyframe_vl.embedder import WARMUP_TEXT, Embedder, TextCache
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

DEADLINE_SLACK_S = 0.01
"""A ``vl/embed`` request cut to a deadline that fails this close to it failed for the deadline."""


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
            from shared.devices import resolve_device
            from shared.perception.encoders import make_vl_encoder

            # The text tower (ViT-H-14's needs about 4 GB) runs where the config puts it.
            encoder = make_vl_encoder(
                cfg.keyframe_vl.vl, device=resolve_device(cfg.query.device, "query.device"), fp16=cfg.keyframe_vl.fp16
            )
            self._embedder = Embedder(encoder, cfg.keyframe_vl.embed_cache_size)
        self.engine = QueryEngine(cfg.query, self._embed, cfg.fusion.graph.room_labels)
        self._text_cache = TextCache(0 if self._embedder is not None else cfg.query.embed_cache_size)
        """Remote embeddings only: the local Embedder keeps its own cache."""
        self.index = QueryIndex.empty()
        self.queries = 0
        self.refused = 0
        self.overloaded = 0
        """Requests answered "overloaded" at once: every worker busy, ``queue_size`` others waiting."""
        self.expired = 0
        """Requests whose deadline ran out before a worker took them: not worked on."""
        self.ready = False
        """The text-embedding path answered the warm-up: the token is declared."""
        self.warmup_s: float | None = None
        """Seconds from the session's start to the warm-up's answer."""
        self.warmup_tries = 0
        self._started = clock()
        self._next_warmup = float("-inf")
        self._slots = threading.BoundedSemaphore(cfg.query.workers)
        """One per worker: a request holds one while it is worked on."""
        self._waiting = 0
        """Requests waiting for a slot now."""
        self._count_lock = threading.Lock()
        self._closed = False
        self.token = None

        book = self.book
        book.figure("segments", lambda: len(self.index))
        book.figure("queries", lambda: self.queries)
        book.figure("refused", lambda: self.refused)
        book.figure("overloaded", lambda: self.overloaded)
        book.figure("expired", lambda: self.expired)
        book.figure("warmup_s", lambda: self.warmup_s)
        self.graph = ReplicaFollower(
            bus, self.topics, book, with_mesh=False, timeout_s=cfg.transport.query_timeout_s, on_change=self._rebuild,
            capacity=256, name="query:delta",
        )  # fmt: skip
        self.sync = self.graph.sync
        self.deltas = self.graph.deltas
        try:
            # A thread per worker and per queue place: a request waiting for a slot waits in
            # on_query, where its deadline can end the wait, not in the queryable's queue.
            self.queryable = bus.serve(
                self.topics.query, QueryRequest, QueryReply, self.on_query, workers=cfg.query.workers + cfg.query.queue_size,
                capacity=0, on_drop=self._on_overload,
            )  # fmt: skip
        except BaseException:
            self.graph.close()
            raise
        pending = getattr(self.queryable, "pending", None)
        book.declare_input("query", lambda: self._waiting + (pending() if pending is not None else 0))
        # State "starting", no token: tick() warms the embedding path up first.

    # ------------------------------------------------------------------ graph

    def tick(self, now: float) -> bool | None:
        """Ask fusion for a snapshot if the replica needs one and the backoff allows it
        (:meth:`ReplicaFollower.tick`, whose result this returns); until the session is ready,
        try the warm-up when it is due."""
        result = self.graph.tick(now)
        if not self.ready and now >= self._next_warmup:
            self._warm_up(now)
        return result

    def _warm_up(self, now: float) -> None:
        """Embed one text past the cache, through the path queries take; on its answer
        declare the token and go ``running``, else try again ``warmup_retry_s`` later."""
        self.warmup_tries += 1
        warm = getattr(self._embedder, "warm_up", None) if self._embedder is not None else None
        try:
            if warm is not None:
                warm()  # a local encoder: load its model and run a text through it
            else:
                self._embed_uncached(EmbedRequest(text=WARMUP_TEXT))
        except Exception as exc:  # noqa: BLE001 - not ready yet, whatever the reason: try again
            self._next_warmup = now + self.cfg.query.warmup_retry_s
            level = logging.INFO if self.warmup_tries == 1 else logging.DEBUG
            log.log(level, "query: text embedding not ready yet (%s); trying again every %.1f s", exc, self.cfg.query.warmup_retry_s)
            return
        self.warmup_s = round(max(self._clock() - self._started, 0.0), 3)
        self.token = self.bus.declare_alive(self.topics.alive("query"))
        self.ready = True
        self.book.set_state("running")
        log.info("query ready: text embedding answered %.1f s after start (try %d)", self.warmup_s, self.warmup_tries)

    def _rebuild(self, replica: GraphReplica, _mesh_changed: bool) -> None:
        try:
            self.index = QueryIndex.build(
                replica.graph_seq, replica.segments.values(), replica.rooms.values(),
                min_view_share=self.cfg.query.min_view_share, previous=self.index,
            )  # fmt: skip
        except QueryError as exc:
            self.book.error()
            log.error("graph version %d not indexed: %s", replica.graph_seq, exc)

    # ------------------------------------------------------------------ queries

    def _embed(self, req: EmbedRequest, deadline: float | None = None) -> np.ndarray:
        # Clients repeat prompts; a remembered text embedding saves the vl/embed round trip.
        if req.text is not None:
            return self._text_cache.get(req.text, lambda: self._embed_uncached(req, deadline))
        return self._embed_uncached(req, deadline)

    def _embed_uncached(self, req: EmbedRequest, deadline: float | None = None) -> np.ndarray:
        """``deadline`` (this session's clock) cuts the ``vl/embed`` round trip's time-out to
        what is left of the request's budget; a local encoder cannot be cut."""
        if self._embedder is not None:
            reply = self._embedder.embed(req)
        else:
            timeout = self.cfg.transport.query_timeout_s
            cut = False
            if deadline is not None:
                left = deadline - self._clock()
                if left <= 0:
                    raise QueryError("deadline exceeded: no time left to embed the query")
                if left < timeout:
                    timeout, cut = left, True
            self.book.published("vl_embed")
            try:
                reply = self.bus.request(self.topics.vl_embed, req, EmbedReply, timeout=timeout)
            except BusError as exc:
                if cut and self._clock() >= deadline - DEADLINE_SLACK_S:
                    raise QueryError(f"deadline exceeded: vl/embed did not answer in the {timeout:.3f} s left of the request's budget") from None
                raise QueryError(f"cannot embed the query: {exc}") from None
        if reply.error is not None or reply.embedding is None:
            raise QueryError(f"cannot embed the query: {reply.error or 'no embedding returned'}")
        return reply.embedding

    def _on_overload(self) -> None:
        """The queryable answered a request "overloaded" (on its receiving thread)."""
        self.book.count("query", "dropped")
        self._count("overloaded")

    def on_query(self, env: Envelope[QueryRequest]) -> QueryReply:
        """One query's reply: refused (with the reason) while the replica is out of sync, or
        when its ``deadline_s`` ran out before a worker took it (counted from
        ``env.received``, else from now: the in-process bus answers at once)."""
        now = self._clock()
        received = env.received if env.received is not None else now
        req = env.body
        deadline = None if req.deadline_s is None else received + req.deadline_s
        self.book.count("query", "received")
        self._count("queries")
        try:
            if not self._take_slot(now, deadline):
                self._count("expired")
                reply = QueryReply(
                    graph_seq=self.sync.graph_seq,
                    error=f"deadline exceeded: waited {self._clock() - received:.3f} s for a worker, the request's "
                    f"deadline_s is {req.deadline_s:g}; not worked on",
                )  # fmt: skip
            else:
                try:
                    reply = self._work(req, deadline)
                finally:
                    self._slots.release()
        except Exception:
            # The queryable answers the caller with an error reply; here it is counted.
            self.book.count("query", "rejected")
            self.book.error()
            raise
        if reply.error is not None:
            self._count("refused")
        self.book.count("query", "processed")
        # From receipt: the time spent waiting for a worker is part of what the client sees.
        self.book.work_done(max(self._clock() - received, 0.0))
        return reply

    def _take_slot(self, now: float, deadline: float | None) -> bool:
        """Wait for a worker's slot until ``deadline`` (this session's clock); False if it
        passed first."""
        if deadline is not None and now >= deadline:
            return False
        self._count("_waiting", 1)
        try:
            return self._slots.acquire(timeout=None if deadline is None else deadline - now)
        finally:
            self._count("_waiting", -1)

    def _work(self, req: QueryRequest, deadline: float | None) -> QueryReply:
        now = self._clock()
        if not self.sync.wait_synced(self.sync_wait_s if deadline is None else max(min(self.sync_wait_s, deadline - now), 0.0)):
            seq = self.sync.graph_seq
            what = "no graph yet: fusion has not answered" if seq == 0 else f"graph resynchronising (at version {seq}, fusion is ahead)"
            return QueryReply(graph_seq=seq, error=f"{what}; try again shortly")
        return self.engine.answer(self.index, req, embed=lambda r: self._embed(r, deadline))

    def _count(self, name: str, n: int = 1) -> None:
        with self._count_lock:  # several worker threads answer at once
            setattr(self, name, getattr(self, name) + n)

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
        if self.token is not None:
            self.token.undeclare()
        log.debug("query session closed after %d queries", self.queries)
