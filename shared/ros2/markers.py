"""What TrackGraph shows a ROS 2 graph: RViz markers of the scene graph and of query hits, the
camera trajectory as a ``nav_msgs/Path`` and hit centroids as a ``geometry_msgs/PoseArray``.

Pure functions from TrackGraph's messages to rosbags message objects (encode them with
:func:`shared.ros2.types.encode`); nothing here talks to Zenoh.

Every ``MarkerArray`` starts with a ``DELETEALL`` marker, so RViz drops whatever the previous
array drew before it draws this one: a removed segment disappears without TrackGraph having
to remember what it sent. Marker ids are stable per node id within a namespace, so RViz's
per-namespace toggles and "selected marker" stay on the same object from one array to the
next. Namespaces of :func:`graph_markers`:

- ``segments``: one ``LINE_LIST`` box outline per segment (id = segment id);
- ``centroids``: one ``SPHERE_LIST`` of all segment centroids (id 0);
- ``ids``: one ``TEXT_VIEW_FACING`` per segment with its id, above its box (with ``show_ids``);
- ``places``: one ``SPHERE_LIST`` of all places (id 0);
- ``rooms``: per room a ``TEXT_VIEW_FACING`` label (id ``2 * room``, with ``show_ids``) and,
  when its box is known, a ``LINE_STRIP`` footprint at its floor (id ``2 * room + 1``);
- ``edges/<kind>``: one ``LINE_LIST`` per edge kind that has edges (id 0).
"""

from __future__ import annotations

import colorsys
import dataclasses
import functools
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np

from shared.geometry import is_rigid, matrix_to_quat
from shared.graph.scene import BUILDING_ID, EdgeKey, edge_key
from shared.messages.graph import Edge, PlaceNode, RoomNode, SegmentNode
from shared.messages.rpc import QueryReply
from shared.ros2.types import msg_class

if TYPE_CHECKING:
    from shared.graph.scene import GraphReplica

log = logging.getLogger(__name__)

EDGE_KINDS = ("segment_place", "place_place", "place_room", "room_building")
"""Edge kinds, in the order their ``edges/<kind>`` markers appear."""

MIN_SCALE_M = 0.01
"""Smallest box extent drawn (m): RViz refuses zero-scale shapes, and a flat segment (a
poster on a wall) still needs a visible outline."""
BOX_LINE_M = 0.015
"""Line width of segment box outlines (m)."""
CENTROID_M = 0.05
"""Diameter of centroid spheres (m)."""
PLACE_M = 0.12
"""Diameter of place spheres (m): a fixed size, not ``PlaceNode.radius`` (the distance to the
nearest obstacle, often over a metre, which would bury the map in spheres)."""
ID_TEXT_M = 0.1
"""Height of segment id text (m)."""
ROOM_TEXT_M = 0.35
"""Height of room label text (m)."""
ROOM_LINE_M = 0.04
"""Line width of room footprints (m)."""
EDGE_LINE_M = 0.01
"""Line width of graph edges (m)."""
BUILDING_ABOVE_M = 1.5
"""The building node (which has no position of its own) is drawn this far above the highest
room, over the rooms' mean centroid, so room-building edges fan out upwards."""
HIT_TEXT_M = 0.15
"""Height of hit labels (m)."""

_EDGE_COLOURS = {
    "segment_place": (0.6, 0.6, 0.7, 0.5),
    "place_place": (0.2, 0.8, 0.9, 0.8),
    "place_room": (1.0, 0.6, 0.1, 0.6),
    "room_building": (0.8, 0.3, 0.9, 0.8),
}
_WHITE = (1.0, 1.0, 1.0, 1.0)
_GREY = (0.6, 0.6, 0.6, 1.0)
_INT32_MAX = 2**31 - 1
_GOLDEN = 0.6180339887498949

Rgba = tuple[float, float, float, float]


@dataclass(frozen=True)
class _Types:
    """The message classes of one distro (looked up once)."""

    time: Any
    duration: Any
    header: Any
    point: Any
    quaternion: Any
    vector3: Any
    pose: Any
    pose_stamped: Any
    colour: Any
    marker: Any
    marker_array: Any
    compressed_image: Any
    mesh_file: Any | None
    path: Any
    pose_array: Any
    marker_fields: frozenset[str]


