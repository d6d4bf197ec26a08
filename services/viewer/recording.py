"""Log a scene graph, the camera and query hits into a Rerun recording.

Functional core of the viewer: no Zenoh, every function takes an explicit
``rr.RecordingStream`` so several recordings (tests, the live node, an offline export) can
coexist in one process. Rerun itself is imported inside the functions: the colour and
geometry helpers here are shared with :mod:`services.viewer.render`, which must work
without it.

Entity paths (the world is z up, metres)::

    world                          ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/mesh                     Mesh3D, vertices coloured by segment (grey: none)
    world/segments/boxes           Boxes3D per segment, labelled "id (room r)"
    world/segments/centroids       Points3D
    world/places                   Points3D, radius a fraction of the free-space radius
    world/rooms                    Points3D labelled "room r"
    world/building                 Points3D, mean room centroid raised by 2 m
    world/edges/<kind>             LineStrips3D, kind in EDGE_KINDS
    world/trajectory               LineStrips3D of the camera positions
    world/camera                   Transform3D (T_world_cam)
    world/camera/image             Pinhole (OpenCV RDF axes) + AnnotationContext
    world/camera/image/rgb         Image (JPEG)
    world/camera/image/tracks      SegmentationImage, class = track id + 1, 0 = none
    world/queries/<slug>           Boxes3D of one query's hits, "#rank score 'text'"

The camera lives under ``world`` (not a separate ``camera/`` root) so that its transform is
resolved in the world frame and the image shows up in the 3D view at the camera's pose.

Timelines: ``graph_seq`` for graph versions, ``frame`` for camera frames; a snapshot logged
without a version is static.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np

from shared.graph.colors import NONE_COLOR, segment_color, segment_colors  # noqa: F401 - the viewer's palette lives in shared
from shared.messages.frames import Frame, TrackedFrame
from shared.messages.graph import GraphSnapshot, MeshChunk
from shared.messages.rpc import QueryHit

if TYPE_CHECKING:
    import rerun as rr

log = logging.getLogger(__name__)

APP_ID = "trackgraph"

WORLD = "world"
MESH = "world/mesh"
SEGMENT_BOXES = "world/segments/boxes"
SEGMENT_CENTROIDS = "world/segments/centroids"
PLACES = "world/places"
ROOMS = "world/rooms"
BUILDING = "world/building"
EDGES = "world/edges"
TRAJECTORY = "world/trajectory"
CAMERA = "world/camera"
IMAGE = "world/camera/image"
RGB_IMAGE = "world/camera/image/rgb"
TRACKS_IMAGE = "world/camera/image/tracks"
QUERIES = "world/queries"

GRAPH_TIMELINE = "graph_seq"
FRAME_TIMELINE = "frame"

EDGE_KINDS = ("segment_place", "place_place", "place_room", "room_building")
EDGE_COLORS: dict[str, tuple[int, int, int]] = {
    "segment_place": (150, 150, 150),
    "place_place": (40, 110, 220),
    "place_room": (60, 170, 90),
    "room_building": (200, 120, 30),
}
PLACE_COLOR = (40, 110, 220)
ROOM_COLOR = (20, 140, 60)
BUILDING_COLOR = (200, 120, 30)
TRAJECTORY_COLOR = (230, 30, 140)
HIT_COLORS = ((255, 30, 30), (255, 140, 0), (255, 220, 0), (255, 0, 200), (0, 230, 255), (120, 255, 0))
"""Bright hit colours by rank (rank 1 red), repeating."""

BUILDING_RAISE_M = 2.0
"""The building node sits this far above the mean room centroid, so its edges are visible."""
PLACE_RADIUS_SCALE = 0.15
"""Place markers are drawn at this fraction of their free-space radius (the full radius
would hide the map)."""
MAX_TRACK_CLASS = 65535



# ---------------------------------------------------------------- colours and geometry


def slug(text: str, max_len: int = 40) -> str:
    """An entity-path-safe name for a query text ("Red armchair!" -> "red_armchair")."""
    s = re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")[:max_len].strip("_")
    return s or "query"


def building_position(snapshot: GraphSnapshot) -> Annotated[np.ndarray, "(3,) float64"] | None:
    """Where the (implicit) building node is drawn: above the mean room centroid."""
    if not snapshot.rooms:
        return None
    c = np.mean([r.centroid for r in snapshot.rooms], axis=0)
    return c + np.array([0.0, 0.0, BUILDING_RAISE_M])


def edge_lines(snapshot: GraphSnapshot) -> dict[str, Annotated[np.ndarray, "(E, 2, 3) float64"]]:
    """Endpoints of every edge by kind; edges to nodes the snapshot lacks are skipped."""
    seg = {s.id: s.centroid for s in snapshot.segments}
    place = {p.id: p.position for p in snapshot.places}
    room = {r.id: r.centroid for r in snapshot.rooms}
    b = building_position(snapshot)
    out: dict[str, list] = {k: [] for k in EDGE_KINDS}
    for e in snapshot.edges:
        if e.kind == "room_building":
            a, z = room.get(e.source), b
        else:
            lo, hi = {"segment_place": (seg, place), "place_place": (place, place), "place_room": (place, room)}[e.kind]
            a, z = lo.get(e.source), hi.get(e.target)
        if a is not None and z is not None:
            out[e.kind].append((a, z))
    return {k: np.asarray(v, np.float64).reshape(-1, 2, 3) for k, v in out.items()}


def vertex_normals(mesh: MeshChunk) -> Annotated[np.ndarray, "(V, 3) float32"] | None:
    """Area-weighted vertex normals, so the mesh is shaded rather than flat colour."""
    v, f = mesh.vertices.astype(np.float64), mesh.faces
    if not f.size:
        return None
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for j in range(3):
        np.add.at(n, f[:, j], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(norm > 0, norm, 1.0)).astype(np.float32)


# ---------------------------------------------------------------- logging


def new_recording(application_id: str = APP_ID, recording_id: str | None = None) -> rr.RecordingStream:
    """A recording that is not the global one (several may coexist)."""
    import rerun as rr

    return rr.RecordingStream(application_id, recording_id=recording_id, make_default=False, make_thread_default=False)


def log_world_frame(rec: rr.RecordingStream) -> None:
    """The world is z up (the synthetic scenes and the dataset readers' world frames)."""
    import rerun as rr

    rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)


