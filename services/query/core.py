"""The query core (paper III-F, eq. 10): ranked segments for an embedded text or image query.

No Zenoh here. A :class:`QueryIndex` is an immutable view of one graph version: every CLIP
gallery row of every segment stacked into one unit-normalised matrix, so a query is one
matrix-vector product followed by a per-segment maximum (eq. 10) or, for the gallery
ablation, a product with the segments' normalised mean features. The service builds a new
index after each applied delta and swaps it in whole, so a query never sees a half-applied
graph; answering needs no lock.

Deviation from the paper (docs/method.md, Q1): eq. 10's maximum runs only over the gallery
rows whose track holds at least ``QueryConfig.min_view_share`` of the segment's hypothesis
weight (a segment keeps its best-supported row), so a small object's track absorbed by a
larger segment cannot make that segment its answer; ``min_view_share: 0`` is the paper's
plain maximum.

Rooms are asked for by name the same way: fusion gives each room an open-vocabulary
``RoomNode.feature`` in the galleries' space, and the index stacks those of the rooms that
have one, so "which room is the kitchen" (``QueryRequest.target: rooms``) is one more
matrix-vector product, and ``QueryRequest.room_text`` ("the sink in the kitchen") filters
the segments to the best-matching room before they are ranked.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np

from shared.config.query import QueryConfig
from shared.messages.graph import RoomNode, SegmentNode
from shared.messages.rpc import EmbedRequest, QueryHit, QueryReply, QueryRequest, RoomHit

log = logging.getLogger(__name__)

Embed = Callable[[EmbedRequest], Annotated[np.ndarray, "(D,) float32"]]
"""Embeds a query's text or image; raises :class:`QueryError` with the reason if it cannot."""


class QueryError(ValueError):
    """A query that cannot be answered, for a reason the client can act on."""


def _unit_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class _Block:
    """One segment's share of an index, kept while the replica keeps the same segment object."""

    source: SegmentNode
    view: SegmentNode
    """``source`` without the gallery rows under ``min_view_share``."""
    rows: Annotated[np.ndarray, "(r, D) float32 unit rows"]
    mean: Annotated[np.ndarray, "(D,) float32 unit mean of rows"]


