"""A spark_dsg graph written by :func:`shared.graph.dsg.write.to_dsg` back as a
:class:`GraphSnapshot` (:func:`from_dsg`); it still reads files of format 1."""

from __future__ import annotations

import base64
import datetime
import logging
import zlib
from typing import Any

import numpy as np
import spark_dsg as sd

from shared.graph.dsg.layout import (
    DERIVED_EDGES,
    EDGE_KINDS,
    KEY_AGENT,
    KEY_PLACE,
    KEY_PLACE_2D,
    KEY_ROOM,
    KEY_SEGMENT,
    KIND_ORDER,
    NO_LABEL,
    READABLE_FORMATS,
)
from shared.messages.graph import Edge, GraphSnapshot, MeshChunk, PlaceNode, RoomNode, SegmentNode

log = logging.getLogger(__name__)


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
        kind = EDGE_KINDS.get((s.category, t.category))
        if kind is None:
            s, t = t, s
            kind = EDGE_KINDS.get((s.category, t.category))
        if kind is None:
            if (s.category, t.category) not in DERIVED_EDGES:
                log.warning("ignoring edge %s - %s of no trackgraph kind", s.str(), t.str())
            continue
        a, b = int(s.category_id), int(t.category_id)
        if kind == "place_place":
            a, b = min(a, b), max(a, b)
        edges.append((kind, a, b))
    edges.sort(key=lambda x: (KIND_ORDER[x[0]], x[1], x[2]))

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
