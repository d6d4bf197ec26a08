"""Export of the scene graph to spark_dsg (Hydra's scene-graph library, 1.1) and back.

A saved ``.sparkdsg`` opens in Hydra's tools with the layers, partitions, symbols and
attribute types Hydra itself writes. The graph is built with Hydra's layer map
(``hydra::SharedDsgInfo::Config``), every key taken from
``spark_dsg.DsgLayers.name_to_layer_id`` and saved with the file's layer names:
``OBJECTS`` 2, ``AGENTS`` 2, ``PLACES`` 3, ``MESH_PLACES`` 3[1], ``ROOMS`` 4, ``BUILDINGS`` 5.

| ours | layer | symbol | spark_dsg attributes |
|---|---|---|---|
| segment | ``OBJECTS`` | ``O<id>`` | ``ObjectNodeAttributes``: box, CLIP gallery as ``semantic_feature``, mesh connections, colour |
| place | ``PLACES`` | ``p<id>`` | ``PlaceNodeAttributes``: ``distance`` = radius, ``is_active``, ``real_place``, colour |
| place outline | ``MESH_PLACES`` | ``Q<id>`` | ``Place2dNodeAttributes``: ``boundary``, Hydra's ellipse, ``is_active``, colour |
| room | ``ROOMS`` | ``R<id>`` | ``RoomNodeAttributes``: name, box, ``semantic_label``, colour, feature as a one-row ``semantic_feature`` |
| building | ``BUILDINGS`` | ``B0`` | ``SemanticNodeAttributes`` at the mean of the room centroids |
| camera pose | ``AGENTS``, partition ``'a'`` | ``a<row>`` | ``AgentNodeAttributes``: position, ``world_R_body``, timestamp |
| mesh | the graph's mesh | | positions, segment colours, per-vertex label = segment id |

**Places: two nodes, one per Hydra place type.** No spark_dsg 1.1 attribute type holds both
a free-space distance and an outline: ``PlaceNodeAttributes`` has ``distance`` and no
boundary, ``Place2dNodeAttributes`` a ``boundary`` and no distance (the third,
``TraversabilityNodeAttributes``, has a grid-aligned box, not a polygon, and Hydra writes no
such layer). Hydra writes its GVD places into ``PLACES`` as ``PlaceNodeAttributes`` with
prefix ``p``, and its code reads them as such: the room finder, the MST factors, the
frontier and descriptor code call ``attributes<PlaceNodeAttributes>()`` on ``PLACES`` nodes
and read ``distance``, and ``UpdateRoomsFunctor`` keeps nodes of category ``p``. Its 2D
places go into ``MESH_PLACES`` (layer 3, partition 1) as ``Place2dNodeAttributes`` with
prefix ``Q`` (``Place2dSegmenter``): ``boundary`` (the convex hull of the region, 3D
points), ``ellipse_centroid`` and ``ellipse_matrix_expand/compress`` from the minimum-area
rectangle (``addRectInfo``, which its place-connection test reads). So each place is a ``p``
node carrying the hierarchy (segment -> place -> room edges, the distance, the active flag)
and, when it has an outline, a ``Q`` node with the same id carrying it: the outline as
written (world xy at the place's height, in its own order, so it reads back exactly) and
the ellipse of its minimum-area rectangle as Hydra computes it. The ``Q`` nodes repeat the
place-place edges among themselves, as Hydra's 2D places have edges of their own.

**Derived edges**, written for Hydra's tools and skipped by :func:`from_dsg`, which rebuilds
them on the next export: consecutive agent nodes are joined (Hydra's pose-graph odometry
edges); each agent node is a child of one place (Hydra's ``LayerConnector`` makes the
nearest place the single parent of every node of layer 2, agents included): the nearest
place whose outline contains the pose's xy, else the nearest place; rooms whose places are
joined by a place-place edge are joined (``addEdgesToRoomLayer``).

**Agents** follow ``PoseGraphPacket::addToGraph``: layer ``AGENTS``'s id with partition = the
robot prefix (robot 0, ``'a'``), symbol ``a<k>`` for trajectory row k (Hydra numbers pose
keys from 0, and ``UpdateFrontiersFunctor`` takes ``a<num_nodes - 1>`` as the latest pose),
``external_key`` = the node's own symbol. The snapshot carries frame indices, not clock
times, and spark_dsg's Python binding passes ``timestamp`` as a ``datetime.timedelta``
(microsecond resolution), so the timestamp is the frame index in microseconds
(``timestamp.count() == 1000 * frame`` ns): Hydra only orders agents by stamp and looks up
the nearest one. The frame index is also in the node's metadata.

**Colours and labels.** Every semantic node has a ``color``: segments the colour of
:func:`shared.graph.colors.segment_colors` for their id (the viewer's palette, so a
segment looks the same in the recording, the PNG renders and Hydra's tools), rooms the same
palette for their id, places their room's colour (grey without a room), the building grey.
Mesh vertices with a segment take their segment's colour; vertices without one keep their
RGB. With ``mesh_colors="segments"`` (the default) the original RGB of the segmented vertices
is kept in the graph metadata (``mesh_rgb``: zlib + base64 of the (V_s, 3) uint8 rows in
vertex order) so :func:`from_dsg` restores the mesh exactly; ``mesh_colors="rgb"`` writes the
RGB as is. Rooms get a ``semantic_label`` from their name in a label space registered with
``DynamicSceneGraph.set_labelspace`` on the ``ROOMS`` layer key (label 0 = ``unknown`` for an
unnamed room, as Hydra's room finder gives label 0; the other names sorted, from 1), the
building label 0 of a ``BUILDINGS`` label space ``{0: "building"}``. Segments are
class-agnostic and places are free space, so both keep ``NO_SEMANTIC_LABEL`` and no label
space is registered for their layers; the mesh labels are segment ids, not classes, so no
``mesh`` label space either (Hydra's would map classes).

A segment's ``semantic_feature`` holds its whole CLIP gallery, one row per gallery track
(a float16 gallery is widened to float32 there; its dtype is kept in the metadata and
restored). The segment's ``mesh_connections`` list its mesh vertices, as Hydra's objects
do. What spark_dsg has no field for goes into the node's JSON metadata under
``"trackgraph"``: the tracks, gallery tracks and weights, the DINOv3 feature, the segment's
flags, room and vertex count, the float64 boxes (the attributes hold float32 boxes), a room's float64 box (absent
when the room had none: then the attribute box comes from its places' outlines), area, an
agent's frame index. Mesh vertices without a segment carry the
label 2**32 - 1. The graph metadata records the format version and this layout. Outline
hulls and the agent-place lookup use scipy (``ConvexHull``, ``cKDTree``). spark-dsg comes with
the ``hydra`` extra (in ``all``); without it fusion logs a warning and saves maps without
``graph.sparkdsg`` (its wheels need an sdist-only ``zmq``, so a robot profile leaves it out).

:func:`from_dsg` rebuilds the :class:`GraphSnapshot` (for float32 galleries exactly), and
still reads files of format 1 (no outlines, agents, room boxes or segment colours).
"""

