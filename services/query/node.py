"""query node: the :class:`~services.query.session.QuerySession` over a Zenoh bus.

The session does the work (replica sync, index, answers); this adapter opens the bus and
ticks the session on a thread of its own, which is where snapshot requests (a late join, a
gap) and their retries with backoff happen, off the delta subscriber's thread.
"""

from __future__ import annotations

from services.query.session import QuerySession
from shared.config.root import TrackGraphConfig
from shared.runtime.adapter import SessionNode, open_bus, session_attr

TICK_S = 0.05
"""How often the session is ticked: a gap is noticed at once, the request follows within this."""


class QueryNode(SessionNode):
    """Serves ``trackgraph/<robot>/query`` over Zenoh; pass a zenoh ``session`` to share one.
    The session declares its liveliness itself, once its text path answered."""

    # What tests and benchmarks look at, as before the session existed.
    sync = session_attr("sync")
    index = session_attr("index")
    deltas = session_attr("deltas")
    queryable = session_attr("queryable")

    def __init__(self, cfg: TrackGraphConfig, *, session=None) -> None:
        self.cfg = cfg
        super().__init__(
            open_bus(cfg, session), lambda b: QuerySession(cfg, b), name="query", tick_s=TICK_S,
            stop_timeout_s=cfg.transport.query_timeout_s + 1,
        )  # fmt: skip

    def stats(self) -> dict:
        report = self.book.report()
        return {
            **report.figures, "errors": report.errors,
            "query_link": self.queryable.stats.as_dict(), "delta_link": self.deltas.stats.as_dict(),
        }  # fmt: skip


def build(cfg, *, out=None, resume: bool = False) -> QueryNode:
    """``trackgraph serve query``."""
    from threadpoolctl import threadpool_limits

    # Each query is one small matrix-vector product, answered on several worker threads:
    # a multi-threaded BLAS only spins against them (9 ms against 1.3 ms for 500 segments
    # of 1024-d galleries on 2 busy cores).
    threadpool_limits(1, user_api="blas")
    return QueryNode(cfg)