@dataclass(frozen=True)
class QueryIndex:
    """The segments of one graph version, arranged for scoring."""

    graph_seq: int
    segments: tuple[SegmentNode, ...]
    """Segments with at least one gallery row, in id order."""
    gallery: Annotated[np.ndarray, "(R, D) float32 unit rows"]
    row_start: Annotated[np.ndarray, "(S + 1,) int64: segment s owns rows row_start[s]:row_start[s+1]"]
    row_segment: Annotated[np.ndarray, "(R,) int64 segment of each gallery row"]
    mean: Annotated[np.ndarray, "(S, D) float32 unit mean gallery feature per segment"]
    centroids: Annotated[np.ndarray, "(S, 3) float64"]
    rooms: Annotated[np.ndarray, "(S,) int64 room id, -1 for none"]
    room_ids: frozenset[int]
    """Every room of the graph (a filter on a room without segments is valid, just empty)."""
    blocks: dict[int, _Block]
    """Per segment id, what the next build may reuse."""
    room_nodes: tuple[RoomNode, ...]
    """Rooms with a feature, in id order: their names, centroids and boxes."""
    room_feature_ids: Annotated[np.ndarray, "(Q,) int64 id of each room_nodes entry"]
    room_features: Annotated[np.ndarray, "(Q, D) float32 unit rows, one per room_nodes entry"]

    @staticmethod
    def build(
        graph_seq: int,
        segments: Iterable[SegmentNode],
        rooms: Iterable[RoomNode | int] = (),
        *,
        min_view_share: float = 0.0,
        previous: QueryIndex | None = None,
    ) -> QueryIndex:
        """``rooms`` are the graph's rooms: their ids make up ``room_ids`` and those with a
        ``feature`` can be ranked; plain ids (rooms without features) are accepted too.

        ``min_view_share`` leaves out gallery rows whose track holds less of the segment
        (``QueryConfig.min_view_share``); a segment always keeps its best-supported row.

        With ``previous`` (built with the same ``min_view_share``), segments that are the
        same objects as then are not normalised again: a delta changes a few segments, and
        renormalising every gallery after each one cost the live service a third of its time.
        """
        old = previous.blocks if previous is not None else {}
        blocks: dict[int, _Block] = {}
        for s in segments:
            if not len(s.gallery_tracks):
                continue
            hit = old.get(s.id)
            if hit is not None and hit.source is s:
                blocks[s.id] = hit
                continue
            view = _views(s, min_view_share)
            rows = _unit_rows(view.gallery)
            blocks[s.id] = _Block(s, view, rows, _unit_rows(rows.sum(0)))
        ids = sorted(blocks)
        dim = blocks[ids[0]].rows.shape[1] if ids else 0
        for i in ids:
            if blocks[i].rows.shape[1] != dim:
                raise QueryError(f"segment {i} has {blocks[i].rows.shape[1]}-d gallery rows, others {dim}-d")
        nodes, room_ids = _room_nodes(rooms)
        room_dim = nodes[0].feature.shape[0] if nodes else 0
        for r in nodes:
            if r.feature.shape[0] != room_dim:
                raise QueryError(f"room {r.id} has a {r.feature.shape[0]}-d feature, other rooms {room_dim}-d")
        if nodes and ids and room_dim != dim:
            raise QueryError(
                f"room features are {room_dim}-d but the segments' gallery rows are {dim}-d: "
                "rooms and segments were embedded by different encoders"
            )
        segs = tuple(blocks[i].view for i in ids)
        counts = np.array([len(blocks[i].rows) for i in ids], np.int64)
        return QueryIndex(
            graph_seq=graph_seq,
            segments=segs,
            gallery=np.concatenate([blocks[i].rows for i in ids]) if ids else np.zeros((0, 0), np.float32),
            row_start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            row_segment=np.repeat(np.arange(len(segs)), counts),
            mean=np.stack([blocks[i].mean for i in ids]) if ids else np.zeros((0, 0), np.float32),
            centroids=np.array([s.centroid for s in segs], np.float64).reshape(-1, 3),
            rooms=np.array([-1 if s.room is None else s.room for s in segs], np.int64),
            room_ids=frozenset(room_ids) | {int(s.room) for s in segs if s.room is not None},
            blocks=blocks,
            room_nodes=nodes,
            room_feature_ids=np.array([r.id for r in nodes], np.int64),
            room_features=_unit_rows(np.stack([r.feature for r in nodes])) if nodes else np.zeros((0, 0), np.float32),
        )

    @staticmethod
    def empty() -> QueryIndex:
        return QueryIndex.build(0, [])

    @property
    def dim(self) -> int:
        return int(self.gallery.shape[1]) if self.gallery.size else 0

    @property
    def room_dim(self) -> int:
        """Dimension of the room features; 0 when no room has one."""
        return int(self.room_features.shape[1]) if self.room_features.size else 0

    @property
    def room_features_count(self) -> int:
        """Rooms that have a feature, the ones ``target: rooms`` and ``room_text`` rank."""
        return len(self.room_nodes)

    def __len__(self) -> int:
        return len(self.segments)

    def score(
        self, query: Annotated[np.ndarray, "(D,) float32"], gallery: Literal["max", "mean"] = "max"
    ) -> tuple[Annotated[np.ndarray, "(S,) float32"], Annotated[np.ndarray, "(S,) int64 best gallery row of each segment"]]:
        """Eq. 10: each segment's maximum cosine over its gallery (or the cosine with its mean
        feature), and the row that gave it."""
        if not len(self):
            return np.zeros(0, np.float32), np.zeros(0, np.int64)
        q = _unit_rows(query)
        cos = self.gallery @ q  # (R,)
        starts = self.row_start[:-1]
        best = np.maximum.reduceat(cos, starts)
        # The row holding each segment's maximum, the first one on ties.
        at_max = np.where(cos == best[self.row_segment], np.arange(len(cos)), len(cos))
        first = np.minimum.reduceat(at_max, starts).astype(np.int64)
        if gallery == "mean":
            return (self.mean @ q).astype(np.float32), first
        return best.astype(np.float32), first