from __future__ import annotations

import base64
import datetime
import logging
import os
import tempfile
import zlib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import spark_dsg as sd

from shared.graph.colors import NONE_COLOR, segment_colors
from shared.graph.scene import BUILDING_ID
from shared.messages.graph import Edge, GraphSnapshot, MeshChunk, PlaceNode, RoomNode, SegmentNode

log = logging.getLogger(__name__)

LAYERS = sd.DsgLayers
HYDRA_LAYERS = (LAYERS.OBJECTS, LAYERS.AGENTS, LAYERS.PLACES, LAYERS.MESH_PLACES, LAYERS.ROOMS, LAYERS.BUILDINGS)
"""The layer names Hydra's ``SharedDsgInfo`` gives a graph; their keys come from spark_dsg."""
KEY_SEGMENT, KEY_PLACE, KEY_PLACE_2D, KEY_ROOM, KEY_BUILDING, KEY_AGENT = "O", "p", "Q", "R", "B", "a"
AGENT_PARTITION = KEY_AGENT
"""Hydra's agent partition is the robot prefix (kimera_pgmo's ``robot_id_to_prefix[0]``)."""
NO_LABEL = 2**32 - 1
UNKNOWN_ROOM = "unknown"
BUILDING_LABEL = 0
FORMAT_VERSION = 2
READABLE_FORMATS = (1, 2)
MeshColors = Literal["segments", "rgb"]

_EDGE_KINDS = {
    (KEY_SEGMENT, KEY_PLACE): "segment_place",
    (KEY_PLACE, KEY_PLACE): "place_place",
    (KEY_PLACE, KEY_ROOM): "place_room",
    (KEY_ROOM, KEY_BUILDING): "room_building",
}
_KEY_OF_KIND = {v: k for k, v in _EDGE_KINDS.items()}
_DERIVED = {(KEY_AGENT, KEY_AGENT), (KEY_AGENT, KEY_PLACE), (KEY_PLACE, KEY_AGENT), (KEY_ROOM, KEY_ROOM), (KEY_PLACE_2D, KEY_PLACE_2D)}
_KIND_ORDER = {"segment_place": 0, "place_place": 1, "place_room": 2, "room_building": 3}
_BUILDING_COLOR = np.array(NONE_COLOR, np.uint8)


