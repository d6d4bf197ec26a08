"""The scene graph above the mesh: segments, places, rooms and the building, versioned.

The fusion service owns a :class:`SceneGraph`. Each :meth:`SceneGraph.apply_update` takes
what the stages below produced (changed and removed segments, a rebuilt place layer, rooms,
the mesh), recomputes the derived edges, diffs against the previous version, bumps
``graph_seq`` and returns the :class:`GraphDelta` to publish. Receivers (the query service,
viewers) hold a :class:`GraphReplica` that applies those deltas in order and asks for a
snapshot when it sees a gap.

Edges (paper III-A; docs/method.md, "Scene graph"):

- ``segment_place``: each segment to its nearest place. With a free-space layout the
  nearest place is found through the grid (the place whose region is nearest the centroid),
  so a segment on a wall is attached on the side it was seen from; otherwise Euclidean.
- ``place_place``: traversable neighbours, as given by the place layer.
- ``place_room``: each place to the room it lies in (``PlaceNode.room``).
- ``room_building``: every room to the single building node, id :data:`BUILDING_ID`.

Segments carry the room of their place in ``SegmentNode.room``; the graph fills it in.

Only real changes reach a delta: nodes equal to their previous version (arrays compared by
value) are left out, and a place that moved less than ``place_tolerance_m`` keeps its
previous version, so rebuilding the places from nearly the same geometry does not churn.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Annotated

import numpy as np
from pydantic import BaseModel
from scipy.spatial import cKDTree

from shared.messages.graph import (
    Edge,
    GraphDelta,
    GraphSnapshot,
    MeshChunk,
    PlaceNode,
    RoomNode,
    SegmentNode,
)

log = logging.getLogger(__name__)

BUILDING_ID = 0
"""Id of the one building node (the wire format has no building message; it is implicit)."""

EdgeKey = tuple[str, int, int]
Locator = Callable[[Annotated[np.ndarray, "(N, 3) float64"]], Annotated[np.ndarray, "(N,) int64 place id, -1 none"]]
RoomDescriber = Callable[[dict[int, SegmentNode], dict[int, RoomNode], dict[int, RoomNode]], dict[int, RoomNode]]
"""(segments, new rooms, previous rooms) -> the new rooms, same ids, attributes filled in."""

_KIND_ORDER = {"segment_place": 0, "place_place": 1, "place_room": 2, "room_building": 3}


@dataclass
class PlaceGraph:
    """One build of the places layer: the nodes (with their room), the traversable
    place-place edges, and optionally a locator mapping points to their nearest place."""

    nodes: list[PlaceNode]
    edges: list[tuple[int, int]] = field(default_factory=list)
    locate: Locator | None = None


def same_node(a: BaseModel, b: BaseModel) -> bool:
    """Field-by-field equality, arrays by dtype, shape and value."""
    if type(a) is not type(b):
        return False
    for name in type(a).model_fields:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (
                isinstance(x, np.ndarray)
                and isinstance(y, np.ndarray)
                and x.dtype == y.dtype
                and x.shape == y.shape
                and np.array_equal(x, y)
            ):
                return False
        elif isinstance(x, BaseModel) or isinstance(y, BaseModel):
            if x is None or y is None or not same_node(x, y):
                return False
        elif x != y:
            return False
    return True


def edge_key(e: Edge) -> EdgeKey:
    return (e.kind, e.source, e.target)


def _sorted_edges(keys: Iterable[EdgeKey]) -> list[Edge]:
    return [Edge(kind=k, source=s, target=t) for k, s, t in sorted(keys, key=lambda x: (_KIND_ORDER[x[0]], x[1], x[2]))]


def _snapshot(g: SceneGraph | GraphReplica, with_mesh: bool) -> GraphSnapshot:
    """The whole graph at its version, nodes sorted by id and edges by kind."""
    return GraphSnapshot(
        graph_seq=g.graph_seq,
        frame_index=g.frame_index,
        segments=_by_id(g.segments),
        places=_by_id(g.places),
        rooms=_by_id(g.rooms),
        edges=_sorted_edges(g.edges),
        mesh=g.mesh if with_mesh else None,
    )


def _by_id(nodes: dict[int, BaseModel]) -> list:
    return [nodes[i] for i in sorted(nodes)]


class SceneGraph:
    """The authoritative, versioned graph in the fusion service."""

    def __init__(self, place_tolerance_m: float = 1e-3) -> None:
        self.graph_seq = 0
        self.frame_index = -1
        self.place_tolerance_m = float(place_tolerance_m)
        self.segments: dict[int, SegmentNode] = {}
        self.places: dict[int, PlaceNode] = {}
        self.rooms: dict[int, RoomNode] = {}
        self.edges: set[EdgeKey] = set()
        self.mesh: MeshChunk | None = None
        self._place_edges: list[tuple[int, int]] = []
        self._locate: Locator | None = None

    # ------------------------------------------------------------ updates

    def apply_update(
        self,
        segments_changed: Sequence[SegmentNode] = (),
        segments_removed: Iterable[int] = (),
        places: PlaceGraph | None = None,
        rooms: Sequence[RoomNode] | None = None,
        mesh: MeshChunk | None = None,
        frame_index: int | None = None,
        describe_rooms: RoomDescriber | None = None,
    ) -> GraphDelta:
        """Apply one update and return the delta to the previous version.

        ``places`` / ``rooms`` of None leave those layers as they are; a value replaces the
        layer (nodes missing from it are removed). A segment both changed and removed is
        removed. Edges pointing at nodes that do not exist are dropped. ``describe_rooms``
        gets the new segments (with their rooms), the new rooms and the previous rooms, and
        returns the rooms to keep, e.g. with features read off their segments.
        """
        segs = dict(self.segments)
        for s in segments_changed:
            segs[s.id] = s
        for sid in segments_removed:
            segs.pop(int(sid), None)

        new_places = self.places
        if places is not None:
            new_places = {}
            for p in places.nodes:
                old = self.places.get(p.id)
                new_places[p.id] = old if old is not None and self._place_close(old, p) else p
            self._place_edges = [(min(a, b), max(a, b)) for a, b in places.edges if a != b]
            self._locate = places.locate
        new_rooms = self.rooms if rooms is None else {r.id: r for r in rooms}

        seg_place = self._nearest_places(segs, new_places)
        edges: set[EdgeKey] = set()
        for sid, pid in seg_place.items():
            edges.add(("segment_place", sid, pid))
        for a, b in self._place_edges:
            if a in new_places and b in new_places:
                edges.add(("place_place", a, b))
        for p in new_places.values():
            if p.room is not None and p.room in new_rooms:
                edges.add(("place_room", p.id, p.room))
        for rid in new_rooms:
            edges.add(("room_building", rid, BUILDING_ID))

        for sid, s in segs.items():
            pid = seg_place.get(sid)
            room = new_places[pid].room if pid is not None else None
            room = room if room in new_rooms else None
            if s.room != room:
                segs[sid] = s.model_copy(update={"room": room})
        if describe_rooms is not None:
            new_rooms = describe_rooms(segs, new_rooms, self.rooms)

        delta = GraphDelta(
            graph_seq=self.graph_seq + 1,
            frame_index=self.frame_index if frame_index is None else int(frame_index),
            segments=self._changed(self.segments, segs),
            removed_segments=sorted(set(self.segments) - set(segs)),
            places=self._changed(self.places, new_places),
            removed_places=sorted(set(self.places) - set(new_places)),
            rooms=self._changed(self.rooms, new_rooms),
            removed_rooms=sorted(set(self.rooms) - set(new_rooms)),
            edges=_sorted_edges(edges - self.edges),
            removed_edges=_sorted_edges(self.edges - edges),
            mesh=mesh,
        )
        self.segments, self.places, self.rooms, self.edges = segs, new_places, new_rooms, edges
        if mesh is not None:
            self.mesh = mesh
        self.graph_seq = delta.graph_seq
        self.frame_index = delta.frame_index
        log.debug(
            "graph %d: %d/%d segments changed/removed, %d/%d places, %d/%d rooms, +%d/-%d edges",
            self.graph_seq, len(delta.segments), len(delta.removed_segments), len(delta.places),
            len(delta.removed_places), len(delta.rooms), len(delta.removed_rooms),
            len(delta.edges), len(delta.removed_edges),
        )  # fmt: skip
        return delta

    def _place_close(self, old: PlaceNode, new: PlaceNode) -> bool:
        return (
            old.room == new.room
            and old.active == new.active
            and old.boundary.shape == new.boundary.shape
            and np.allclose(old.boundary, new.boundary, rtol=0.0, atol=self.place_tolerance_m)
            and abs(old.radius - new.radius) <= self.place_tolerance_m
            and float(np.linalg.norm(old.position - new.position)) <= self.place_tolerance_m
        )

    @staticmethod
    def _changed(old: dict[int, BaseModel], new: dict[int, BaseModel]) -> list:
        return [new[i] for i in sorted(new) if i not in old or not (old[i] is new[i] or same_node(old[i], new[i]))]

    def _nearest_places(self, segs: dict[int, SegmentNode], places: dict[int, PlaceNode]) -> dict[int, int]:
        if not segs or not places:
            return {}
        sids = sorted(segs)
        centroids = np.stack([segs[i].centroid for i in sids])
        found = np.full(len(sids), -1, np.int64)
        if self._locate is not None:
            found = np.asarray(self._locate(centroids), np.int64)
            # The locator belongs to one build of the places; a place it names may have
            # been removed since (or the places set by hand), so check membership.
            found = np.where(np.isin(found, list(places)), found, -1)
        missing = found < 0
        if missing.any():
            pids = np.array(sorted(places), np.int64)
            tree = cKDTree(np.stack([places[i].position for i in pids]))
            _, k = tree.query(centroids[missing])
            found[missing] = pids[np.asarray(k, np.int64)]
        return {sid: int(pid) for sid, pid in zip(sids, found, strict=True)}

    # ------------------------------------------------------------ snapshots

    def snapshot(self, with_mesh: bool = False) -> GraphSnapshot:
        """The whole graph at this version, nodes sorted by id and edges by kind."""
        return _snapshot(self, with_mesh)

    @classmethod
    def from_snapshot(cls, snap: GraphSnapshot, place_tolerance_m: float = 1e-3) -> SceneGraph:
        """Resume from a saved snapshot; versions continue from its graph_seq."""
        g = cls(place_tolerance_m)
        g.graph_seq, g.frame_index = snap.graph_seq, snap.frame_index
        g.segments = {s.id: s for s in snap.segments}
        g.places = {p.id: p for p in snap.places}
        g.rooms = {r.id: r for r in snap.rooms}
        g.edges = {edge_key(e) for e in snap.edges}
        g._place_edges = sorted((e.source, e.target) for e in snap.edges if e.kind == "place_place")
        g.mesh = snap.mesh
        return g

    def place_graph(self) -> PlaceGraph:
        """The current place layer, e.g. to seed a hierarchy builder after a restart."""
        return PlaceGraph(nodes=_by_id(self.places), edges=list(self._place_edges), locate=self._locate)


class ApplyResult(str, Enum):
    """What a replica did with a delta."""

    APPLIED = "applied"
    STALE = "stale"
    """graph_seq not newer than the replica's: a duplicate, ignored."""
    NEED_SNAPSHOT = "need_snapshot"
    """A gap in graph_seq: the replica stays at its version until it gets a snapshot."""