def _room_nodes(rooms: Iterable[RoomNode | int]) -> tuple[tuple[RoomNode, ...], set[int]]:
    """The rooms with a feature, in id order, and the ids of all of them."""
    ids: set[int] = set()
    featured: dict[int, RoomNode] = {}
    for r in rooms:
        if isinstance(r, RoomNode):
            ids.add(int(r.id))
            if r.feature is not None:
                featured[int(r.id)] = r
        elif isinstance(r, (int, np.integer)) and not isinstance(r, bool):
            ids.add(int(r))
        else:
            raise TypeError(f"QueryIndex.build rooms: expected RoomNode objects or room ids, got {type(r).__name__}")
    return tuple(featured[i] for i in sorted(featured)), ids


def _checked(embedding: np.ndarray, dim: int, what: str, against: str) -> Annotated[np.ndarray, "(D,) float32"]:
    """``embedding`` flat, or QueryError when it is not ``dim``-d and finite."""
    emb = np.asarray(embedding, np.float32).reshape(-1)
    if emb.shape[0] != dim or not np.isfinite(emb).all():
        raise QueryError(
            f"{what} is {emb.shape[0]}-d but the map's {against} are {dim}-d: the query encoder differs from the one that built the map"
        )
    return emb


def _views(s: SegmentNode, min_share: float) -> SegmentNode:
    w = s.gallery_weights
    if min_share <= 0 or not w or min(w) >= min_share:
        return s
    keep = [i for i, x in enumerate(w) if x >= min_share] or [int(np.argmax(w))]
    return s.model_copy(update={
        "gallery": s.gallery[keep], "gallery_tracks": [s.gallery_tracks[i] for i in keep], "gallery_weights": [w[i] for i in keep],
    })  # fmt: skip