def _palette(ids: list[int]) -> dict[int, np.ndarray]:
    """The viewer's colour of each id, in one call (the palette is vectorised)."""
    return dict(zip(ids, segment_colors(np.array(ids, np.int64)), strict=True)) if ids else {}


def _new_graph() -> sd.DynamicSceneGraph:
    names = {}
    for name in HYDRA_LAYERS:
        key = LAYERS.name_to_layer_id(name)
        if key is None:
            raise RuntimeError(f"spark_dsg {sd.version()} has no default key for layer {name!r}")
        names[name] = key
    return sd.DynamicSceneGraph(list(names.values()), names)


def to_dsg(snap: GraphSnapshot, mesh_colors: MeshColors = "segments") -> sd.DynamicSceneGraph:
    """The snapshot as a spark_dsg graph in Hydra's layout (with its mesh, if the snapshot has
    one). ``mesh_colors="segments"`` colours the vertices of each segment with its colour and
    keeps their RGB in the metadata; ``"rgb"`` writes the vertex RGB as is."""
    if mesh_colors not in ("segments", "rgb"):
        raise ValueError(f"mesh_colors must be 'segments' or 'rgb', not {mesh_colors!r}")
    traj, frames = snap.trajectory, snap.trajectory_frames
    if traj.shape[0] != frames.shape[0]:
        raise ValueError(f"GraphSnapshot.trajectory has {traj.shape[0]} rows but trajectory_frames has {frames.shape[0]}")
    g = _new_graph()
    sym = sd.NodeSymbol
    vertices_of = _vertices_by_segment(snap.mesh)
    place_room = _place_rooms(snap)
    seg_color, room_color = _palette([s.id for s in snap.segments]), _palette([r.id for r in snap.rooms])
    grey = np.array(NONE_COLOR, np.uint8)

    for s in snap.segments:
        a = sd.ObjectNodeAttributes()
        a.position = np.asarray(s.centroid, np.float64)
        lo, hi = np.asarray(s.bbox_min, np.float32), np.asarray(s.bbox_max, np.float32)
        a.bounding_box = _box(lo, hi)
        a.semantic_feature = np.asarray(s.gallery, np.float32)
        a.is_active = bool(s.active)
        a.name = f"segment {s.id}"
        a.color = seg_color[s.id]
        a.mesh_connections = vertices_of.get(s.id, [])
        a.metadata.set({"trackgraph": {
            "tracks": list(s.tracks),
            "gallery_tracks": list(s.gallery_tracks),
            "gallery_weights": list(s.gallery_weights),
            "gallery_dtype": s.gallery.dtype.name,
            "gallery_dim": int(s.gallery.shape[1]),
            "dino": s.dino.tolist(),
            "dino_dtype": s.dino.dtype.name,
            "active": bool(s.active),
            "room": s.room,
            "num_vertices": int(s.num_vertices),
            "centroid": s.centroid.tolist(),
            "bbox_min": s.bbox_min.tolist(),
            "bbox_max": s.bbox_max.tolist(),
        }})  # fmt: skip
        _add(g, LAYERS.OBJECTS, sym(KEY_SEGMENT, s.id), a)

    for p in snap.places:
        room = place_room.get(p.id)
        color = room_color.get(room, grey) if room is not None else grey
        a = sd.PlaceNodeAttributes()
        a.position = np.asarray(p.position, np.float64)
        a.distance = float(p.radius)
        a.real_place = True
        a.is_active = bool(p.active)
        a.color = color
        a.metadata.set({"trackgraph": {"room": p.room}})
        _add(g, LAYERS.PLACES, sym(KEY_PLACE, p.id), a)
        if p.boundary.shape[0]:
            _add(g, LAYERS.MESH_PLACES, sym(KEY_PLACE_2D, p.id), _place_2d(p, color))

    names = sorted({r.name for r in snap.rooms if r.name} - {UNKNOWN_ROOM})
    label_of = {n: i + 1 for i, n in enumerate(names)}
    for r in snap.rooms:
        _add(g, LAYERS.ROOMS, sym(KEY_ROOM, r.id), _room(r, snap, place_room, label_of.get(r.name, 0), room_color[r.id]))

    if snap.rooms:
        b = sd.SemanticNodeAttributes()
        b.position = np.mean([r.centroid for r in snap.rooms], axis=0).astype(np.float64)
        b.name = "building"
        b.semantic_label = BUILDING_LABEL
        b.color = _BUILDING_COLOR
        _add(g, LAYERS.BUILDINGS, sym(KEY_BUILDING, BUILDING_ID), b)

    agents_key = g.get_layer_key(LAYERS.AGENTS)
    agent_layer = sd.LayerKey(agents_key.layer, AGENT_PARTITION)
    for k in range(traj.shape[0]):
        a = sd.AgentNodeAttributes()
        x, y, z, qx, qy, qz, qw = (float(v) for v in traj[k])
        a.position = np.array([x, y, z], np.float64)
        a.world_R_body = sd.Quaternion(qw, qx, qy, qz)
        a.timestamp = datetime.timedelta(microseconds=int(frames[k]))
        a.external_key = sym(KEY_AGENT, k).value
        a.metadata.set({"trackgraph": {"frame": int(frames[k])}})
        if not g.add_node(agent_layer, sym(KEY_AGENT, k), a):
            raise RuntimeError(f"spark_dsg refused agent node a{k}")

    for e in snap.edges:
        ks, kt = _KEY_OF_KIND[e.kind]
        if not g.insert_edge(sym(ks, e.source), sym(kt, e.target)):
            log.warning("spark_dsg refused edge %s %d -> %d", e.kind, e.source, e.target)
    _derived_edges(g, snap, place_room)

    if snap.mesh is not None and snap.mesh.vertices.shape[0]:
        g.mesh = _to_spark_mesh(snap.mesh, mesh_colors)
    info: dict[str, Any] = {
        "format": FORMAT_VERSION,
        "graph_seq": snap.graph_seq,
        "frame_index": snap.frame_index,
        "layers": {"segments": LAYERS.OBJECTS, "places": LAYERS.PLACES, "place_outlines": LAYERS.MESH_PLACES,
                   "rooms": LAYERS.ROOMS, "building": LAYERS.BUILDINGS, "agents": LAYERS.AGENTS},
        "agent_partition": AGENT_PARTITION,
        "agent_timestamp": "trajectory frame index, in microseconds",
        "semantic_feature": {"segments": "CLIP gallery of the segment, one row per gallery track"},
        "has_mesh": snap.mesh is not None,
        "mesh_colors": mesh_colors,
    }  # fmt: skip
    if mesh_colors == "segments" and snap.mesh is not None and snap.mesh.vertices.shape[0]:
        rgb = np.ascontiguousarray(snap.mesh.colors[snap.mesh.segment_ids >= 0], np.uint8)
        info["mesh_rgb"] = base64.b64encode(zlib.compress(rgb.tobytes(), 6)).decode("ascii")
    g.metadata.set({"trackgraph": info})
    # set_labelspace adds to the graph metadata, so it comes after the set above.
    rooms_key, building_key = g.get_layer_key(LAYERS.ROOMS), g.get_layer_key(LAYERS.BUILDINGS)
    g.set_labelspace(sd.Labelspace({0: UNKNOWN_ROOM, **{i: n for n, i in label_of.items()}}), rooms_key.layer, rooms_key.partition)
    g.set_labelspace(sd.Labelspace({BUILDING_LABEL: "building"}), building_key.layer, building_key.partition)
    return g


