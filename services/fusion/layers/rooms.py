"""Rooms from free space, as Hydra segments them, and the builder of the places and rooms
layers with ids that stay stable from one rebuild to the next.

Deviation from the paper (docs/method.md, F5): Hydra segments rooms on its 3D places graph;
here the same erode-and-grow idea runs on the 2D free-space grid of :mod:`.places`.

Room segmentation (:func:`segment_rooms`):

1. Erode the 2D free space by ``GraphConfig.room_erosion_m`` (a cell survives when no
   non-free cell is within that distance, read off the ESDF). Doorways narrower than twice
   the erosion close, so the rooms on either side fall apart.
2. The 4-connected components of the eroded space are room seeds.
3. Grow the seeds back over the un-eroded free space: every free cell goes to the
   geodesically nearest seed cell (multi-source Dijkstra on the free grid), so a doorway is
   split where the two rooms' fronts meet and corridors too thin to survive the erosion
   are shared among the rooms they join.
4. Rooms whose grown area is below ``GraphConfig.min_room_area_m2`` are dropped and the
   others grow again into their space (a closet joins the room it opens onto).
5. Each place takes the room of its grid cell; a room's centroid is the mean of its places
   (of its cells, lifted to place height, if it has none).

Ids (:class:`HierarchyBuilder`): a rebuilt place takes the id of the nearest previous place
within half the place spacing (greedy one-to-one, closest pairs first); a rebuilt room takes
the id of the previous room that most of its places belonged to. Everything unmatched gets
a fresh id from a counter that only grows (after a restart it resumes above the largest saved
id), so a receiver cannot mistake a new node for an old one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from services.fusion.layers.places import (
    FreeSpaceMap,
    FreeSpaceParams,
    PlaceLayout,
    extract_places,
    geodesic_owner,
    place_outlines,
)
from shared.config.fusion import GraphConfig
from shared.graph.scene import PlaceGraph
from shared.messages.graph import PlaceNode, RoomNode

log = logging.getLogger(__name__)

_CROSS = ndimage.generate_binary_structure(2, 1)


@dataclass
class RoomLayout:
    """Rooms of one rebuild, indexed 0..R-1 (largest first)."""

    labels: Annotated[np.ndarray, "(H, W) int32 room index per cell, -1 none"]
    areas_m2: Annotated[np.ndarray, "(R,) float64"]
    centroids: Annotated[np.ndarray, "(R, 3) float64 world metres"]
    place_room: Annotated[np.ndarray, "(P,) int64 room index of each place, -1 none"]

    def __len__(self) -> int:
        return int(self.areas_m2.shape[0])


def segment_rooms(
    fs: FreeSpaceMap,
    place_cells: Annotated[np.ndarray, "(P, 2) int grid cells of the places"],
    place_positions: Annotated[np.ndarray, "(P, 3) float world metres"],
    cfg: GraphConfig | None = None,
) -> RoomLayout:
    """Rooms by erosion, seeding and regrowth of the floor inside the walls (module docstring)."""
    cfg = cfg or GraphConfig()
    cell_area = fs.resolution**2
    space = fs.free if fs.interior is None else fs.interior
    # Distance to the nearest cell outside the room space: walls and unmapped floor, never
    # furniture, so a furnished room keeps one core.
    clearance = ndimage.distance_transform_edt(space) * fs.resolution
    eroded = space & (clearance > cfg.room_erosion_m)
    comp, n = ndimage.label(eroded, structure=_CROSS)
    labels = np.full(fs.shape, -1, np.int32)
    keep = np.arange(1, n + 1)
    for _ in range(2):
        if keep.size == 0:
            labels[:] = -1
            break
        seeds = np.argwhere(np.isin(comp, keep))
        owner = geodesic_owner(space, seeds)
        seed_room = np.searchsorted(keep, comp[seeds[:, 0], seeds[:, 1]])
        labels = np.where(owner >= 0, seed_room[np.maximum(owner, 0)], -1).astype(np.int32)
        area = np.bincount(labels[labels >= 0], minlength=keep.size) * cell_area
        big = area >= cfg.min_room_area_m2
        if big.all():
            break
        log.debug("rooms: dropping %d seeds under %.1f m2", int((~big).sum()), cfg.min_room_area_m2)
        keep = keep[big]

    r = int(labels.max()) + 1 if labels.size and labels.max() >= 0 else 0
    area = np.bincount(labels[labels >= 0], minlength=r).astype(np.float64) * cell_area
    # Largest first, ties by the first cell in row-major order: independent of label numbering.
    uniq, first_at = np.unique(labels.ravel(), return_index=True)
    first = first_at[uniq >= 0].astype(np.int64)
    order = np.lexsort((first, -area))
    remap = np.full(r + 1, -1, np.int32)
    remap[order] = np.arange(r, dtype=np.int32)
    labels = remap[labels]
    area = area[order]

    pc = np.asarray(place_cells, np.int64).reshape(-1, 2)
    pos = np.asarray(place_positions, np.float64).reshape(-1, 3)
    if pc.size and r:
        # A place on free space the room space left out (past a gap in the wall band) takes
        # the room of the nearest room cell.
        _, near = ndimage.distance_transform_edt(labels < 0, return_indices=True)
        place_room = labels[near[0][pc[:, 0], pc[:, 1]], near[1][pc[:, 0], pc[:, 1]]].astype(np.int64)
    else:
        place_room = np.full(pc.shape[0], -1, np.int64)
    centroids = np.zeros((r, 3))
    for k in range(r):
        mine = place_room == k
        if mine.any():
            centroids[k] = pos[mine].mean(axis=0)
        else:
            xy = fs.center_of(np.argwhere(labels == k)).mean(axis=0)
            centroids[k] = [xy[0], xy[1], fs.place_z]
    return RoomLayout(labels=labels, areas_m2=area, centroids=centroids, place_room=place_room)


def room_boxes(
    fs: FreeSpaceMap, rooms: RoomLayout, points: Annotated[np.ndarray, "(N, 3) float world metres"]
) -> Annotated[np.ndarray, "(R, 2, 3) float64 min and max corner of each room"]:
    """Each room's box: its footprint's cells in xy, from the floor to the highest surface
    over the footprint or its walls (the ceiling, where it was seen) in z."""
    r = len(rooms)
    out = np.zeros((r, 2, 3))
    if r == 0:
        return out
    c = fs.cell_of(points)
    inside = (c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 0] < fs.shape[0]) & (c[:, 1] < fs.shape[1])
    # The walls around a room stand on cells just outside it: a point within two cells of a
    # room belongs to its box, so the box reaches the wall tops where no ceiling was seen.
    dist, (ni, nj) = ndimage.distance_transform_edt(rooms.labels < 0, return_indices=True)
    near = np.where(dist <= 2.0, rooms.labels[ni, nj], -1)
    lab = np.full(len(points), -1, np.int64)
    lab[inside] = near[c[inside, 0], c[inside, 1]]
    top = np.full(r, fs.place_z)
    mine = lab >= 0
    np.maximum.at(top, lab[mine], points[mine, 2])
    for k, box in enumerate(ndimage.find_objects(rooms.labels + 1, max_label=r)):
        if box is None:
            continue
        lo = (np.array([box[0].start, box[1].start]) + fs.origin_cell) * fs.resolution
        hi = (np.array([box[0].stop, box[1].stop]) + fs.origin_cell) * fs.resolution
        out[k, 0] = [lo[0], lo[1], fs.floor_z]
        out[k, 1] = [hi[0], hi[1], max(top[k], fs.floor_z)]
    return out


def match_by_distance(
    prev_ids: Annotated[np.ndarray, "(Q,) int64"],
    prev_pos: Annotated[np.ndarray, "(Q, 3) float"],
    new_pos: Annotated[np.ndarray, "(P, 3) float"],
    max_dist: float,
) -> Annotated[np.ndarray, "(P,) int64 matched previous id, -1 none"]:
    """Greedy one-to-one matching, closest pairs first, within ``max_dist``."""
    out = np.full(new_pos.shape[0], -1, np.int64)
    if prev_ids.size == 0 or new_pos.shape[0] == 0:
        return out
    pairs = cKDTree(new_pos).sparse_distance_matrix(cKDTree(prev_pos), max_dist, output_type="ndarray")
    if pairs.size == 0:
        return out
    order = np.lexsort((pairs["j"], pairs["i"], pairs["v"]))
    used = np.zeros(prev_ids.size, bool)
    for i, j in zip(pairs["i"][order], pairs["j"][order], strict=True):
        if out[i] < 0 and not used[j]:
            out[i] = prev_ids[j]
            used[j] = True
    return out


def match_by_votes(
    votes: Annotated[np.ndarray, "(K, 2) int64 (new index, previous id) one row per vote"],
    n_new: int,
) -> Annotated[np.ndarray, "(n_new,) int64 matched previous id, -1 none"]:
    """Greedy one-to-one matching by vote count, most votes first."""
    out = np.full(n_new, -1, np.int64)
    if votes.size == 0:
        return out
    pairs, counts = np.unique(votes, axis=0, return_counts=True)
    used: set[int] = set()
    for k in np.lexsort((pairs[:, 1], pairs[:, 0], -counts)):
        i, prev = int(pairs[k, 0]), int(pairs[k, 1])
        if out[i] < 0 and prev not in used:
            out[i] = prev
            used.add(prev)
    return out


@dataclass
class Hierarchy:
    """One rebuild of the places and rooms layers."""

    places: PlaceGraph
    rooms: list[RoomNode]
    layout: PlaceLayout
    room_layout: RoomLayout


class HierarchyBuilder:
    """Rebuilds places and rooms from the mapped surfaces, keeping node ids stable."""

    def __init__(self, cfg: GraphConfig | None = None, params: FreeSpaceParams | None = None) -> None:
        self.cfg = cfg or GraphConfig()
        self.params = params or FreeSpaceParams()
        self._places: list[PlaceNode] = []
        self._rooms: list[RoomNode] = []
        self._next_place = 0
        self._next_room = 0
        self.room_ids = np.zeros(0, np.int64)
        """Room id of each room index of the last build."""
        self._outlines: dict = {}
        """Place outlines of the last build by region mask (``place_outlines``)."""

    def restore(self, places: list[PlaceNode], rooms: list[RoomNode]) -> None:
        """Continue ids from a saved graph (after a restart)."""
        self._places, self._rooms = list(places), list(rooms)
        self._next_place = max((p.id for p in places), default=-1) + 1
        self._next_room = max((r.id for r in rooms), default=-1) + 1

    def build(
        self,
        points: Annotated[np.ndarray, "(N, 3) float surface points of the whole map, world metres"],
        trajectory: Annotated[np.ndarray, "(M, 3) float camera positions"] | None = None,
        floor_z: float | None = None,
        active: tuple[Annotated[np.ndarray, "(3,) camera position"], float] | None = None,
    ) -> Hierarchy:
        """Places and rooms of the map; ``active`` (centre, radius) marks the places within
        fusion's active window (all are active without it)."""
        layout = extract_places(points, trajectory, self.cfg, self.params, floor_z)
        rooms = segment_rooms(layout.freespace, layout.cells, layout.positions, self.cfg)
        fs = layout.freespace
        outlines = place_outlines(fs, layout.owner, len(layout), self._outlines)
        if active is None:
            is_active = np.ones(len(layout), bool)
        else:
            is_active = np.linalg.norm(layout.positions - np.asarray(active[0], np.float64)[None], axis=1) <= active[1]
        boxes = room_boxes(fs, rooms, np.asarray(points, np.float64).reshape(-1, 3))

        prev_ids = np.array([p.id for p in self._places], np.int64)
        prev_pos = np.stack([p.position for p in self._places]) if self._places else np.zeros((0, 3))
        pid = match_by_distance(prev_ids, prev_pos, layout.positions, 0.5 * self.cfg.place_spacing_m)
        pid = self._fresh(pid, "_next_place")

        prev_room_of = {p.id: p.room for p in self._places if p.room is not None}
        votes = np.array(
            [(rooms.place_room[k], prev_room_of[int(i)]) for k, i in enumerate(pid) if rooms.place_room[k] >= 0 and int(i) in prev_room_of],
            np.int64,
        ).reshape(-1, 2)
        live_prev = {r.id for r in self._rooms}
        votes = votes[np.isin(votes[:, 1], list(live_prev))] if votes.size else votes
        rid = self._fresh(match_by_votes(votes, len(rooms)), "_next_room")

        place_nodes = [
            PlaceNode(
                id=int(pid[k]),
                position=layout.positions[k].astype(np.float64),
                radius=float(layout.radii[k]),
                room=int(rid[rooms.place_room[k]]) if rooms.place_room[k] >= 0 else None,
                boundary=outlines[k],
                active=bool(is_active[k]),
            )
            for k in range(len(layout))
        ]
        room_nodes = sorted(
            (
                RoomNode(
                    id=int(rid[k]), centroid=rooms.centroids[k].astype(np.float64),
                    bbox_min=boxes[k, 0], bbox_max=boxes[k, 1], area_m2=float(rooms.areas_m2[k]),
                )  # fmt: skip
                for k in range(len(rooms))
            ),
            key=lambda r: r.id,
        )
        self.room_ids = rid.astype(np.int64)
        edges = [(int(pid[a]), int(pid[b])) for a, b in layout.edges]

        def locate(pts: np.ndarray) -> np.ndarray:
            idx = layout.place_index_of(pts)
            return np.where(idx >= 0, pid[np.maximum(idx, 0)] if pid.size else -1, -1)

        self._places, self._rooms = place_nodes, room_nodes
        log.info("hierarchy: %d places, %d edges, %d rooms", len(place_nodes), len(edges), len(room_nodes))
        return Hierarchy(
            places=PlaceGraph(nodes=sorted(place_nodes, key=lambda p: p.id), edges=edges, locate=locate),
            rooms=room_nodes,
            layout=layout,
            room_layout=rooms,
        )

    def _fresh(self, ids: np.ndarray, counter: str) -> np.ndarray:
        ids = ids.copy()
        for k in np.flatnonzero(ids < 0):
            ids[k] = getattr(self, counter)
            setattr(self, counter, ids[k] + 1)
        return ids