class QueryEngine:
    """Validates, embeds and answers queries against a :class:`QueryIndex`.

    Rooms are ranked for a text by their *margin* (``RoomHit.margin``): the text's cosine with
    the room's feature minus the best cosine of any other of ``room_labels``. A plain cosine
    favours the rooms described best whatever the text: on ``small`` the dining room's
    feature (0.88 with "dining room") was nearer "hall" than the glimpsed hall's own was
    (named "hall" at 0.55). The labels are embedded through the same path as the query
    (cached). An image query, or an engine without labels, ranks by the cosine.
    """

    def __init__(self, cfg: QueryConfig, embed: Embed, room_labels: Iterable[str] = ()) -> None:
        self.cfg = cfg
        self.embed = embed
        self.room_labels = [str(t) for t in room_labels if str(t).strip()]

    def check(self, req: QueryRequest) -> None:
        """Raise QueryError for a request the service refuses (the message schema already
        rejects an empty query and a center without a radius)."""
        cfg = self.cfg
        if req.text is not None and len(req.text) > cfg.max_text_chars:
            raise QueryError(f"text query has {len(req.text)} characters; at most {cfg.max_text_chars} allowed")
        if req.room_text is not None and len(req.room_text) > cfg.max_text_chars:
            raise QueryError(f"room_text has {len(req.room_text)} characters; at most {cfg.max_text_chars} allowed")
        if req.target == "rooms":
            # These narrow down segments; a ranking of rooms has nothing for them to act on.
            given = [name for name, v in (("room", req.room), ("room_text", req.room_text), ("center", req.center)) if v is not None]
            if given:
                raise QueryError(f"target rooms ranks the rooms themselves: {', '.join(given)} (a filter of segments) does not apply")
        if req.image is not None:
            h, w = req.image.shape[:2]
            if h * w > cfg.max_image_pixels:
                raise QueryError(f"image query has {w}x{h} = {h * w} pixels; at most {cfg.max_image_pixels} allowed")
        if req.top_k is not None and req.top_k > cfg.max_top_k:
            raise QueryError(f"top_k {req.top_k} exceeds the service's maximum of {cfg.max_top_k}")

    def answer(self, index: QueryIndex, req: QueryRequest, embed: Embed | None = None) -> QueryReply:
        """The ranked segments (or with ``target: rooms`` the ranked rooms), or a reply
        carrying the reason it was refused. ``embed`` replaces the engine's own for this
        request (the service's, cut to its deadline); a ``room_text`` is embedded with it too."""
        embed = embed or self.embed
        try:
            self.check(req)
            if req.room_text is not None and not index.room_nodes:
                # Refused before anything is embedded: no embedding could change the answer.
                raise QueryError(
                    f"no room has a feature yet: cannot tell which room is {req.room_text!r} "
                    f"({len(index.room_ids)} rooms in graph version {index.graph_seq}); "
                    "use room with a room id, or ask again once fusion has described the rooms"
                )
            query = embed(EmbedRequest(text=req.text, image=req.image))
            if req.target == "rooms":
                others = self._other_labels(index, req.text, embed) if req.text is not None else None
                return QueryReply(graph_seq=index.graph_seq, rooms=self.rank_rooms(index, query, req.top_k, others=others))
            rooms: list[RoomHit] = []
            room = req.room
            if req.room_text is not None:
                others = self._other_labels(index, req.room_text, embed)
                rooms = self.rank_rooms(index, embed(EmbedRequest(text=req.room_text)), req.top_k, what="the room_text embedding", others=others)
                room = rooms[0].room
                log.debug("room_text %r: room %d (score %.3f) of %d", req.room_text, room, rooms[0].score, len(index.room_nodes))
            hits = self.rank(index, req, query, room=room)
        except QueryError as exc:
            return QueryReply(graph_seq=index.graph_seq, error=str(exc))
        return QueryReply(graph_seq=index.graph_seq, hits=hits, rooms=rooms)

    def _other_labels(self, index: QueryIndex, text: str, embed: Embed) -> Annotated[np.ndarray, "(L, D) float32"] | None:
        """The unit embeddings of the room labels other than ``text`` (case and spacing
        aside), or None without labels or room features."""
        key = " ".join(text.lower().split())
        labels = [t for t in self.room_labels if " ".join(t.lower().split()) != key]
        if not labels or not index.room_nodes:
            return None
        try:
            rows = [np.asarray(embed(EmbedRequest(text=t)), np.float32).reshape(-1) for t in labels]
        except QueryError as exc:
            # The query itself was embedded: answer it by cosine rather than not at all.
            log.warning("room labels not embedded (%s); rooms ranked by cosine", exc)
            return None
        if len({r.shape for r in rows}) != 1:
            return None
        return _unit_rows(np.stack(rows))

    def _k(self, top_k: int | None, n: int) -> int:
        return min(top_k or self.cfg.default_top_k, self.cfg.max_top_k, n)

    def rank_rooms(
        self,
        index: QueryIndex,
        embedding: Annotated[np.ndarray, "(D,) float32"],
        top_k: int | None = None,
        *,
        what: str = "the query embedding",
        others: Annotated[np.ndarray, "(L, D) float32 unit rows"] | None = None,
    ) -> list[RoomHit]:
        """The rooms with a feature, best first (ties by room id), at most ``top_k`` (capped
        as for segments); none when no room has a feature. With ``others`` (the other room
        labels' embeddings) by margin over them, else by cosine with ``embedding``."""
        if not index.room_nodes:
            return []
        emb = _checked(embedding, index.room_dim, what, "room features")
        scores = index.room_features @ _unit_rows(emb)
        margins = None
        if others is not None and others.shape[0] and others.shape[1] == index.room_dim:
            margins = scores - (index.room_features @ others.T).max(axis=1)
        key = scores if margins is None else margins
        ids = index.room_feature_ids
        order = np.lexsort((ids, -key))[: self._k(top_k, len(ids))]
        hits = []
        for i in order.tolist():
            r = index.room_nodes[i]
            hits.append(
                RoomHit(
                    room=r.id, score=float(scores[i]), margin=None if margins is None else float(margins[i]), name=r.name,
                    centroid=r.centroid, bbox_min=r.bbox_min, bbox_max=r.bbox_max,
                )  # fmt: skip
            )
        return hits

    def rank(
        self,
        index: QueryIndex,
        req: QueryRequest,
        embedding: Annotated[np.ndarray, "(D,) float32"],
        *,
        room: int | None = None,
    ) -> list[QueryHit]:
        """The segments by eq. 10, best first, filtered by ``room`` (default ``req.room``;
        the room a ``room_text`` chose) and by ``center``/``radius``."""
        room = req.room if room is None else room
        if room is not None and room not in index.room_ids:
            known = ", ".join(str(r) for r in sorted(index.room_ids)) or "none yet"
            raise QueryError(f"unknown room {room}; rooms in the graph: {known}")
        if not len(index):
            return []
        emb = _checked(embedding, index.dim, "the query embedding", "galleries")
        scores, rows = index.score(emb, req.gallery or self.cfg.gallery)
        keep = np.ones(len(index), bool)
        if room is not None:
            keep &= index.rooms == room
        if req.center is not None:
            keep &= np.linalg.norm(index.centroids - np.asarray(req.center, np.float64), axis=1) <= req.radius
        cand = np.flatnonzero(keep)
        k = self._k(req.top_k, len(cand))
        # Highest score first; equal scores by segment id, so answers are deterministic.
        order = cand[np.lexsort((cand, -scores[cand]))][:k]
        hits = []
        for i in order.tolist():
            s = index.segments[i]
            row = int(rows[i]) - int(index.row_start[i])
            hits.append(
                QueryHit(
                    segment=s.id,
                    score=float(scores[i]),
                    centroid=s.centroid,
                    bbox_min=s.bbox_min,
                    bbox_max=s.bbox_max,
                    room=s.room,
                    best_track=s.gallery_tracks[row] if 0 <= row < len(s.gallery_tracks) else None,
                )
            )
        return hits


def hit_rows(hits: list[QueryHit]) -> list[dict]:
    """Hits as the command line's ``--json`` rows (docs/architecture.md, "Command-line
    contract")."""
    return [
        {
            "segment": h.segment,
            "score": round(h.score, 6),
            "centroid": [round(float(v), 4) for v in h.centroid],
            "bbox": [[round(float(v), 4) for v in h.bbox_min], [round(float(v), 4) for v in h.bbox_max]],
            "room": h.room,
            "best_track": h.best_track,
        }
        for h in hits
    ]


def room_rows(rooms: list[RoomHit]) -> list[dict]:
    """Ranked rooms as ``trackgraph query --rooms --json`` rows (docs/architecture.md,
    "Command-line contract"); ``bbox`` is None when the room's box is unknown."""
    return [
        {
            "room": r.room,
            "score": round(r.score, 6),
            "margin": None if r.margin is None else round(r.margin, 6),
            "name": r.name,
            "centroid": [round(float(v), 4) for v in r.centroid],
            "bbox": None
            if r.bbox_min is None or r.bbox_max is None
            else [[round(float(v), 4) for v in r.bbox_min], [round(float(v), 4) for v in r.bbox_max]],
        }
        for r in rooms
    ]