def _add(g: sd.DynamicSceneGraph, layer: str, node: sd.NodeSymbol, attrs: sd.NodeAttributes) -> None:
    if not g.add_node(layer, node, attrs):
        raise RuntimeError(f"spark_dsg refused node {node.str()} in layer {layer}")


def _box(lo: np.ndarray, hi: np.ndarray) -> sd.BoundingBox:
    # spark_dsg's two-argument box is (dimensions, centre).
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    return sd.BoundingBox(hi - lo, (lo + hi) / 2)


def _place_rooms(snap: GraphSnapshot) -> dict[int, int]:
    """Room of each place: its place_room edge, else its ``room`` field."""
    out = {p.id: p.room for p in snap.places if p.room is not None}
    out.update({e.source: e.target for e in snap.edges if e.kind == "place_room"})
    return out


def _place_2d(p: PlaceNode, color: np.ndarray) -> sd.Place2dNodeAttributes:
    a = sd.Place2dNodeAttributes()
    a.position = np.asarray(p.position, np.float64)
    z = float(p.position[2])
    a.boundary = [np.array([x, y, z], np.float64) for x, y in p.boundary]
    a.is_active = bool(p.active)
    a.color = color
    ellipse = _hydra_ellipse(p.boundary)
    if ellipse is not None:
        centre, expand, compress = ellipse
        a.ellipse_centroid = np.array([centre[0], centre[1], z], np.float64)
        a.ellipse_matrix_expand = expand
        a.ellipse_matrix_compress = compress
    else:
        a.ellipse_centroid = np.array([p.position[0], p.position[1], z], np.float64)
        a.ellipse_matrix_expand = np.zeros((2, 2))
        a.ellipse_matrix_compress = np.zeros((2, 2))
    return a