@functools.cache
def _types(distro: str) -> _Types:
    marker = msg_class("visualization_msgs/msg/Marker", distro)
    fields = frozenset(f.name for f in dataclasses.fields(marker))
    return _Types(
        time=msg_class("builtin_interfaces/msg/Time", distro),
        duration=msg_class("builtin_interfaces/msg/Duration", distro),
        header=msg_class("std_msgs/msg/Header", distro),
        point=msg_class("geometry_msgs/msg/Point", distro),
        quaternion=msg_class("geometry_msgs/msg/Quaternion", distro),
        vector3=msg_class("geometry_msgs/msg/Vector3", distro),
        pose=msg_class("geometry_msgs/msg/Pose", distro),
        pose_stamped=msg_class("geometry_msgs/msg/PoseStamped", distro),
        colour=msg_class("std_msgs/msg/ColorRGBA", distro),
        marker=marker,
        marker_array=msg_class("visualization_msgs/msg/MarkerArray", distro),
        compressed_image=msg_class("sensor_msgs/msg/CompressedImage", distro),
        # MeshFile only exists where Marker has mesh_file (Iron on, and Humble's rosbags defs)
        mesh_file=msg_class("visualization_msgs/msg/MeshFile", distro) if "mesh_file" in fields else None,
        path=msg_class("nav_msgs/msg/Path", distro),
        pose_array=msg_class("geometry_msgs/msg/PoseArray", distro),
        marker_fields=fields,
    )


# ---------------------------------------------------------------------------------------------
# Basic messages


def header(frame_id: str, stamp_ns: int, distro: str = "jazzy") -> Any:
    """A ``std_msgs/Header`` in ``frame_id`` at ``stamp_ns`` (ns since the epoch)."""
    if not isinstance(frame_id, str) or not frame_id:
        raise ValueError(f"header.frame_id must be a non-empty TF frame name (got {frame_id!r})")
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    if not 0 <= sec <= _INT32_MAX:
        raise ValueError(f"header.stamp {stamp_ns} ns is outside builtin_interfaces/Time's range (0 to 2^31 s)")
    t = _types(distro)
    return t.header(stamp=t.time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def pose_msg(T: Annotated[np.ndarray, "(4, 4) rigid transform"], distro: str = "jazzy") -> Any:
    """The ``geometry_msgs/Pose`` of a rigid 4x4 transform (quaternion by Shepperd's method,
    ``w >= 0``)."""
    T = np.asarray(T, np.float64)
    if not is_rigid(T):
        raise ValueError(f"pose: expected a finite rigid (4, 4) transform, got shape {T.shape}")
    w, x, y, z = matrix_to_quat(T[:3, :3])
    t = _types(distro)
    return t.pose(
        position=t.point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=t.quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def _position_pose(p: np.ndarray, t: _Types) -> Any:
    """A pose at ``p`` with the identity orientation (what RViz wants for markers)."""
    return t.pose(
        position=t.point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=t.quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
    )


def trajectory_path(
    poses: Annotated[np.ndarray, "(N, 4, 4) T_world_cam"],
    stamps_ns: Annotated[np.ndarray, "(N,) int64"],
    *,
    frame_id: str,
    distro: str = "jazzy",
) -> Any:
    """The camera trajectory as a ``nav_msgs/Path`` in ``frame_id``: one ``PoseStamped`` per
    pose with its own stamp; the path's header carries the newest stamp (0 when empty)."""
    poses = np.asarray(poses, np.float64)
    stamps = np.asarray(stamps_ns)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"trajectory poses: expected (N, 4, 4) T_world_cam, got shape {poses.shape}")
    if stamps.shape != (poses.shape[0],) or (stamps.size and not np.issubdtype(stamps.dtype, np.integer)):
        raise ValueError(
            f"trajectory stamps_ns: expected ({poses.shape[0]},) integer ns, got shape {stamps.shape} {stamps.dtype}"
        )
    t = _types(distro)
    out = []
    for i, (T, s) in enumerate(zip(poses, stamps, strict=True)):
        if not is_rigid(T):
            raise ValueError(f"trajectory poses[{i}] is not a finite rigid transform")
        out.append(t.pose_stamped(header=header(frame_id, int(s), distro), pose=pose_msg(T, distro)))
    last = int(stamps[-1]) if stamps.size else 0
    return t.path(header=header(frame_id, last, distro), poses=out)


# ---------------------------------------------------------------------------------------------
# Colours


def _clip_rgba(c: Rgba) -> Rgba:
    r, g, b, a = (min(max(float(v), 0.0), 1.0) for v in c)
    return (r, g, b, max(a, 0.05))  # RViz draws nothing at alpha 0


def id_colour(node_id: int, *, dim: bool = False) -> Rgba:
    """A stable, well-spread colour for ``node_id`` (golden-ratio hue steps, so neighbouring
    ids differ clearly); ``dim`` (inactive segments, history) is darker and translucent."""
    h = (int(node_id) * _GOLDEN) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, 0.7, 0.5 if dim else 0.95)
    return _clip_rgba((r, g, b, 0.55 if dim else 1.0))


