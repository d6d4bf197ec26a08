"""The fusion core: tracked frames in, scene-graph deltas out. No Zenoh here.

Per frame it fuses depth, colour and source-track masks into the hypothesis TSDF (III-C,
eqs. 5-6) and moves the active window (III-A). Every ``mesh_every_n_frames`` frames it runs
marching cubes, the segment updater and re-identification (III-D, III-E), rebuilds places
and rooms, and returns the resulting :class:`GraphDelta`.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

import numpy as np

from services.fusion.hypotheses import confidence
from services.fusion.roomnames import (
    VIEW_SAMPLE_STRIDE,
    RoomVocabulary,
    describe_rooms,
    view_shares,
)
from services.fusion.rooms import Hierarchy, HierarchyBuilder
from services.fusion.segments import SegmentLayer
from services.fusion.tsdf import HypothesisTSDF
from services.fusion.types import HypothesisMesh, TrackState
from shared.config.fusion import FusionConfig
from shared.geometry import backproject, pose_row
from shared.graph.roomgrid import RoomGrid
from shared.graph.scene import SceneGraph
from shared.messages.frames import TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, MeshChunk, RoomNode, SegmentNode
from shared.messages.keyframes import TrackFeatures

log = logging.getLogger(__name__)

SURFACE_CELL_M = 0.05
"""Resolution of the whole-map surface sample that places and rooms are built from."""


class FusionCore:
    """TSDF, segments and the hierarchy for one robot's map."""

    def __init__(self, cfg: FusionConfig, device: str = "auto") -> None:
        self.cfg = cfg
        self.tsdf = HypothesisTSDF(cfg.tsdf, device=device, mesh_weight_threshold=cfg.tsdf.mesh_min_weight)
        self.segments = SegmentLayer(cfg.segments, cfg.reid)
        self.hierarchy = HierarchyBuilder(cfg.graph)
        self.graph = SceneGraph()
        self.tracks: dict[int, TrackState] = {}
        self.trajectory: list[np.ndarray] = []
        self.poses: list[np.ndarray] = []
        """(7,) ``x y z qx qy qz qw`` of each fused frame, for the agent layer."""
        self.pose_frames: list[int] = []
        self.last_hierarchy: Hierarchy | None = None
        self.views: dict[int, np.ndarray] = {}
        """Keyframe index -> its whole-image embedding (``TrackFeatures.view``), for room features."""
        self.view_points: dict[int, np.ndarray] = {}
        """Keyframe index -> (N, 2) float32 world xy of a sparse sample of its depth: what the
        view shows, to give it to a room."""
        self.room_vocabulary: RoomVocabulary | None = None
        """The room labels' text embeddings; set by the session once ``vl/embed`` answers."""
        self.surface: dict[tuple[int, int, int], np.ndarray] = {}
        self.frames = 0
        self.updates = 0
        self.last_frame_index = -1
        self.mesh: HypothesisMesh | None = None

    # ------------------------------------------------------------------ inputs

    def add_frame(self, tf: TrackedFrame) -> GraphDelta | None:
        """Fuse one tracked frame; every N frames also update the graph and return its delta."""
        fr = tf.frame
        tsdf = self.cfg.tsdf
        gamma = {o.track_id: confidence(o.keyframe, o.frames_since_keyframe, tsdf.alpha_p, tsdf.beta_p) for o in tf.tracks}
        ids = tf.track_ids
        # Not in the paper (docs/method.md, F3): a propagated pixel votes only where eq. 1 was
        # confident of its track; ``min_label_confidence: 0`` fuses every pixel as the paper does.
        if tf.confidence is not None and tsdf.min_label_confidence > 0:
            ids = np.where(tf.confidence >= round(255 * tsdf.min_label_confidence), ids, -1)
        stats = self.tsdf.integrate(fr.depth_m(), fr.rgb, fr.intrinsics, fr.T_world_cam, ids, gamma)
        for tid, w in stats.displaced.items():
            self._track(tid).displaced_weight += float(w)
        for o in tf.tracks:
            self._track(o.track_id)
        if tf.keyframe:
            self.view_points[int(fr.frame_index)] = _seen_xy(fr)
        position = fr.T_world_cam[:3, 3].copy()
        self.tsdf.update_window(position)
        self.trajectory.append(position)
        self.poses.append(pose_row(fr.T_world_cam))
        self.pose_frames.append(int(fr.frame_index))
        self.frames += 1
        self.last_frame_index = fr.frame_index
        if self.frames % self.cfg.mesh_every_n_frames == 0:
            return self.update()
        return None

    def add_track_features(self, msg: TrackFeatures) -> None:
        """Track features from the tracker (aggregated DINOv3 and CLIP, eq. 4)."""
        for f in msg.tracks:
            st = self._track(f.track_id)
            st.dino = np.asarray(f.dino, np.float32)
            st.clip = None if f.clip is None else np.asarray(f.clip, np.float32)
            st.clip_count = f.clip_count
        for tid in msg.retired:
            self._track(tid).retired = True
        if msg.view is not None:
            self.views[int(msg.frame_index)] = np.asarray(msg.view, np.float32)

    def set_room_vocabulary(self, labels: list[str], embeddings: Annotated[np.ndarray, "(L, D) float32"]) -> None:
        """The room labels (``GraphConfig.room_labels``) and their text embeddings: rooms are
        named from the next update on."""
        emb = np.asarray(embeddings, np.float32).reshape(len(labels), -1)
        self.room_vocabulary = RoomVocabulary(tuple(labels), emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12))

    def _track(self, tid: int) -> TrackState:
        st = self.tracks.get(tid)
        if st is None:
            st = self.tracks[tid] = TrackState(track_id=tid)
        return st

    # ------------------------------------------------------------------ graph

    def update(self) -> GraphDelta:
        """Mesh, segments, re-identification, places and rooms; the delta to the last version."""
        mesh = self.tsdf.extract_mesh()
        self.mesh = mesh
        center = self.trajectory[-1] if self.trajectory else np.zeros(3)
        changes = self.segments.update(mesh, self.tracks, window=(center, self.cfg.tsdf.active_window_m))
        self._add_surface(mesh.vertices)
        places = rooms = None
        points = self.surface_points()
        if len(points) and len(self.trajectory):
            try:
                h = self.hierarchy.build(points, np.stack(self.trajectory), active=(center, self.cfg.tsdf.active_window_m))
                places, rooms = h.places, h.rooms
                self.last_hierarchy = h
            except ValueError as exc:
                # Too little of the floor is mapped yet to find free space; keep the last layers.
                log.debug("places and rooms not rebuilt: %s", exc)
        ids = sorted(set(changes.added) | set(changes.changed))
        self.updates += 1
        with_mesh = self.updates % self.cfg.mesh_delta_every_n_updates == 0
        return self.graph.apply_update(
            segments_changed=self.segments.nodes(ids),
            segments_removed=changes.removed,
            places=places,
            rooms=rooms,
            mesh=self.mesh_chunk() if with_mesh else None,
            frame_index=self.last_frame_index,
            describe_rooms=self._describe_rooms,
        )

    def _view_shares(self, order: list[int]) -> tuple[Annotated[np.ndarray, "(K, R) float64"], Annotated[np.ndarray, "(K, D) float32"]]:
        """What share of each keyframe view falls in each room of ``order``, and the views."""
        h = self.last_hierarchy
        none = np.zeros((0, len(order))), np.zeros((0, 0), np.float32)
        if h is None or not self.views or not order:
            return none
        at = {f: k for k, f in enumerate(self.pose_frames)}
        frames = [f for f in sorted(self.views) if f in at]
        dims = {self.views[f].shape[0] for f in frames}
        if len(dims) > 1:
            log.warning("keyframe views of %s dimensions; room features use none of them", sorted(dims))
            return none
        fs = h.layout.freespace
        lab, ids = h.room_layout.labels, self.hierarchy.room_ids
        empty = np.zeros((0, 2), np.float32)
        shares = [
            view_shares(lab, ids, order, fs.cell_of(self.view_points.get(f, empty)), fs.cell_of(self.poses[at[f]][None, :2])[0], fs.resolution)
            for f in frames
        ]  # fmt: skip
        if not shares:
            return none
        return np.stack(shares), np.stack([self.views[f] for f in frames])

    def _describe_rooms(
        self, segments: dict[int, SegmentNode], rooms: dict[int, RoomNode], previous: dict[int, RoomNode]
    ) -> dict[int, RoomNode]:
        shares, views = self._view_shares(sorted(rooms))
        return describe_rooms(rooms, segments, shares, views, self.room_vocabulary, self.cfg.graph.room_view_weight, previous)

    def finish(self) -> GraphDelta:
        """A last update after the final frame, so nothing fused is left out of the graph."""
        return self.update()

    def mesh_chunk(self) -> MeshChunk:
        mesh = self.mesh if self.mesh is not None else HypothesisMesh.empty(self.cfg.tsdf.hypotheses)
        seg = self.segments.vertex_segments() if len(mesh) else np.zeros(0, np.int32)
        return MeshChunk(vertices=mesh.vertices, colors=mesh.colors, faces=mesh.faces, segment_ids=seg.astype(np.int32))

    def full_mesh_chunk(self) -> MeshChunk:
        """The whole map's mesh: the active window's, and the archived blocks' with each
        vertex's segment from its winning track (a final export; it runs marching cubes over
        the archive)."""
        active = self.mesh_chunk()
        arch = self.tsdf.extract_archived_mesh()
        if len(arch) == 0:
            return active
        win = arch.winners()
        has = win >= 0
        tracks, inverse = np.unique(win[has], return_inverse=True)
        seg_of = np.array([-1 if (s := self.segments.segment_of_track(int(t))) is None else s for t in tracks], np.int32)
        seg = np.full(len(win), -1, np.int32)
        seg[has] = seg_of[inverse]
        n = len(active.vertices)
        return MeshChunk(
            vertices=np.concatenate([active.vertices, arch.vertices]),
            colors=np.concatenate([active.colors, arch.colors]),
            faces=np.concatenate([active.faces, arch.faces + n]).astype(np.int32),
            segment_ids=np.concatenate([active.segment_ids, seg]),
        )

    def snapshot(self, with_mesh: bool = False, whole_map: bool = False) -> GraphSnapshot:
        """The graph; ``with_mesh`` adds the active window's mesh, ``whole_map`` the whole
        map's instead (for saving a finished map)."""
        snap = self.graph.snapshot(with_mesh=with_mesh and not whole_map)
        update: dict[str, Any] = {
            "trajectory": np.stack(self.poses) if self.poses else np.zeros((0, 7)),
            "trajectory_frames": np.asarray(self.pose_frames, np.int64),
        }
        if whole_map:
            update["mesh"] = self.full_mesh_chunk()
        return snap.model_copy(update=update)

    def room_grid(self) -> RoomGrid | None:
        """The rooms' footprints of the last rebuild (room ids per free-space cell), or None
        before the first."""
        h = self.last_hierarchy
        if h is None:
            return None
        ids = self.hierarchy.room_ids
        lab = h.room_layout.labels
        names = {r.id: r.name for r in self.graph.rooms.values()}
        return RoomGrid(
            labels=np.where(lab >= 0, ids[np.maximum(lab, 0)] if ids.size else -1, -1).astype(np.int32),
            origin=h.layout.freespace.origin.astype(np.float64),
            resolution=float(h.layout.freespace.resolution),
            room_ids=ids.copy(),
            names=[names.get(int(i), "") for i in ids],
        )

    def _add_surface(self, vertices: Annotated[np.ndarray, "(V, 3) float32"]) -> None:
        """Keep one point per 5 cm cell of everything ever meshed: places and rooms must cover
        the whole map, not only the active window."""
        if len(vertices) == 0:
            return
        cells = np.floor(vertices / SURFACE_CELL_M).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        for k in first:
            self.surface.setdefault(tuple(cells[k]), vertices[k])

    def surface_points(self) -> Annotated[np.ndarray, "(N, 3) float32"]:
        if not self.surface:
            return np.zeros((0, 3), np.float32)
        return np.stack(list(self.surface.values())).astype(np.float32)

    # ------------------------------------------------------------------ persistence

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume mapping (the graph itself is saved as a snapshot)."""
        tracks = sorted(self.tracks)
        dino_dim = next((len(t.dino) for t in self.tracks.values() if t.dino is not None), 0)
        clip_dim = next((len(t.clip) for t in self.tracks.values() if t.clip is not None), 0)
        return {
            "tsdf": self.tsdf.state_dict(),
            "segments": _segments_tree(self.segments.state_dict()),
            "tracks": {
                "ids": np.asarray(tracks, np.int64),
                "dino": np.stack([self.tracks[t].dino if self.tracks[t].dino is not None else np.zeros(dino_dim, np.float32) for t in tracks]) if tracks else np.zeros((0, dino_dim), np.float32),
                "has_dino": np.asarray([self.tracks[t].dino is not None for t in tracks], bool),
                "clip": np.stack([self.tracks[t].clip if self.tracks[t].clip is not None else np.zeros(clip_dim, np.float32) for t in tracks]) if tracks else np.zeros((0, clip_dim), np.float32),
                "clip_count": np.asarray([self.tracks[t].clip_count for t in tracks], np.int64),
                "displaced": np.asarray([self.tracks[t].displaced_weight for t in tracks], np.float64),
                "retired": np.asarray([self.tracks[t].retired for t in tracks], bool),
            },
            "trajectory": np.stack(self.trajectory) if self.trajectory else np.zeros((0, 3)),
            "poses": np.stack(self.poses) if self.poses else np.zeros((0, 7)),
            "pose_frames": np.asarray(self.pose_frames, np.int64),
            "surface": self.surface_points(),
            "views": {
                "frames": np.asarray(sorted(self.views), np.int64),
                "features": np.stack([self.views[f] for f in sorted(self.views)]) if self.views else np.zeros((0, 0), np.float32),
                "seen_frames": np.asarray(sorted(self.view_points), np.int64),
                "seen_counts": np.asarray([len(self.view_points[f]) for f in sorted(self.view_points)], np.int64),
                "seen_xy": np.concatenate([self.view_points[f] for f in sorted(self.view_points)]) if self.view_points else np.zeros((0, 2), np.float32),
            },
            "counters": np.asarray([self.frames, self.updates, self.last_frame_index], np.int64),
        }

    def load_state_dict(self, state: dict[str, Any], snapshot: GraphSnapshot) -> None:
        """Resume from :meth:`state_dict` and the graph snapshot saved with it."""
        self.tsdf.load_state_dict(state["tsdf"])
        self.segments.load_state_dict(_segments_untree(state["segments"]))
        t = state["tracks"]
        self.tracks = {}
        for k, tid in enumerate(np.asarray(t["ids"]).tolist()):
            self.tracks[tid] = TrackState(
                track_id=tid,
                dino=np.asarray(t["dino"][k], np.float32) if t["has_dino"][k] else None,
                clip=np.asarray(t["clip"][k], np.float32) if t["clip_count"][k] > 0 else None,
                clip_count=int(t["clip_count"][k]),
                displaced_weight=float(t["displaced"][k]),
                retired=bool(t["retired"][k]),
            )
        self.trajectory = [np.asarray(p, np.float64) for p in np.asarray(state["trajectory"]).reshape(-1, 3)]
        # Maps saved before poses were kept resume with positions and no orientation.
        poses = np.asarray(state.get("poses", np.zeros((0, 7))), np.float64).reshape(-1, 7)
        frames = np.asarray(state.get("pose_frames", np.zeros(0)), np.int64).reshape(-1)
        if len(poses) != len(self.trajectory) or len(frames) != len(poses):
            poses = np.column_stack([np.stack(self.trajectory), np.tile([0.0, 0.0, 0.0, 1.0], (len(self.trajectory), 1))]) if self.trajectory else np.zeros((0, 7))
            frames = np.full(len(poses), -1, np.int64)
        self.poses, self.pose_frames = list(poses), frames.tolist()
        self.surface = {}
        self._add_surface(np.asarray(state["surface"], np.float32).reshape(-1, 3))
        # Maps saved before keyframe views were kept resume without them.
        views = state.get("views") or {}
        vf = np.asarray(views.get("frames", np.zeros(0)), np.int64).reshape(-1)
        feats = np.asarray(views.get("features", np.zeros((0, 0))), np.float32)
        self.views = {int(f): feats[k].copy() for k, f in enumerate(vf.tolist())} if len(vf) == len(feats) else {}
        sf = np.asarray(views.get("seen_frames", np.zeros(0)), np.int64).reshape(-1)
        counts = np.asarray(views.get("seen_counts", np.zeros(0)), np.int64).reshape(-1)
        xy = np.asarray(views.get("seen_xy", np.zeros((0, 2))), np.float32).reshape(-1, 2)
        self.view_points = {}
        if len(sf) == len(counts) and counts.sum() == len(xy):
            for f, part in zip(sf.tolist(), np.split(xy, np.cumsum(counts)[:-1]) if len(counts) else [], strict=True):
                self.view_points[int(f)] = part.copy()
        self.frames, self.updates, self.last_frame_index = (int(x) for x in np.asarray(state["counters"]))
        self.graph = SceneGraph.from_snapshot(snapshot)
        self.hierarchy.restore(snapshot.places, snapshot.rooms)
        self.mesh = None


def _seen_xy(fr) -> Annotated[np.ndarray, "(N, 2) float32 world xy"]:
    """World xy of every ``VIEW_SAMPLE_STRIDE``-th pixel of the frame with depth."""
    depth = fr.depth_m()[::VIEW_SAMPLE_STRIDE, ::VIEW_SAMPLE_STRIDE]
    pts = backproject(fr.intrinsics, fr.depth_m())[::VIEW_SAMPLE_STRIDE, ::VIEW_SAMPLE_STRIDE].reshape(-1, 3)
    pts = pts[(depth.reshape(-1) > 0) & np.isfinite(depth.reshape(-1))]
    T = np.asarray(fr.T_world_cam, np.float64)
    return (pts @ T[:3, :3].T + T[:3, 3])[:, :2].astype(np.float32)


def _segments_tree(state: dict[str, Any]) -> dict[str, Any]:
    """The segment layer's list of segments as a dict keyed by position: the map store keeps
    nested dicts of arrays, not lists."""
    out = dict(state)
    out["segments"] = {f"{i:06d}": seg for i, seg in enumerate(state["segments"])}
    return out


def _segments_untree(state: dict[str, Any]) -> dict[str, Any]:
    out = dict(state)
    segs = state["segments"]
    out["segments"] = [segs[k] for k in sorted(segs)] if isinstance(segs, dict) else list(segs)
    out["format"] = state["format"].item() if isinstance(state["format"], np.ndarray) else state["format"]
    return out