def _convex_hull(xy: Annotated[np.ndarray, "(N, 2)"]) -> Annotated[np.ndarray, "(H, 2) counter-clockwise"] | None:
    """The outline's convex hull (qhull), None where it has no area."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(xy, np.float64)
    if pts.shape[0] < 3:
        return None
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:  # collinear or repeated points
        return None


def _hydra_ellipse(
    xy: Annotated[np.ndarray, "(B, 2)"],
) -> tuple[Annotated[np.ndarray, "(2,)"], Annotated[np.ndarray, "(2, 2)"], Annotated[np.ndarray, "(2, 2)"]] | None:
    """Hydra's 2D-place ellipse (``addRectInfo``, scale factor 1): the minimum-area rectangle of
    the outline, ``expand`` = sqrt(2)/2 * [side1 side2] as columns, ``compress`` =
    inv(expand)^T inv(expand); None for an outline of no area."""
    hull = _convex_hull(xy)
    if hull is None:
        return None
    edges = np.roll(hull, -1, axis=0) - hull
    lengths = np.linalg.norm(edges, axis=1)
    keep = lengths > 0
    u = edges[keep] / lengths[keep, None]
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)
    pu, pv = hull @ u.T, hull @ v.T  # (H, E): the hull projected on each edge's axes
    du, dv = pu.max(0) - pu.min(0), pv.max(0) - pv.min(0)
    best = int(np.argmin(du * dv))
    if du[best] * dv[best] <= 1e-12:
        return None
    cu, cv = (pu[:, best].max() + pu[:, best].min()) / 2, (pv[:, best].max() + pv[:, best].min()) / 2
    centre = u[best] * cu + v[best] * cv
    expand = np.sqrt(2.0) / 2.0 * np.stack([u[best] * du[best], v[best] * dv[best]], axis=1)
    inv = np.linalg.inv(expand)
    return centre, expand, inv.T @ inv


def _room(r: RoomNode, snap: GraphSnapshot, place_room: dict[int, int], label: int, color: np.ndarray) -> sd.RoomNodeAttributes:
    a = sd.RoomNodeAttributes()
    a.position = np.asarray(r.centroid, np.float64)
    a.name = r.name
    a.semantic_label = label
    a.color = color
    meta: dict[str, Any] = {"area_m2": float(r.area_m2)}
    if r.feature is not None:
        # One row, as a segment's gallery: Hydra-side tools read it as the node's feature.
        a.semantic_feature = np.asarray(r.feature, np.float32).reshape(1, -1)
        meta["feature_dtype"] = r.feature.dtype.name
    if r.name_score is not None:
        meta["name_score"] = float(r.name_score)
    if r.bbox_min is not None and r.bbox_max is not None:
        a.bounding_box = _box(r.bbox_min, r.bbox_max)
        meta["bbox_min"], meta["bbox_max"] = r.bbox_min.tolist(), r.bbox_max.tolist()
    else:
        box = _box_of_places([p for p in snap.places if place_room.get(p.id) == r.id])
        if box is not None:
            a.bounding_box = _box(*box)
    a.metadata.set({"trackgraph": meta})
    return a


def _box_of_places(places: list[PlaceNode]) -> tuple[np.ndarray, np.ndarray] | None:
    """A room's box from its places: xy from their outlines (their free-space discs where none
    has one), z from their heights +- their free-space radius."""
    if not places:
        return None
    outlines = [p.boundary for p in places if p.boundary.shape[0]]
    if outlines:
        xy = np.concatenate(outlines)
        xy_lo, xy_hi = xy.min(0), xy.max(0)
    else:
        pos, rad = np.array([p.position[:2] for p in places]), np.array([p.radius for p in places])[:, None]
        xy_lo, xy_hi = (pos - rad).min(0), (pos + rad).max(0)
    z = np.array([p.position[2] for p in places])
    rad = np.array([p.radius for p in places])
    return np.r_[xy_lo, (z - rad).min()], np.r_[xy_hi, (z + rad).max()]


def _inside(points: Annotated[np.ndarray, "(N, 2)"], polygon: Annotated[np.ndarray, "(B, 2)"]) -> Annotated[np.ndarray, "(N,) bool"]:
    """Even-odd point-in-polygon test of each point."""
    x, y = points[:, :1], points[:, 1:2]
    xi, yi = polygon[:, 0][None], polygon[:, 1][None]
    xj, yj = np.roll(polygon[:, 0], 1)[None], np.roll(polygon[:, 1], 1)[None]
    crosses = (yi > y) != (yj > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = (xj - xi) * (y - yi) / (yj - yi) + xi
    return (np.count_nonzero(crosses & (x < x_at), axis=1) % 2) == 1


def agent_places(
    snap: GraphSnapshot, chunk: int = 2048
) -> Annotated[np.ndarray, "(M,) int64 place id per trajectory row, -1 without places"]:
    """The place each trajectory pose passed: the nearest (3D) place whose outline contains the
    pose's xy, else the nearest place."""
    traj = snap.trajectory
    out = np.full(traj.shape[0], -1, np.int64)
    if not snap.places or traj.shape[0] == 0:
        return out
    pos = traj[:, :3]
    ids = np.array([p.id for p in snap.places], np.int64)
    centres = np.array([p.position for p in snap.places], np.float64)
    best_d = np.full(traj.shape[0], np.inf)
    outlined = [p for p in snap.places if p.boundary.shape[0] >= 3]
    lo = np.array([p.boundary.min(0) for p in outlined]).reshape(-1, 2)
    hi = np.array([p.boundary.max(0) for p in outlined]).reshape(-1, 2)
    # Poses within each outline's box, found for all outlines at once, chunk by chunk.
    hits: list[list[np.ndarray]] = [[] for _ in outlined]
    for s in range(0, traj.shape[0], chunk):
        xy = pos[s : s + chunk, None, :2]
        rows, cols = np.nonzero(np.all((xy >= lo[None]) & (xy <= hi[None]), axis=2))
        if cols.size == 0:
            continue  # no pose of this chunk within any outline's box
        order = np.argsort(cols, kind="stable")
        uniq, start = np.unique(cols[order], return_index=True)
        for j, grp in zip(uniq, np.split(rows[order] + s, start[1:]), strict=True):
            hits[j].append(grp)
    for p, found in zip(outlined, hits, strict=True):
        if not found:
            continue
        cand = np.concatenate(found)
        cand = cand[_inside(pos[cand, :2], p.boundary)]
        d = np.linalg.norm(pos[cand] - p.position, axis=1)
        closer = d < best_d[cand]
        best_d[cand[closer]] = d[closer]
        out[cand[closer]] = p.id
    rest = np.flatnonzero(out < 0)
    if rest.size:
        from scipy.spatial import cKDTree

        out[rest] = ids[cKDTree(centres).query(pos[rest])[1]]
    return out