def rank_colour(rank: int, n: int) -> Rgba:
    """Hit colour by rank: the best green, then through yellow to red for the last of ``n``."""
    f = rank / (n - 1) if n > 1 else 0.0
    return _clip_rgba((min(1.0, 2 * f) * 0.9 + 0.1, min(1.0, 2 * (1 - f)) * 0.85 + 0.1, 0.1, 1.0))


# ---------------------------------------------------------------------------------------------
# Markers


class _Builder:
    """Makes markers of one array: same header, the defaults RViz expects filled in."""

    def __init__(self, frame_id: str, stamp_ns: int, distro: str) -> None:
        self.t = _types(distro)
        self.frame_id, self.stamp_ns, self.distro = frame_id, stamp_ns, distro
        header(frame_id, stamp_ns, distro)  # validate once, with a clear error
        self.sec, self.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        self.markers: list[Any] = []

    def _header(self) -> Any:
        # one Header object per marker: they are mutable dataclasses, and a caller editing one
        # marker's header must not edit the others'
        t = self.t
        return t.header(stamp=t.time(sec=self.sec, nanosec=self.nanosec), frame_id=self.frame_id)

    def point(self, p: Iterable[float]) -> Any:
        x, y, z = p
        return self.t.point(x=float(x), y=float(y), z=float(z))

    def colour(self, c: Rgba) -> Any:
        r, g, b, a = c
        return self.t.colour(r=r, g=g, b=b, a=a)

    def add(
        self,
        ns: str,
        marker_id: int,
        kind: int,
        *,
        position: np.ndarray | None = None,
        scale: tuple[float, float, float] = (1.0, 1.0, 1.0),
        colour: Rgba = _WHITE,
        points: list[Any] | None = None,
        colours: list[Any] | None = None,
        text: str = "",
        action: int | None = None,
    ) -> Any:
        t = self.t
        if not 0 <= marker_id <= _INT32_MAX:
            raise ValueError(f"marker {ns}/{marker_id}: id outside int32 (node id too large for a Marker.id)")
        sx, sy, sz = (max(float(v), MIN_SCALE_M) for v in scale)
        kw: dict[str, Any] = dict(
            header=self._header(),
            ns=ns,
            id=marker_id,
            type=kind,
            action=t.marker.ADD if action is None else action,
            pose=_position_pose(np.zeros(3) if position is None else position, t),
            scale=t.vector3(x=sx, y=sy, z=sz),
            color=self.colour(colour),
            lifetime=t.duration(sec=0, nanosec=0),  # 0: until replaced or deleted
            frame_locked=False,
            points=points or [],
            colors=colours or [],
            text=text,
            mesh_resource="",
            mesh_use_embedded_materials=False,
        )
        f = t.marker_fields
        if "texture_resource" in f:
            kw["texture_resource"] = ""
            kw["texture"] = t.compressed_image(header=self._header(), format="", data=np.zeros(0, np.uint8))
            kw["uv_coordinates"] = []
        if "mesh_file" in f:
            kw["mesh_file"] = t.mesh_file(filename="", data=np.zeros(0, np.uint8))
        m = t.marker(**{k: v for k, v in kw.items() if k in f})
        self.markers.append(m)
        return m

    def delete_all(self) -> None:
        # ns "" : both RViz readings of DELETEALL (everything, or everything in ns) clear all
        self.add("", 0, self.t.marker.CUBE, action=self.t.marker.DELETEALL)

    def array(self) -> Any:
        return self.t.marker_array(markers=self.markers)


