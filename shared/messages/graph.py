"""Scene-graph deltas and snapshots (``graph/delta``, ``graph/snapshot``)."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from shared.arrays import ArraySpec
from shared.messages.base import METRES, Message, register
from shared.messages.keyframes import FeatureRows, Vector

Vec3 = Annotated[np.ndarray, ArraySpec(("float64",), (3,), finite=True)]
Vertices = Annotated[np.ndarray, ArraySpec(("float32",), (None, 3), finite=True)]
Colors = Annotated[np.ndarray, ArraySpec(("uint8",), (None, 3))]
Faces = Annotated[np.ndarray, ArraySpec(("int32",), (None, 3))]
VertexIds = Annotated[np.ndarray, ArraySpec(("int32",), (None,))]
Polygon = Annotated[np.ndarray, ArraySpec(("float64",), (None, 2), finite=True)]
Poses = Annotated[np.ndarray, ArraySpec(("float64",), (None, 7), finite=True)]
FrameIndices = Annotated[np.ndarray, ArraySpec(("int64",), (None,))]


class SegmentNode(Message):
    """A persistent class-agnostic 3D segment (III-A's N_S)."""

    id: int = Field(ge=0)
    """Segment id, stable for the life of the map."""
    centroid: Annotated[Vec3, METRES]
    """Centroid of its vertices (m, world)."""
    bbox_min: Annotated[Vec3, METRES]
    """Axis-aligned box corner (m, world)."""
    bbox_max: Annotated[Vec3, METRES]
    """Axis-aligned box corner (m, world)."""
    tracks: list[int]
    """Source tracks assigned to the segment (T)."""
    dino: Vector
    """Aggregated DINOv3 feature."""
    gallery: FeatureRows
    """(T', D) CLIP gallery, one row per track with a CLIP feature (III-F)."""
    gallery_tracks: list[int]
    """Track id of each gallery row."""
    gallery_weights: list[float] = Field(default_factory=list)
    """Share of the segment's hypothesis weight held by each gallery row's track (0-1), so a
    query can leave out views of tracks that barely make up the segment; empty if unknown."""
    active: bool
    """Active (in the window) or historical."""
    room: int | None = None
    """Room the segment lies in, if known."""
    num_vertices: int = Field(0, ge=0)
    """Mesh vertices assigned to the segment."""

    @model_validator(mode="after")
    def _gallery(self) -> SegmentNode:
        """``gallery`` has one row per ``gallery_tracks`` entry, a subset of ``tracks``; ``gallery_weights`` is empty or
        one value in [0, 1] per row; ``bbox_min`` <= ``bbox_max``."""
        if self.gallery.shape[0] != len(self.gallery_tracks):
            raise ValueError(f"gallery has {self.gallery.shape[0]} rows for {len(self.gallery_tracks)} tracks")
        if not set(self.gallery_tracks) <= set(self.tracks):
            raise ValueError("gallery_tracks must be a subset of tracks")
        if self.gallery_weights and len(self.gallery_weights) != len(self.gallery_tracks):
            raise ValueError(f"gallery_weights has {len(self.gallery_weights)} entries for {len(self.gallery_tracks)} gallery rows")
        if any(not (0.0 <= w <= 1.0) for w in self.gallery_weights):
            raise ValueError("gallery_weights must lie in [0, 1]")
        if np.any(self.bbox_min > self.bbox_max):
            raise ValueError("bbox_min exceeds bbox_max")
        return self


class PlaceNode(Message):
    """A sparse free-space place."""

    id: int = Field(ge=0)
    """Place id."""
    position: Annotated[Vec3, METRES]
    """Position (m, world)."""
    radius: Annotated[float, METRES] = Field(ge=0)
    """Distance to the nearest obstacle (m)."""
    room: int | None = None
    """Room containing the place."""
    boundary: Annotated[Polygon, METRES] = Field(default_factory=lambda: np.zeros((0, 2)))
    """(B, 2) outline of the free space the place stands for (its geodesic region on the
    free-space grid), world xy, counter-clockwise; empty if unknown."""
    active: bool = False
    """Within fusion's active window around the camera (Hydra's active flag): it may still
    change; an inactive place is history."""


class RoomNode(Message):
    """A room: a region of free space."""

    id: int = Field(ge=0)
    """Room id."""
    centroid: Annotated[Vec3, METRES]
    """Centroid of its places (m, world)."""
    name: str = ""
    """Its best label among ``GraphConfig.room_labels`` by ``feature`` (e.g. "bedroom"); ""
    while it has no feature or fusion has no label embeddings yet."""
    bbox_min: Annotated[Vec3, METRES] | None = None
    """Axis-aligned box corner of its free space, floor to ceiling (m, world); None if unknown."""
    bbox_max: Annotated[Vec3, METRES] | None = None
    """Axis-aligned box corner (m, world); None if unknown."""
    area_m2: float = Field(0.0, ge=0)
    """Area of its free-space footprint (m^2)."""
    feature: Vector | None = None
    """(D,) L2-normalised open-vocabulary feature in the VL encoder's space: the keyframe views
    taken from inside the room and the CLIP galleries of its segments, pooled
    (``GraphConfig.room_view_weight``); None before either exists. Text such as "kitchen" is
    ranked against it."""
    name_score: float | None = None
    """Cosine between ``feature`` and the embedding of ``name`` (its label in
    ``GraphConfig.room_labels``); None when the room has no name."""


class Edge(Message):
    """An edge between two nodes of the hierarchy."""

    kind: Literal["segment_place", "place_place", "place_room", "room_building"]
    """Which layers it joins."""
    source: int = Field(ge=0)
    """Lower-layer node id."""
    target: int = Field(ge=0)
    """Upper-layer (or same-layer) node id."""


class MeshChunk(Message):
    """A mesh with each vertex's winning segment: the active window's, or with
    ``SnapshotRequest.whole_map`` the whole map's."""

    vertices: Annotated[Vertices, METRES]
    """(V, 3) float32 positions (world)."""
    colors: Colors
    """(V, 3) uint8 colours."""
    faces: Faces
    """(F, 3) int32 vertex indices."""
    segment_ids: VertexIds
    """(V,) int32 segment id per vertex, -1 for none."""

    @model_validator(mode="after")
    def _sizes(self) -> MeshChunk:
        """``colors`` and ``segment_ids`` have one row per vertex; ``faces`` index existing vertices."""
        v = self.vertices.shape[0]
        if self.colors.shape[0] != v or self.segment_ids.shape[0] != v:
            raise ValueError("colors and segment_ids need one row per vertex")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= v):
            raise ValueError(f"faces index outside 0..{v - 1}")
        return self