def _derived_edges(g: sd.DynamicSceneGraph, snap: GraphSnapshot, place_room: dict[int, int]) -> None:
    sym = sd.NodeSymbol
    with_outline = {p.id for p in snap.places if p.boundary.shape[0]}
    for e in snap.edges:
        if e.kind != "place_place":
            continue
        if e.source in with_outline and e.target in with_outline:
            g.insert_edge(sym(KEY_PLACE_2D, e.source), sym(KEY_PLACE_2D, e.target))
        ra, rb = place_room.get(e.source), place_room.get(e.target)
        if ra is not None and rb is not None and ra != rb and g.has_node(sym(KEY_ROOM, ra)) and g.has_node(sym(KEY_ROOM, rb)):
            g.insert_edge(sym(KEY_ROOM, ra), sym(KEY_ROOM, rb))
    for k in range(1, snap.trajectory.shape[0]):
        g.insert_edge(sym(KEY_AGENT, k - 1), sym(KEY_AGENT, k))
    for k, pid in enumerate(agent_places(snap)):
        if pid >= 0:
            # The place is the parent, one per agent, as Hydra's LayerConnector inserts it.
            g.insert_edge(sym(KEY_PLACE, int(pid)), sym(KEY_AGENT, k), True)


def _vertices_by_segment(mesh: MeshChunk | None) -> dict[int, list[int]]:
    if mesh is None or mesh.segment_ids.size == 0:
        return {}
    ids = mesh.segment_ids
    order = np.argsort(ids, kind="stable")
    uniq, start = np.unique(ids[order], return_index=True)
    groups = np.split(order, start[1:])
    return {int(u): grp.tolist() for u, grp in zip(uniq, groups, strict=True) if u >= 0}