def _at_graph(rec: rr.RecordingStream, time_seq: int | None) -> bool:
    """Set the graph timeline; returns whether to log static (no version given)."""
    if time_seq is None:
        return True
    rec.set_time(GRAPH_TIMELINE, sequence=int(time_seq))
    return False


def log_snapshot(rec: rr.RecordingStream, snapshot: GraphSnapshot, *, time_seq: int | None = None) -> None:
    """Log the whole graph; each layer replaces the previous one, so removed nodes vanish.

    A snapshot without a mesh leaves the logged mesh as it is (the live viewer only sends
    the mesh when it changed).
    """
    import rerun as rr

    static = _at_graph(rec, time_seq)
    if snapshot.mesh is not None:
        _log_mesh(rec, snapshot.mesh, static)

    segs = snapshot.segments
    ids = np.array([s.id for s in segs], np.int64)
    colors = segment_colors(ids)
    alpha = np.array([255 if s.active else 110 for s in segs], np.uint8).reshape(-1, 1)
    mins = np.array([s.bbox_min for s in segs], np.float64).reshape(-1, 3)
    maxs = np.array([s.bbox_max for s in segs], np.float64).reshape(-1, 3)
    labels = [f"{s.id}" if s.room is None else f"{s.id} (room {s.room})" for s in segs]
    rec.log(
        SEGMENT_BOXES,
        rr.Boxes3D(mins=mins, sizes=maxs - mins, colors=np.hstack([colors, alpha]), labels=labels, radii=0.004),
        static=static,
    )
    cents = np.array([s.centroid for s in segs], np.float64).reshape(-1, 3)
    rec.log(SEGMENT_CENTROIDS, rr.Points3D(cents, colors=colors, radii=0.03), static=static)

    pos = np.array([p.position for p in snapshot.places], np.float64).reshape(-1, 3)
    radii = np.clip(np.array([p.radius for p in snapshot.places], np.float64) * PLACE_RADIUS_SCALE, 0.02, 0.3)
    rec.log(PLACES, rr.Points3D(pos, radii=radii, colors=PLACE_COLOR), static=static)

    rpos = np.array([r.centroid for r in snapshot.rooms], np.float64).reshape(-1, 3)
    rlabels = [f"room {r.id}" + (f" {r.name}" if r.name else "") for r in snapshot.rooms]
    rec.log(ROOMS, rr.Points3D(rpos, radii=0.12, colors=ROOM_COLOR, labels=rlabels), static=static)
    b = building_position(snapshot)
    bpos = np.zeros((0, 3)) if b is None else b.reshape(1, 3)
    rec.log(BUILDING, rr.Points3D(bpos, radii=0.18, colors=BUILDING_COLOR, labels=["building"][: len(bpos)]), static=static)

    for kind, lines in edge_lines(snapshot).items():
        rec.log(
            f"{EDGES}/{kind}",
            rr.LineStrips3D(list(lines), colors=EDGE_COLORS[kind], radii=0.008 if kind == "segment_place" else 0.015),
            static=static,
        )