@register
class GraphDelta(Message):
    """Changes since graph_seq - 1. A receiver that sees a gap asks for a snapshot."""

    graph_seq: int = Field(ge=0)
    """Graph version after applying this delta."""
    frame_index: int = Field(ge=-1)
    """Last frame fused into this version."""
    segments: list[SegmentNode] = Field(default_factory=list)
    """Segments added or changed."""
    removed_segments: list[int] = Field(default_factory=list)
    """Segments removed (merged by re-identification)."""
    places: list[PlaceNode] = Field(default_factory=list)
    """Places added or changed."""
    removed_places: list[int] = Field(default_factory=list)
    """Places removed."""
    rooms: list[RoomNode] = Field(default_factory=list)
    """Rooms added or changed."""
    removed_rooms: list[int] = Field(default_factory=list)
    """Rooms removed."""
    edges: list[Edge] = Field(default_factory=list)
    """Edges added."""
    removed_edges: list[Edge] = Field(default_factory=list)
    """Edges removed."""
    mesh: MeshChunk | None = None
    """The active-window mesh, in every Nth delta."""


@register
class GraphSnapshot(Message):
    """The whole graph at one version (reply of the ``graph/snapshot`` queryable)."""

    graph_seq: int = Field(ge=0)
    """Graph version."""
    frame_index: int = Field(ge=-1)
    """Last frame fused."""
    segments: list[SegmentNode] = Field(default_factory=list)
    """All segments."""
    places: list[PlaceNode] = Field(default_factory=list)
    """All places."""
    rooms: list[RoomNode] = Field(default_factory=list)
    """All rooms."""
    edges: list[Edge] = Field(default_factory=list)
    """All edges."""
    mesh: MeshChunk | None = None
    """The mesh, if asked for: the active window's, or with ``whole_map`` the whole map's."""
    trajectory: Annotated[Poses, METRES] = Field(default_factory=lambda: np.zeros((0, 7)))
    """(M, 7) camera poses fused, ``x y z qx qy qz qw`` (world, camera-to-world), for the
    agent layer; empty in replies that do not carry it."""
    trajectory_frames: FrameIndices = Field(default_factory=lambda: np.zeros(0, np.int64))
    """(M,) frame index of each ``trajectory`` row."""
    error: str | None = None
    """Why the mesh asked for is not in this reply (the graph still is), e.g. a whole-map mesh
    over the codec's array limits; None when the reply is everything asked for."""


@register
class SnapshotRequest(Message):
    """Request of the ``graph/snapshot`` queryable."""

    with_mesh: bool = False
    """Include the active window's mesh (large)."""
    whole_map: bool = False
    """Include the whole map's mesh instead, the active window's and the archived blocks', as
    the saved map has it (implies ``with_mesh``). Fusion runs marching cubes over the archive
    for it while frames wait, so ask for it rarely (a viewer joining, an export), not per delta."""