def mesh_vertex_colors(m: MeshChunk) -> Annotated[np.ndarray, "(V, 3) uint8"]:
    """Each vertex's segment colour, its own RGB where it has no segment."""
    has = m.segment_ids >= 0
    return np.where(has[:, None], segment_colors(m.segment_ids), m.colors).astype(np.uint8)


def _to_spark_mesh(m: MeshChunk, mesh_colors: MeshColors) -> sd.Mesh:
    mesh = sd.Mesh(True, False, True, False)
    rgb = mesh_vertex_colors(m) if mesh_colors == "segments" else m.colors
    mesh.set_vertices(np.vstack([m.vertices.T.astype(np.float64), rgb.T.astype(np.float64) / 255.0]))
    mesh.set_faces(np.ascontiguousarray(m.faces.T, np.int32))
    labels = np.where(m.segment_ids >= 0, m.segment_ids.astype(np.int64), NO_LABEL).tolist()
    # spark_dsg exposes labels one vertex at a time only (about 0.5 us each).
    for i, lab in enumerate(labels):
        mesh.set_label(i, lab)
    return mesh


def _from_spark_mesh(mesh: sd.Mesh, info: dict[str, Any]) -> MeshChunk:
    # Copies: the arrays spark_dsg hands out may view memory freed with the graph.
    v = np.array(mesh.get_vertices(), np.float64, copy=True)
    labels = np.asarray(mesh.get_labels(), np.int64)
    faces = np.array(mesh.get_faces(), np.int32, copy=True).reshape(3, -1).T
    ids = np.where(labels == NO_LABEL, -1, labels).astype(np.int32)
    colors = np.ascontiguousarray(np.clip(np.round(v[3:6].T * 255.0), 0, 255), np.uint8)
    if info.get("mesh_colors", "rgb") == "segments":
        has = ids >= 0
        packed = info.get("mesh_rgb")
        if packed is None:
            raise ValueError("trackgraph scene graph with segment-coloured mesh lacks its 'mesh_rgb' metadata")
        rgb = np.frombuffer(zlib.decompress(base64.b64decode(packed)), np.uint8)
        if rgb.size != 3 * int(has.sum()):
            raise ValueError(f"'mesh_rgb' metadata holds {rgb.size // 3} colours for {int(has.sum())} segmented vertices")
        colors[has] = rgb.reshape(-1, 3)
    return MeshChunk(
        vertices=np.ascontiguousarray(v[:3].T, np.float32),
        colors=colors,
        faces=np.ascontiguousarray(faces, np.int32),
        segment_ids=ids,
    )


def from_dsg(g: sd.DynamicSceneGraph) -> GraphSnapshot:
    """Rebuild a snapshot from a graph written by :func:`to_dsg` (format 2, or the older 1)."""
    info = dict(g.metadata.get()).get("trackgraph")
    if not isinstance(info, dict) or info.get("format") not in READABLE_FORMATS:
        raise ValueError(f"not a trackgraph scene graph of format {' or '.join(map(str, READABLE_FORMATS))} (metadata: {info!r})")
    segments, places, rooms, agents, outlines = [], [], [], [], {}
    for node in g.nodes:
        cat, nid, a = node.id.category, int(node.id.category_id), node.attributes
        if cat == KEY_SEGMENT:
            segments.append(_segment(nid, a))
        elif cat == KEY_PLACE:
            m = dict(a.metadata.get()).get("trackgraph", {})
            places.append(dict(id=nid, position=np.array(a.position, np.float64, copy=True).reshape(3),
                               radius=float(a.distance), room=m.get("room"), active=bool(a.is_active)))  # fmt: skip
        elif cat == KEY_PLACE_2D:
            b = np.array([np.asarray(p, np.float64) for p in a.boundary], np.float64).reshape(-1, 3)
            outlines[nid] = np.ascontiguousarray(b[:, :2])
        elif cat == KEY_ROOM:
            rooms.append(_room_node(nid, a))
        elif cat == KEY_AGENT:
            agents.append((nid, a))

    edges = []
    for e in g.edges:
        s, t = sd.NodeSymbol(e.source), sd.NodeSymbol(e.target)
        kind = _EDGE_KINDS.get((s.category, t.category))
        if kind is None:
            s, t = t, s
            kind = _EDGE_KINDS.get((s.category, t.category))
        if kind is None:
            if (s.category, t.category) not in _DERIVED:
                log.warning("ignoring edge %s - %s of no trackgraph kind", s.str(), t.str())
            continue
        a, b = int(s.category_id), int(t.category_id)
        if kind == "place_place":
            a, b = min(a, b), max(a, b)
        edges.append((kind, a, b))
    edges.sort(key=lambda x: (_KIND_ORDER[x[0]], x[1], x[2]))

    mesh = None
    if info.get("has_mesh"):
        mesh = _from_spark_mesh(g.mesh, info) if g.has_mesh() else MeshChunk(
            vertices=np.zeros((0, 3), np.float32), colors=np.zeros((0, 3), np.uint8),
            faces=np.zeros((0, 3), np.int32), segment_ids=np.zeros(0, np.int32),
        )  # fmt: skip
    traj, frames = _trajectory(agents)
    return GraphSnapshot(
        graph_seq=int(info["graph_seq"]),
        frame_index=int(info["frame_index"]),
        segments=sorted(segments, key=lambda s: s.id),
        places=[PlaceNode(**p, boundary=outlines.get(p["id"], np.zeros((0, 2)))) for p in sorted(places, key=lambda p: p["id"])],
        rooms=sorted(rooms, key=lambda r: r.id),
        edges=[Edge(kind=k, source=s, target=t) for k, s, t in edges],
        mesh=mesh,
        trajectory=traj,
        trajectory_frames=frames,
    )


