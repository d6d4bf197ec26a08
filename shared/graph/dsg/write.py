"""A :class:`GraphSnapshot` as a spark_dsg graph in Hydra's layout (:func:`to_dsg`)."""

from __future__ import annotations

import base64
import datetime
import logging
import zlib
from typing import Annotated, Any

import numpy as np
import spark_dsg as sd

from shared.graph.colors import NONE_COLOR, segment_colors
from shared.graph.dsg.hydra import box_of_places, derived_edges, place_2d
from shared.graph.dsg.layout import (
    AGENT_PARTITION,
    BUILDING_LABEL,
    FORMAT_VERSION,
    HYDRA_LAYERS,
    KEY_AGENT,
    KEY_BUILDING,
    KEY_OF_KIND,
    KEY_PLACE,
    KEY_PLACE_2D,
    KEY_ROOM,
    KEY_SEGMENT,
    LAYERS,
    NO_LABEL,
    UNKNOWN_ROOM,
    MeshColors,
)
from shared.graph.scene import BUILDING_ID
from shared.messages.graph import GraphSnapshot, MeshChunk, RoomNode

log = logging.getLogger(__name__)

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
            _add(g, LAYERS.MESH_PLACES, sym(KEY_PLACE_2D, p.id), place_2d(p, color))

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
        ks, kt = KEY_OF_KIND[e.kind]
        if not g.insert_edge(sym(ks, e.source), sym(kt, e.target)):
            log.warning("spark_dsg refused edge %s %d -> %d", e.kind, e.source, e.target)
    derived_edges(g, snap, place_room)

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
        box = box_of_places([p for p in snap.places if place_room.get(p.id) == r.id])
        if box is not None:
            a.bounding_box = _box(*box)
    a.metadata.set({"trackgraph": meta})
    return a


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