def _finite(where: str, *arrays: np.ndarray | None) -> None:
    for a in arrays:
        if a is not None and not np.all(np.isfinite(a)):
            raise ValueError(f"{where}: non-finite coordinates {np.asarray(a).tolist()}")


def _padded_box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box grown about its centre to at least :data:`MIN_SCALE_M` on every axis."""
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    c, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, MIN_SCALE_M / 2)
    return c - half, c + half


# The 12 edges of a box as pairs of corner indices; corner k has x from bit 0, y bit 1, z bit 2.
_BOX_EDGES = [(a, a | b) for b in (1, 2, 4) for a in range(8) if not a & b]


def _box_outline(b: _Builder, lo: np.ndarray, hi: np.ndarray) -> list[Any]:
    """The 24 end points of a box's 12 edges, for a ``LINE_LIST``."""
    pts = [b.point([(hi if k & bit else lo)[axis] for axis, bit in enumerate((1, 2, 4))]) for k in range(8)]
    return [pts[i] for e in _BOX_EDGES for i in e]


def graph_markers(
    segments: Iterable[SegmentNode],
    places: Iterable[PlaceNode],
    rooms: Iterable[RoomNode],
    edges: Iterable[Edge],
    *,
    frame_id: str,
    stamp_ns: int,
    show_ids: bool = True,
    distro: str = "jazzy",
) -> Any:
    """The scene graph as one ``visualization_msgs/MarkerArray`` that replaces the previous one
    in RViz (``DELETEALL`` first); namespaces and ids as in this module's docstring. Nodes are
    drawn in id order; of two nodes with one id, the later wins. An edge to a node not given is
    left out."""
    return _graph_markers(segments, places, rooms, (edge_key(e) for e in edges), frame_id, stamp_ns, show_ids, distro)


def replica_markers(replica: GraphReplica, *, frame_id: str, stamp_ns: int, show_ids: bool = True, distro: str = "jazzy") -> Any:
    """:func:`graph_markers` of a :class:`~shared.graph.scene.GraphReplica` (its edges are
    stored as ``(kind, source, target)`` keys, taken as they are)."""
    return _graph_markers(
        replica.segments.values(), replica.places.values(), replica.rooms.values(), replica.edges,
        frame_id, stamp_ns, show_ids, distro,
    )