def _segment(nid: int, a: sd.ObjectNodeAttributes) -> SegmentNode:
    m = dict(a.metadata.get())["trackgraph"]
    gal = np.array(a.semantic_feature, np.float32, copy=True).reshape(-1, int(m["gallery_dim"]))
    return SegmentNode(
        id=nid,
        centroid=np.asarray(m["centroid"], np.float64),
        bbox_min=np.asarray(m["bbox_min"], np.float64),
        bbox_max=np.asarray(m["bbox_max"], np.float64),
        tracks=list(m["tracks"]),
        dino=np.asarray(m["dino"], np.float64).astype(m["dino_dtype"]),
        gallery=gal.astype(m["gallery_dtype"]),
        gallery_tracks=list(m["gallery_tracks"]),
        gallery_weights=list(m.get("gallery_weights", [])),
        active=bool(m["active"]),
        room=m["room"],
        num_vertices=int(m["num_vertices"]),
    )


def _room_node(nid: int, a: sd.RoomNodeAttributes) -> RoomNode:
    m = dict(a.metadata.get()).get("trackgraph", {})
    box = {k: np.asarray(m[k], np.float64) for k in ("bbox_min", "bbox_max") if k in m}
    feature = None
    if "feature_dtype" in m:
        feature = np.asarray(a.semantic_feature, np.float32).reshape(-1).astype(m["feature_dtype"])
    return RoomNode(
        id=nid,
        centroid=np.array(a.position, np.float64, copy=True).reshape(3),
        name=a.name,
        area_m2=float(m.get("area_m2", 0.0)),
        feature=feature,
        name_score=m.get("name_score"),
        **box,
    )


def _trajectory(agents: list[tuple[int, sd.AgentNodeAttributes]]) -> tuple[np.ndarray, np.ndarray]:
    agents = sorted(agents, key=lambda x: x[0])
    if [k for k, _ in agents] != list(range(len(agents))):
        raise ValueError(f"agent nodes are not a0..a{len(agents) - 1}: {[k for k, _ in agents][:10]}")
    rows, frames = [], []
    for _, a in agents:
        q, p = a.world_R_body, np.asarray(a.position, np.float64).reshape(3)
        rows.append([p[0], p[1], p[2], q.x, q.y, q.z, q.w])
        m = dict(a.metadata.get()).get("trackgraph", {})
        # Without our metadata the timestamp is the frame index in microseconds.
        frames.append(int(m["frame"]) if "frame" in m else a.timestamp // datetime.timedelta(microseconds=1))
    traj = np.array(rows, np.float64).reshape(-1, 7)
    return traj, np.array(frames, np.int64).reshape(-1)


def save_dsg(snap: GraphSnapshot, path: Path | str, include_mesh: bool = True, mesh_colors: MeshColors = "segments") -> Path:
    """Write ``path`` (.sparkdsg) atomically: spark_dsg writes a temporary file in the same
    folder, which is fsynced and renamed over ``path``. ``mesh_colors`` as in :func:`to_dsg`."""
    path = Path(path)
    g = to_dsg(snap if include_mesh else snap.model_copy(update={"mesh": None}), mesh_colors=mesh_colors)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.sparkdsg", dir=path.parent)
    os.close(fd)
    try:
        g.save(tmp, include_mesh=include_mesh)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def load_dsg(path: Path | str) -> GraphSnapshot:
    """Read a ``.sparkdsg`` written by :func:`save_dsg`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no scene graph at {path}")
    return from_dsg(sd.DynamicSceneGraph.load(str(path)))