class GraphReplica:
    """Receiver-side copy of the graph, kept in step by deltas.

    A new replica is at version 0 (empty), which is where a new :class:`SceneGraph` starts,
    so a receiver that is there from the beginning never needs a snapshot. A fusion service
    resumed from disk continues its graph_seq, so an old replica sees a gap, not a reset.
    """

    def __init__(self) -> None:
        self.graph_seq = 0
        self.frame_index = -1
        self.segments: dict[int, SegmentNode] = {}
        self.places: dict[int, PlaceNode] = {}
        self.rooms: dict[int, RoomNode] = {}
        self.edges: set[EdgeKey] = set()
        self.mesh: MeshChunk | None = None

    def apply_delta(self, delta: GraphDelta) -> ApplyResult:
        if delta.graph_seq <= self.graph_seq:
            return ApplyResult.STALE
        if delta.graph_seq != self.graph_seq + 1:
            log.info("graph delta %d after %d: gap, need a snapshot", delta.graph_seq, self.graph_seq)
            return ApplyResult.NEED_SNAPSHOT
        for e in delta.removed_edges:
            self.edges.discard(edge_key(e))
        for table, removed, changed in (
            (self.segments, delta.removed_segments, delta.segments),
            (self.places, delta.removed_places, delta.places),
            (self.rooms, delta.removed_rooms, delta.rooms),
        ):
            for i in removed:
                table.pop(i, None)
            for n in changed:
                table[n.id] = n
        self.edges.update(edge_key(e) for e in delta.edges)
        self._drop_dangling()
        if delta.mesh is not None:
            self.mesh = delta.mesh
        self.graph_seq, self.frame_index = delta.graph_seq, delta.frame_index
        return ApplyResult.APPLIED

    def apply_snapshot(self, snap: GraphSnapshot) -> None:
        """Replace everything with the snapshot (authoritative, even if older). A snapshot
        without a mesh keeps the replica's mesh."""
        self.graph_seq, self.frame_index = snap.graph_seq, snap.frame_index
        self.segments = {s.id: s for s in snap.segments}
        self.places = {p.id: p for p in snap.places}
        self.rooms = {r.id: r for r in snap.rooms}
        self.edges = {edge_key(e) for e in snap.edges}
        if snap.mesh is not None:
            self.mesh = snap.mesh
        self._drop_dangling()

    def snapshot(self, with_mesh: bool = False) -> GraphSnapshot:
        return _snapshot(self, with_mesh)

    def _drop_dangling(self) -> None:
        layers = {
            "segment_place": (self.segments, self.places),
            "place_place": (self.places, self.places),
            "place_room": (self.places, self.rooms),
            "room_building": (self.rooms, None),
        }
        bad = set()
        for k in self.edges:
            lo, hi = layers[k[0]]
            if k[1] not in lo or (hi is not None and k[2] not in hi):
                bad.add(k)
        if bad:
            log.warning("graph replica: dropping %d edges to missing nodes", len(bad))
            self.edges -= bad