def _graph_markers(
    segments: Iterable[SegmentNode],
    places: Iterable[PlaceNode],
    rooms: Iterable[RoomNode],
    edge_keys: Iterable[EdgeKey],
    frame_id: str,
    stamp_ns: int,
    show_ids: bool,
    distro: str,
) -> Any:
    b = _Builder(frame_id, stamp_ns, distro)
    M = b.t.marker
    segs = {s.id: s for s in segments}
    plcs = {p.id: p for p in places}
    rms = {r.id: r for r in rooms}
    b.delete_all()

    # Segments as wire boxes rather than translucent CUBEs: an outline does not hide the mesh
    # or point cloud inside it, boxes nested in others (a cup on a table) stay visible, and
    # overlapping boxes do not blend into a coloured fog, which translucent cubes do in RViz
    # (it does not sort transparent markers). Query hits, few, are the solid ones (hits_markers).
    cents, cent_colours = [], []
    for sid in sorted(segs):
        s = segs[sid]
        _finite(f"segment {sid}", s.centroid, s.bbox_min, s.bbox_max)
        colour = id_colour(sid, dim=not s.active)
        lo, hi = _padded_box(s.bbox_min, s.bbox_max)
        b.add("segments", sid, M.LINE_LIST, scale=(BOX_LINE_M,) * 3, colour=colour, points=_box_outline(b, lo, hi))
        cents.append(b.point(s.centroid))
        cent_colours.append(b.colour(colour))
    if cents:
        b.add("centroids", 0, M.SPHERE_LIST, scale=(CENTROID_M,) * 3, points=cents, colours=cent_colours)
    if show_ids:
        for sid in sorted(segs):
            s = segs[sid]
            top = np.array([s.centroid[0], s.centroid[1], max(s.bbox_max[2], s.centroid[2]) + ID_TEXT_M])
            b.add("ids", sid, M.TEXT_VIEW_FACING, position=top, scale=(ID_TEXT_M,) * 3, text=str(sid))

    # places coloured by their room, so the room segmentation reads off the place layer
    if plcs:
        pts, cols = [], []
        for pid in sorted(plcs):
            p = plcs[pid]
            _finite(f"place {pid}", p.position)
            pts.append(b.point(p.position))
            c = id_colour(p.room, dim=not p.active) if p.room is not None else _GREY
            cols.append(b.colour(c))
        b.add("places", 0, M.SPHERE_LIST, scale=(PLACE_M,) * 3, points=pts, colours=cols)

    for rid in sorted(rms):
        r = rms[rid]
        _finite(f"room {rid}", r.centroid, r.bbox_min, r.bbox_max)
        if 2 * rid + 1 > _INT32_MAX:
            raise ValueError(f"room {rid}: id too large for its marker ids (2 * id + 1 must fit int32)")
        colour = id_colour(rid)
        has_box = r.bbox_min is not None and r.bbox_max is not None
        if show_ids:
            top = (max(r.bbox_max[2], r.centroid[2]) if has_box else r.centroid[2]) + ROOM_TEXT_M
            pos = np.array([r.centroid[0], r.centroid[1], top])
            b.add("rooms", 2 * rid, M.TEXT_VIEW_FACING, position=pos, scale=(ROOM_TEXT_M,) * 3, colour=colour,
                  text=r.name or f"room {rid}")
        if has_box:
            lo, hi = _padded_box(r.bbox_min, r.bbox_max)
            z = lo[2]
            ring = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1]), (lo[0], lo[1])]
            pts = [b.point((x, y, z)) for x, y in ring]
            b.add("rooms", 2 * rid + 1, M.LINE_STRIP, scale=(ROOM_LINE_M,) * 3, colour=colour, points=pts)

    _edge_markers(b, segs, plcs, rms, edge_keys)
    return b.array()


def _edge_markers(
    b: _Builder, segs: dict[int, SegmentNode], plcs: dict[int, PlaceNode], rms: dict[int, RoomNode], edge_keys: Iterable[EdgeKey]
) -> None:
    building = None
    if rms:
        cs = np.array([r.centroid for r in rms.values()])
        top = max(max(r.bbox_max[2], r.centroid[2]) if r.bbox_max is not None else r.centroid[2] for r in rms.values())
        building = np.array([cs[:, 0].mean(), cs[:, 1].mean(), top + BUILDING_ABOVE_M])

    def where(layer: str, i: int) -> np.ndarray | None:
        if layer == "segment":
            n = segs.get(i)
            return None if n is None else n.centroid
        if layer == "place":
            n = plcs.get(i)
            return None if n is None else n.position
        if layer == "room":
            n = rms.get(i)
            return None if n is None else n.centroid
        return building if i == BUILDING_ID else None

    layers = {
        "segment_place": ("segment", "place"),
        "place_place": ("place", "place"),
        "place_room": ("place", "room"),
        "room_building": ("room", "building"),
    }
    by_kind: dict[str, list[Any]] = {k: [] for k in EDGE_KINDS}
    skipped = 0
    for kind, src, dst in sorted(edge_keys):
        if kind not in layers:
            raise ValueError(f"edge ({kind!r}, {src}, {dst}): unknown kind, expected one of {', '.join(EDGE_KINDS)}")
        lo_layer, hi_layer = layers[kind]
        a, c = where(lo_layer, src), where(hi_layer, dst)
        if a is None or c is None:
            skipped += 1
            continue
        by_kind[kind] += [b.point(a), b.point(c)]
    if skipped:
        log.debug("graph markers: %d edges to nodes not in the graph left out", skipped)
    for kind in EDGE_KINDS:
        if by_kind[kind]:  # an empty LINE_LIST makes RViz warn; a kind without edges has none
            b.add(f"edges/{kind}", 0, b.t.marker.LINE_LIST, scale=(EDGE_LINE_M,) * 3, colour=_EDGE_COLOURS[kind],
                  points=by_kind[kind])