def _log_mesh(rec: rr.RecordingStream, mesh: MeshChunk, static: bool) -> None:
    import rerun as rr

    if mesh.vertices.shape[0] == 0:
        rec.log(MESH, rr.Clear(recursive=False), static=static)
        return
    rec.log(
        MESH,
        rr.Mesh3D(
            vertex_positions=mesh.vertices,
            triangle_indices=mesh.faces if mesh.faces.size else None,
            vertex_normals=vertex_normals(mesh),
            vertex_colors=segment_colors(mesh.segment_ids),
        ),
        static=static,
    )


def log_trajectory(
    rec: rr.RecordingStream, positions: Annotated[np.ndarray, "(N, 3) float"], *, time_frame: int | None = None
) -> None:
    """The camera path as one line strip (static unless a frame time is given)."""
    import rerun as rr

    p = np.asarray(positions, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    static = time_frame is None
    if not static:
        rec.set_time(FRAME_TIMELINE, sequence=int(time_frame))
    strips = [p] if len(p) >= 2 else []
    rec.log(TRAJECTORY, rr.LineStrips3D(strips, colors=TRAJECTORY_COLOR, radii=0.02), static=static)


def log_frame(
    rec: rr.RecordingStream,
    frame: Frame,
    track_ids: Annotated[np.ndarray, "(H, W) int, -1 = none"] | None = None,
    *,
    jpeg_quality: int = 85,
) -> None:
    """The camera at this frame: pose, pinhole, RGB (JPEG, to keep recordings small) and
    the track map as a segmentation overlay coloured like the segments."""
    import rerun as rr

    rec.set_time(FRAME_TIMELINE, sequence=int(frame.frame_index))
    T = frame.T_world_cam
    rec.log(CAMERA, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    h, w = frame.rgb.shape[:2]
    rec.log(
        IMAGE,
        rr.Pinhole(
            image_from_camera=frame.intrinsics.matrix(),
            resolution=[w, h],
            camera_xyz=rr.ViewCoordinates.RDF,
            image_plane_distance=0.4,
        ),
    )
    rec.log(RGB_IMAGE, rr.Image(frame.rgb).compress(jpeg_quality=jpeg_quality))
    if track_ids is None:
        return
    ids = _fit(np.asarray(track_ids), h, w)
    present = np.unique(ids[ids >= 0])
    if present.size and present.max() >= MAX_TRACK_CLASS:
        log.warning("track ids above %d drawn as none", MAX_TRACK_CLASS - 1)
        ids = np.where(ids >= MAX_TRACK_CLASS, -1, ids)
        present = present[present < MAX_TRACK_CLASS]
    cols = segment_colors(present)
    infos = [rr.AnnotationInfo(0, "none", (0, 0, 0, 0))] + [
        rr.AnnotationInfo(int(t) + 1, f"track {int(t)}", tuple(int(x) for x in c)) for t, c in zip(present, cols, strict=True)
    ]
    rec.log(IMAGE, rr.AnnotationContext(infos))
    rec.log(TRACKS_IMAGE, rr.SegmentationImage((ids + 1).astype(np.uint16), opacity=0.5))


def _fit(ids: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resize of a track map to the image (a tracker may run smaller)."""
    if ids.shape == (h, w):
        return ids.astype(np.int64)
    rows = np.minimum((np.arange(h) * ids.shape[0]) // h, ids.shape[0] - 1)
    cols = np.minimum((np.arange(w) * ids.shape[1]) // w, ids.shape[1] - 1)
    return ids[np.ix_(rows, cols)].astype(np.int64)


def log_tracked_frame(rec: rr.RecordingStream, tf: TrackedFrame) -> None:
    """A tracker output frame: the camera, its image and its source-track masks."""
    log_frame(rec, tf.frame, tf.track_ids)


def log_query_hits(rec: rr.RecordingStream, text: str, hits: list[QueryHit], *, time_seq: int | None = None) -> str:
    """One query's hits as thick bright boxes under ``world/queries/<slug>``; returns the path."""
    import rerun as rr

    path = f"{QUERIES}/{slug(text)}"
    static = _at_graph(rec, time_seq)
    mins = np.array([h.bbox_min for h in hits], np.float64).reshape(-1, 3)
    maxs = np.array([h.bbox_max for h in hits], np.float64).reshape(-1, 3)
    # Pad so a hit box is drawn around, not inside, its segment's box.
    pad = 0.03
    colors = [HIT_COLORS[i % len(HIT_COLORS)] for i in range(len(hits))]
    labels = [f"#{i + 1} {h.score:.2f} '{text}'" for i, h in enumerate(hits)]
    rec.log(
        path,
        rr.Boxes3D(mins=mins - pad, sizes=maxs - mins + 2 * pad, colors=colors, labels=labels, radii=0.025, show_labels=True),
        static=static,
    )
    return path


# ---------------------------------------------------------------- offline export


def write_map_recording(
    map_dir: Path,
    out_rrd: Path,
    *,
    queries: dict[str, list[QueryHit]] | None = None,
    sequence_dir: Path | None = None,
    max_frames: int = 60,
) -> Path:
    """A self-contained .rrd of a saved map (graph, trajectory, hits and, with the
    sequence and ``--save-tracks`` output, a sample of tracked frames).

    Written under a temporary name and renamed, so a viewer never opens a half file.
    """
    from shared.graph.store import MapStore

    map_dir, out_rrd = Path(map_dir), Path(out_rrd)
    store = MapStore(map_dir / "graph")
    if store.latest_name() is None and not store.names():
        raise FileNotFoundError(f"{map_dir}: no map snapshot in {map_dir / 'graph'} (is it a `trackgraph map` output folder?)")
    state = store.load()
    out_rrd.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_rrd.with_name(f".{out_rrd.stem}.{os.getpid()}.partial.rrd")
    rec = new_recording()
    try:
        rec.save(tmp)
        log_world_frame(rec)
        log_snapshot(rec, state.snapshot)
        traj = state.extra.get("trajectory")
        if traj is not None:
            log_trajectory(rec, np.asarray(traj))
        for text, hits in (queries or {}).items():
            log_query_hits(rec, text, hits)
        if sequence_dir is not None:
            n = _log_sequence_frames(rec, map_dir, Path(sequence_dir), max_frames)
            log.info("logged %d tracked frames from %s", n, sequence_dir)
        rec.flush()
        rec.disconnect()
        os.replace(tmp, out_rrd)
    except BaseException:
        rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise
    log.info("wrote %s (graph %d, %d segments)", out_rrd, state.snapshot.graph_seq, len(state.snapshot.segments))
    return out_rrd


def pick_even(indices: list[int], k: int) -> list[int]:
    """At most ``k`` evenly spaced entries, first and last included."""
    if k <= 0 or not indices:
        return []
    if len(indices) <= k:
        return list(indices)
    pos = np.unique(np.round(np.linspace(0, len(indices) - 1, k)).astype(int))
    return [indices[i] for i in pos]


def _log_sequence_frames(rec: rr.RecordingStream, map_dir: Path, sequence_dir: Path, max_frames: int) -> int:
    from shared.datasets import open_sequence
    from shared.eval.track_io import list_track_frames, read_id_png, track_path, tracks_dir

    if not tracks_dir(map_dir).is_dir():
        log.warning("%s has no tracks/ folder (map it with --save-tracks): no frames logged", map_dir)
        return 0
    frames = pick_even(list_track_frames(map_dir), max_frames)
    n = 0
    with open_sequence(sequence_dir, "replica") as reader:
        for i in frames:
            if i >= len(reader):
                log.warning("track map of frame %d but %s has %d frames; skipped", i, sequence_dir, len(reader))
                continue
            log_frame(rec, reader.frame(i), read_id_png(track_path(map_dir, i)))
            n += 1
    return n


def entity_paths(rrd: Path) -> set[str]:
    """Entity paths in a saved recording (for tests and sanity checks)."""
    from rerun.chunk import RrdReader

    return {str(c.entity_path) for c in RrdReader(Path(rrd)).stream().to_chunks()}
