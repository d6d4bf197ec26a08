"""A Python client of the query service, for scripts and for ``trackgraph query --live``.

    with QueryClient(TransportConfig(connect=["tcp/base:7447"])) as client:
        for hit in client.query("red armchair", top_k=3):
            print(hit.segment, hit.score, hit.centroid)
        kitchen = client.rooms("kitchen", top_k=1)[0].room
        sink = client.query("sink", room_text="kitchen")  # or: room=kitchen

Any number of clients may query one service at once; each call is one Zenoh request, with
a ``deadline_s`` a little under the client's time-out, so a service too busy to answer in
time says so ("deadline exceeded", or "overloaded" at once) instead of leaving it to time out.
:meth:`QueryClient.snapshot` asks fusion for the graph itself (``graph/snapshot``), with the
whole map's mesh if wanted.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np

from shared.config.transport import TransportConfig
from shared.messages.graph import GraphSnapshot, SnapshotRequest
from shared.messages.rpc import QueryHit, QueryReply, QueryRequest, RoomHit
from shared.topics import Topics
from shared.transport import TransportError, open_session, request

WHOLE_MAP_TIMEOUT_S = 30.0
"""Least time-out of a whole-map snapshot: marching cubes over a large map's archive takes
seconds, a bare graph milliseconds."""


DEADLINE_MARGIN_S = 0.2
"""A request's ``deadline_s`` is the client's time-out less this (at most a fifth of it): the
trip to the service and the reply's way back come out of the time-out too, so the service's
"deadline exceeded" answer still arrives before the client gives up."""


def deadline_for(timeout_s: float) -> float:
    """The ``deadline_s`` a request sent with ``timeout_s`` carries."""
    return max(timeout_s - DEADLINE_MARGIN_S, 0.8 * timeout_s)


class QueryRefused(TransportError):
    """The service answered, but refused the query (the message says why)."""


class QueryClient:
    """Queries ``trackgraph/<robot_id>/query``; pass a session to share one."""

    def __init__(
        self,
        transport: TransportConfig | None = None,
        *,
        robot_id: str = "robot0",
        session=None,
        timeout_s: float | None = None,
    ) -> None:
        self.transport = transport or TransportConfig()
        self.topics = Topics(robot_id)
        self.robot_id = robot_id
        self.timeout_s = timeout_s if timeout_s is not None else max(self.transport.query_timeout_s, 5.0)
        if not self.timeout_s > 0:
            raise ValueError(f"QueryClient timeout_s must be positive, got {self.timeout_s}")
        self._own_session = session is None
        self.session = session or open_session(self.transport)
        self._seq = 0
        self.last_graph_seq = -1

    def query(
        self,
        text: str | None = None,
        *,
        image: Annotated[np.ndarray, "(H, W, 3) uint8"] | None = None,
        top_k: int | None = None,
        room: int | None = None,
        center: Annotated[np.ndarray, "(3,) float world metres"] | None = None,
        radius: float | None = None,
        gallery: Literal["max", "mean"] | None = None,
        room_text: str | None = None,
    ) -> list[QueryHit]:
        """Ranked segments for a text or an image; ``room_text`` keeps only the segments of
        the room that best matches it (the chosen room is in :meth:`ask`'s ``reply.rooms``).
        Raises QueryRefused or TransportError."""
        req = QueryRequest(
            text=text, image=image, top_k=top_k, room=room, room_text=room_text, radius=radius, gallery=gallery,
            center=None if center is None else np.asarray(center, np.float64),
        )  # fmt: skip
        reply = self.ask(req)
        if reply.error is not None:
            raise QueryRefused(f"query refused: {reply.error}")
        return reply.hits

    def rooms(
        self,
        text: str | None = None,
        *,
        image: Annotated[np.ndarray, "(H, W, 3) uint8"] | None = None,
        top_k: int | None = None,
    ) -> list[RoomHit]:
        """The graph's rooms ranked by their feature against a text ("kitchen") or an image,
        best first; empty while no room has a feature. Raises QueryRefused or TransportError."""
        reply = self.ask(QueryRequest(text=text, image=image, top_k=top_k, target="rooms"))
        if reply.error is not None:
            raise QueryRefused(f"query refused: {reply.error}")
        return reply.rooms

    def ask(self, req: QueryRequest) -> QueryReply:
        """The raw reply to one request, error replies included. A request without
        ``deadline_s`` gets one from this client's time-out (:func:`deadline_for`)."""
        if req.deadline_s is None:
            req = req.model_copy(update={"deadline_s": deadline_for(self.timeout_s)})
        self._seq += 1
        reply = request(
            self.session, self.topics.query, req, QueryReply,
            robot_id=self.robot_id, timeout=self.timeout_s, codec=self.transport.codec, seq=self._seq,
        ).body  # fmt: skip
        self.last_graph_seq = reply.graph_seq
        return reply

    def snapshot(self, *, with_mesh: bool = False, whole_map: bool = False, timeout_s: float | None = None) -> GraphSnapshot:
        """fusion's graph now: with ``with_mesh`` the active window's mesh, with ``whole_map``
        the whole map's, the same as the saved map's (fusion builds it from the archive while
        frames wait: seconds on a large map, so the default time-out is at least
        ``WHOLE_MAP_TIMEOUT_S``). Raises QueryRefused when fusion declines the mesh (its reason),
        TransportError on a time-out or an error reply."""
        timeout = timeout_s if timeout_s is not None else max(self.timeout_s, WHOLE_MAP_TIMEOUT_S if whole_map else 0.0)
        self._seq += 1
        snap = request(
            self.session, self.topics.graph_snapshot, SnapshotRequest(with_mesh=with_mesh, whole_map=whole_map), GraphSnapshot,
            robot_id=self.robot_id, timeout=timeout, codec=self.transport.codec, seq=self._seq,
        ).body  # fmt: skip
        if snap.error is not None:
            raise QueryRefused(f"snapshot refused: {snap.error}")
        return snap

    def close(self) -> None:
        if self._own_session:
            self.session.close()

    def __enter__(self) -> QueryClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