def hits_markers(reply: QueryReply, *, frame_id: str, stamp_ns: int, distro: str = "jazzy") -> Any:
    """A query's answer as a ``MarkerArray`` replacing the previous one (``DELETEALL`` first):
    per segment hit a translucent ``CUBE`` over its box (ns ``hits``, id = rank - 1), coloured
    by rank (best green, last red), and a label ``#rank id score`` above it (ns ``hits/labels``);
    per room hit a label ``#rank name score`` at its centroid (ns ``hits/rooms``). A reply with an
    error (no hits) clears the previous hits."""
    b = _Builder(frame_id, stamp_ns, distro)
    M = b.t.marker
    b.delete_all()
    n = len(reply.hits)
    for i, h in enumerate(reply.hits):
        _finite(f"query hit #{i + 1} (segment {h.segment})", h.centroid, h.bbox_min, h.bbox_max)
        lo, hi = _padded_box(h.bbox_min, h.bbox_max)
        r, g, bl, _ = rank_colour(i, n)
        # solid enough to stand out from the graph's wire boxes, translucent enough to see the object
        b.add("hits", i, M.CUBE, position=(lo + hi) / 2, scale=tuple(hi - lo), colour=(r, g, bl, 0.5))
        pos = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] + HIT_TEXT_M])
        b.add("hits/labels", i, M.TEXT_VIEW_FACING, position=pos, scale=(HIT_TEXT_M,) * 3, colour=(r, g, bl, 1.0),
              text=f"#{i + 1} {h.segment} {h.score:.2f}")
    nr = len(reply.rooms)
    for i, rh in enumerate(reply.rooms):
        _finite(f"query room hit #{i + 1} (room {rh.room})", rh.centroid)
        top = (max(rh.bbox_max[2], rh.centroid[2]) if rh.bbox_max is not None else rh.centroid[2]) + ROOM_TEXT_M
        pos = np.array([rh.centroid[0], rh.centroid[1], top])
        label = rh.name or f"room {rh.room}"
        b.add("hits/rooms", i, M.TEXT_VIEW_FACING, position=pos, scale=(ROOM_TEXT_M,) * 3, colour=rank_colour(i, nr),
              text=f"#{i + 1} {label} {rh.score:.2f}")
    return b.array()


def hits_pose_array(reply: QueryReply, *, frame_id: str, stamp_ns: int, distro: str = "jazzy") -> Any:
    """A query's answer as goals for a planner: a ``geometry_msgs/PoseArray`` of the hits'
    centroids, best first, identity orientation; for a reply without segment hits (a ``rooms``
    target), the ranked rooms' centroids. Empty for an error reply."""
    t = _types(distro)
    pts = [h.centroid for h in reply.hits] if reply.hits else [r.centroid for r in reply.rooms]
    for i, p in enumerate(pts):
        _finite(f"query hit #{i + 1}", p)
    return t.pose_array(header=header(frame_id, stamp_ns, distro), poses=[_position_pose(p, t) for p in pts])


def marker_count(array: Any) -> dict[str, int]:
    """Markers per namespace of a ``MarkerArray`` (``""`` is the DELETEALL); for logs and tests."""
    out: dict[str, int] = {}
    for m in array.markers:
        out[m.ns] = out.get(m.ns, 0) + 1
    return out

