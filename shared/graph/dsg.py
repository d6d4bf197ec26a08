"""Export of the scene graph to spark_dsg (Hydra's scene-graph library) and back.

A saved ``.sparkdsg`` opens in Hydra's tools. The mapping:

| ours | spark_dsg |
|---|---|
| segment | layer 2 (Hydra's objects layer, which segments replace), symbol ``O<id>``, ``ObjectNodeAttributes`` |
| place | layer 3, ``p<id>``, ``PlaceNodeAttributes`` (``distance`` = radius) |
| room | layer 4, ``R<id>``, ``RoomNodeAttributes`` |
| building | layer 5, ``B0``, ``SemanticNodeAttributes`` at the mean of the room centroids |
| mesh | the graph's mesh: positions, colours, and per-vertex label = segment id |

A segment's ``semantic_feature`` holds its whole CLIP gallery, one row per gallery track:
spark_dsg stores it as a float32 matrix of any shape, so no averaging is needed (a float16
gallery is widened to float32 there; its dtype is kept in the metadata and restored). The
segment's ``mesh_connections`` list its mesh vertices, as Hydra's objects do. What spark_dsg
has no field for goes into the node's JSON metadata under ``"trackgraph"``: the source and
gallery tracks, the DINOv3 feature, the active flag, the room, the vertex count, and the
centroid and box in float64 (the attributes hold float32 boxes). Mesh vertices without a
segment carry the label 2**32 - 1. The graph metadata records the version and this layout.

:func:`load_dsg` rebuilds the :class:`GraphSnapshot`; for float32 galleries the round trip
is exact.
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.graph.scene import BUILDING_ID
from shared.messages.graph import Edge, GraphSnapshot, MeshChunk, PlaceNode, RoomNode, SegmentNode

if TYPE_CHECKING:
    import spark_dsg

log = logging.getLogger(__name__)

LAYER_SEGMENTS, LAYER_PLACES, LAYER_ROOMS, LAYER_BUILDINGS = 2, 3, 4, 5
KEY_SEGMENT, KEY_PLACE, KEY_ROOM, KEY_BUILDING = "O", "p", "R", "B"
NO_LABEL = 2**32 - 1
FORMAT_VERSION = 1
_EDGE_KINDS = {
    (KEY_SEGMENT, KEY_PLACE): "segment_place",
    (KEY_PLACE, KEY_PLACE): "place_place",
    (KEY_PLACE, KEY_ROOM): "place_room",
    (KEY_ROOM, KEY_BUILDING): "room_building",
}
_KEY_OF_KIND = {v: k for k, v in _EDGE_KINDS.items()}


def _dsg() -> Any:
    import spark_dsg

    return spark_dsg


def to_dsg(snap: GraphSnapshot) -> spark_dsg.DynamicSceneGraph:
    """The snapshot as a spark_dsg graph (with its mesh, if the snapshot has one)."""
    sd = _dsg()
    g = sd.DynamicSceneGraph()
    sym = sd.NodeSymbol
    vertices_of = _vertices_by_segment(snap.mesh)

    for s in snap.segments:
        a = sd.ObjectNodeAttributes()
        a.position = np.asarray(s.centroid, np.float64)
        lo, hi = np.asarray(s.bbox_min, np.float32), np.asarray(s.bbox_max, np.float32)
        # spark_dsg's two-argument box is (dimensions, centre).
        a.bounding_box = sd.BoundingBox(hi - lo, (lo + hi) / 2)
        a.semantic_feature = np.asarray(s.gallery, np.float32)
        a.is_active = bool(s.active)
        a.name = f"segment {s.id}"
        a.mesh_connections = vertices_of.get(s.id, [])
        a.metadata.set({"trackgraph": {
            "tracks": list(s.tracks),
            "gallery_tracks": list(s.gallery_tracks),
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
        g.add_node(LAYER_SEGMENTS, sym(KEY_SEGMENT, s.id), a)

    for p in snap.places:
        a = sd.PlaceNodeAttributes()
        a.position = np.asarray(p.position, np.float64)
        a.distance = float(p.radius)
        a.real_place = True
        a.metadata.set({"trackgraph": {"room": p.room}})
        g.add_node(LAYER_PLACES, sym(KEY_PLACE, p.id), a)

    for r in snap.rooms:
        a = sd.RoomNodeAttributes()
        a.position = np.asarray(r.centroid, np.float64)
        a.name = r.name
        g.add_node(LAYER_ROOMS, sym(KEY_ROOM, r.id), a)

    if snap.rooms:
        b = sd.SemanticNodeAttributes()
        b.position = np.mean([r.centroid for r in snap.rooms], axis=0).astype(np.float64)
        b.name = "building"
        g.add_node(LAYER_BUILDINGS, sym(KEY_BUILDING, BUILDING_ID), b)

    for e in snap.edges:
        ks, kt = _KEY_OF_KIND[e.kind]
        if not g.insert_edge(sym(ks, e.source), sym(kt, e.target)):
            log.warning("spark_dsg refused edge %s %d -> %d", e.kind, e.source, e.target)

    if snap.mesh is not None and snap.mesh.vertices.shape[0]:
        g.mesh = _to_spark_mesh(snap.mesh)
    g.metadata.set({"trackgraph": {
        "format": FORMAT_VERSION,
        "graph_seq": snap.graph_seq,
        "frame_index": snap.frame_index,
        "layers": {"segments": LAYER_SEGMENTS, "places": LAYER_PLACES, "rooms": LAYER_ROOMS, "building": LAYER_BUILDINGS},
        "semantic_feature": "CLIP gallery of the segment, one row per gallery track",
        "has_mesh": snap.mesh is not None,
    }})  # fmt: skip
    return g


def _vertices_by_segment(mesh: MeshChunk | None) -> dict[int, list[int]]:
    if mesh is None or mesh.segment_ids.size == 0:
        return {}
    ids = mesh.segment_ids
    order = np.argsort(ids, kind="stable")
    uniq, start = np.unique(ids[order], return_index=True)
    groups = np.split(order, start[1:])
    return {int(u): grp.tolist() for u, grp in zip(uniq, groups, strict=True) if u >= 0}


def _to_spark_mesh(m: MeshChunk) -> spark_dsg.Mesh:
    sd = _dsg()
    mesh = sd.Mesh(True, False, True, False)
    mesh.set_vertices(np.vstack([m.vertices.T.astype(np.float64), m.colors.T.astype(np.float64) / 255.0]))
    mesh.set_faces(np.ascontiguousarray(m.faces.T, np.int32))
    labels = np.where(m.segment_ids >= 0, m.segment_ids.astype(np.int64), NO_LABEL).tolist()
    # spark_dsg exposes labels one vertex at a time only (about 0.5 us each).
    for i, lab in enumerate(labels):
        mesh.set_label(i, lab)
    return mesh


def _from_spark_mesh(mesh: spark_dsg.Mesh) -> MeshChunk:
    # Copies: the arrays spark_dsg hands out may view memory freed with the graph.
    v = np.array(mesh.get_vertices(), np.float64, copy=True)
    labels = np.asarray(mesh.get_labels(), np.int64)
    faces = np.array(mesh.get_faces(), np.int32, copy=True).reshape(3, -1).T
    return MeshChunk(
        vertices=np.ascontiguousarray(v[:3].T, np.float32),
        colors=np.ascontiguousarray(np.clip(np.round(v[3:6].T * 255.0), 0, 255), np.uint8),
        faces=np.ascontiguousarray(faces, np.int32),
        segment_ids=np.where(labels == NO_LABEL, -1, labels).astype(np.int32),
    )


def from_dsg(g: spark_dsg.DynamicSceneGraph) -> GraphSnapshot:
    """Rebuild a snapshot from a graph written by :func:`to_dsg`."""
    info = dict(g.metadata.get()).get("trackgraph")
    if not isinstance(info, dict) or info.get("format") != FORMAT_VERSION:
        raise ValueError(f"not a trackgraph scene graph of format {FORMAT_VERSION} (metadata: {info!r})")
    segments, places, rooms = [], [], []
    for node in g.nodes:
        cat, nid, a = node.id.category, int(node.id.category_id), node.attributes
        if cat == KEY_SEGMENT:
            m = dict(a.metadata.get())["trackgraph"]
            gal = np.array(a.semantic_feature, np.float32, copy=True).reshape(-1, int(m["gallery_dim"]))
            segments.append(SegmentNode(
                id=nid,
                centroid=np.asarray(m["centroid"], np.float64),
                bbox_min=np.asarray(m["bbox_min"], np.float64),
                bbox_max=np.asarray(m["bbox_max"], np.float64),
                tracks=list(m["tracks"]),
                dino=np.asarray(m["dino"], np.float64).astype(m["dino_dtype"]),
                gallery=gal.astype(m["gallery_dtype"]),
                gallery_tracks=list(m["gallery_tracks"]),
                active=bool(m["active"]),
                room=m["room"],
                num_vertices=int(m["num_vertices"]),
            ))  # fmt: skip
        elif cat == KEY_PLACE:
            m = dict(a.metadata.get()).get("trackgraph", {})
            places.append(PlaceNode(
                id=nid, position=np.array(a.position, np.float64, copy=True).reshape(3),
                radius=float(a.distance), room=m.get("room"),
            ))  # fmt: skip
        elif cat == KEY_ROOM:
            rooms.append(RoomNode(id=nid, centroid=np.array(a.position, np.float64, copy=True).reshape(3), name=a.name))

    edges = []
    for e in g.edges:
        s, t = _dsg().NodeSymbol(e.source), _dsg().NodeSymbol(e.target)
        kind = _EDGE_KINDS.get((s.category, t.category))
        if kind is None:
            s, t = t, s
            kind = _EDGE_KINDS.get((s.category, t.category))
        if kind is None:
            log.warning("ignoring edge %s - %s of no trackgraph kind", s.str(), t.str())
            continue
        a, b = int(s.category_id), int(t.category_id)
        if kind == "place_place":
            a, b = min(a, b), max(a, b)
        edges.append((kind, a, b))
    order = {"segment_place": 0, "place_place": 1, "place_room": 2, "room_building": 3}
    edges.sort(key=lambda x: (order[x[0]], x[1], x[2]))

    mesh = None
    if info.get("has_mesh"):
        mesh = _from_spark_mesh(g.mesh) if g.has_mesh() else MeshChunk(
            vertices=np.zeros((0, 3), np.float32), colors=np.zeros((0, 3), np.uint8),
            faces=np.zeros((0, 3), np.int32), segment_ids=np.zeros(0, np.int32),
        )  # fmt: skip
    return GraphSnapshot(
        graph_seq=int(info["graph_seq"]),
        frame_index=int(info["frame_index"]),
        segments=sorted(segments, key=lambda s: s.id),
        places=sorted(places, key=lambda p: p.id),
        rooms=sorted(rooms, key=lambda r: r.id),
        edges=[Edge(kind=k, source=s, target=t) for k, s, t in edges],
        mesh=mesh,
    )


def save_dsg(snap: GraphSnapshot, path: Path | str, include_mesh: bool = True) -> Path:
    """Write ``path`` (.sparkdsg) atomically: spark_dsg writes a temporary file in the same
    folder, which is fsynced and renamed over ``path``."""
    path = Path(path)
    g = to_dsg(snap if include_mesh else snap.model_copy(update={"mesh": None}))
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
    return from_dsg(_dsg().DynamicSceneGraph.load(str(path)))
