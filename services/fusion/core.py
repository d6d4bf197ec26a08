"""The fusion core: tracked frames in, scene-graph deltas out. No Zenoh here.

Per frame it fuses depth, colour and source-track masks into the hypothesis TSDF (III-C,
eqs. 5-6) and moves the active window (III-A). Every ``mesh_every_n_frames`` frames it runs
marching cubes, the segment updater and re-identification (III-D, III-E), rebuilds places
and rooms, and returns the resulting :class:`GraphDelta`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Annotated, Any

import numpy as np

from services.fusion.corrections.observations import ObservationLog
from services.fusion.corrections.poses import CorrectionError, PoseBook
from services.fusion.layers.roomnames import (
    VIEW_SAMPLE_STRIDE,
    RoomLookup,
    RoomVocabulary,
    describe_rooms,
    view_shares,
)
from services.fusion.layers.rooms import Hierarchy, HierarchyBuilder
from services.fusion.layers.segments import SegmentLayer
from services.fusion.layers.surface import SurfaceSample
from services.fusion.types import HypothesisMesh, TrackState
from services.fusion.volume.cubes import BlockCopy
from services.fusion.volume.cubes import warm_up as warm_cubes
from services.fusion.volume.hypotheses import confidence
from services.fusion.volume.incremental import BlockUpdate
from services.fusion.volume.incremental import warm_up as warm_incremental
from services.fusion.volume.move import warm_up
from services.fusion.volume.tsdf import HypothesisTSDF
from shared.config.fusion import FusionConfig
from shared.geometry import Intrinsics, pixel_stride, pose_from_row, pose_row
from shared.graph.roomgrid import RoomGrid
from shared.graph.scene import SceneGraph
from shared.messages.frames import Frame, TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, MeshChunk, RoomNode, SegmentNode
from shared.messages.keyframes import TrackFeatures
from shared.messages.poses import PoseCorrection

log = logging.getLogger(__name__)

@dataclass
class CorrectionCounters:
    """Pose corrections the core took (the fusion service's ``corrections`` status figure)."""

    applied: int = 0
    unchanged: int = 0
    """Corrections that moved nothing: the newest sent again, or the same poses once more."""
    refused: int = 0
    last_id: int = -1
    seconds_move: float = 0.0
    """Time the newest correction took to move the map (TSDF, segments, surface, views)."""
    seconds_update: float = 0.0
    """Time of the graph update after it (mesh, segments and re-identification, places, rooms)."""
    refused_frames: int = 0
    """Frames the last re-fusion (``fusion.refuse``) fused again at their corrected poses."""
    seconds_refuse: float = 0.0
    """Time of that re-fusion, graph update included."""

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class UpdateInput:
    """What a graph update reads from the frame path, captured at one frame
    (:meth:`FusionCore.capture_update`): the map path works on this, never on the live state."""

    mesh: HypothesisMesh | None
    """The active window's hypothesis mesh, or None when ``blocks`` holds what to mesh."""
    blocks: BlockCopy | BlockUpdate | None
    """The active window's blocks, copied: the map path meshes them (numba marching cubes,
    :mod:`services.fusion.volume.cubes`), or with ``fusion.incremental_mesh`` those whose
    part of the mesh changed (:mod:`services.fusion.volume.incremental`); None on CUDA,
    where the frame path meshes."""
    center: Annotated[np.ndarray, "(3,) float64 m"]
    """The newest position: the active window's centre."""
    tracks: dict[int, TrackState]
    """Copies of the track states (the frame path goes on changing the originals)."""
    trajectory: Annotated[np.ndarray, "(N, 3) float64 m"]
    poses: list[np.ndarray]
    """(7,) pose row of each fused frame."""
    pose_frames: list[int]
    views: dict[int, np.ndarray]
    """Keyframe index -> whole-image embedding."""
    view_points: dict[int, np.ndarray]
    """Keyframe index -> (N, 3) world points it shows."""
    frame_index: int
    """The newest fused frame: the frame the delta reflects."""


@dataclass
class RefuseStats:
    """What :meth:`FusionCore.refuse` did."""

    frames: int
    seconds_fuse: float
    seconds_update: float
    kept_mb: float
    """Size of the kept observations (compressed)."""
    delta: GraphDelta | None


@dataclass
class CorrectionOutcome:
    """What :meth:`FusionCore.apply_correction` did."""

    correction_id: int
    status: str
    """``applied`` or ``unchanged`` (a refused correction raises)."""
    delta: GraphDelta | None
    """The graph update after the move (None when nothing moved)."""
    frames_moved: int
    max_shift_m: float
    seconds_move: float
    seconds_update: float


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
        """Keyframe index -> (N, 3) float32 world points of a sparse sample of its depth: what
        the view shows, to give it to a room (by xy)."""
        self.room_vocabulary: RoomVocabulary | None = None
        """The room labels' text embeddings; set by the session once ``vl/embed`` answers."""
        self.surface = SurfaceSample(cfg.graph.surface_cell_m)
        self.book = PoseBook()
        """Raw and corrected pose of every fused frame (:mod:`services.fusion.corrections.poses`)."""
        self.tsdf.epoch_motion = self.book.epoch_motion
        warm_up()  # the voxel-moving kernels, so a first correction is not slower than the next
        warm_cubes()  # and marching cubes, so the first graph update is not
        if cfg.incremental_mesh:
            warm_incremental()
        self._moved: set[int] = set()
        """Segments a correction moved, reported changed by the next update."""
        self.corrections = CorrectionCounters()
        self.observations: ObservationLog | None = None
        """Every fused frame, kept to re-fuse the map at its corrected poses (:meth:`refuse`);
        None: not kept (``fusion.refuse`` off). The session gives it a file when it has a store."""
        self._refused_epoch = 0
        self.frames = 0
        self.updates = 0
        self.last_frame_index = -1
        self.mesh: HypothesisMesh | None = None
        self.sync_updates = True
        """True: :meth:`add_frame` updates the graph every ``mesh_every_n_frames`` frames and
        returns the delta. False (``fusion.map_path: async``): it never does; the map path
        (:class:`services.fusion.mappath.MapPath`) decides when."""

    # ------------------------------------------------------------------ inputs

    def _votes(self, tf: TrackedFrame) -> tuple[Annotated[np.ndarray, "(H, W) int32"], dict[int, float]]:
        """The track label each pixel votes for, and each track's gamma (eq. 6)."""
        tsdf = self.cfg.tsdf
        gamma = {o.track_id: confidence(o.keyframe, o.frames_since_keyframe, tsdf.alpha_p, tsdf.beta_p) for o in tf.tracks}
        ids = tf.track_ids
        # Not in the paper (docs/method.md, F3): a propagated pixel votes only where eq. 1 was
        # confident of its track; ``min_label_confidence: 0`` fuses every pixel as the paper does.
        if tf.confidence is not None and tsdf.min_label_confidence > 0:
            ids = np.where(tf.confidence >= round(255 * tsdf.min_label_confidence), ids, -1)
        return ids, gamma

    def _fused_pixels(
        self, fr: Frame, ids: Annotated[np.ndarray, "(H, W) int32"]
    ) -> tuple[Annotated[np.ndarray, "(h, w) float32 m"], Annotated[np.ndarray, "(h, w, 3) uint8"], Intrinsics, Annotated[np.ndarray, "(h, w) int32"]]:
        """Depth, colour, intrinsics and vote labels as they are fused: every
        ``fusion.tsdf.pixel_stride``-th pixel of every such row."""
        step = pixel_stride(self.cfg.tsdf.pixel_stride, fr.intrinsics.width)
        if step == 1:
            return fr.depth_m(), fr.rgb, fr.intrinsics, ids
        depth = fr.depth[::step, ::step].astype(np.float32) / np.float32(fr.depth_scale)
        return depth, np.ascontiguousarray(fr.rgb[::step, ::step]), fr.intrinsics.strided(step), np.ascontiguousarray(ids[::step, ::step])

    def add_frame(self, tf: TrackedFrame) -> GraphDelta | None:
        """Fuse one tracked frame; every N frames also update the graph and return its delta."""
        fr = tf.frame
        ids, gamma = self._votes(tf)
        # the pose the frame came with, as the newest pose correction places it
        T = self.book.add(int(fr.frame_index), fr.T_world_cam)
        depth, rgb, K, fused_ids = self._fused_pixels(fr, ids)
        stats = self.tsdf.integrate(depth, rgb, K, T, fused_ids, gamma, frame_index=int(fr.frame_index))
        if self.observations is not None:
            self.observations.append(tf)
        for tid, w in stats.displaced.items():
            self._track(tid).displaced_weight += float(w)
        for o in tf.tracks:
            self._track(o.track_id)
        if tf.keyframe:
            self.view_points[int(fr.frame_index)] = _seen_points(fr, T)
        position = T[:3, 3].copy()
        self.tsdf.update_window(position)
        self.trajectory.append(position)
        self.poses.append(pose_row(T))
        self.pose_frames.append(int(fr.frame_index))
        self.frames += 1
        self.last_frame_index = fr.frame_index
        if self.sync_updates and self.frames % self.cfg.mesh_every_n_frames == 0:
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
        return self.build_update(self.capture_update())

    def capture_update(self) -> UpdateInput:
        """The frame path's half of an update: a copy of the active window's blocks (on CUDA
        their mesh) and copies of what the rest reads from the frame path (tracks, trajectory,
        keyframe views), all as of the newest fused frame. :meth:`build_update` may then run
        beside later frames (``fusion.map_path: async``, :mod:`services.fusion.mappath`)."""
        blocks = self.tsdf.copy_changed() if self.cfg.incremental_mesh else self.tsdf.copy_active()
        return UpdateInput(
            mesh=self.tsdf.extract_mesh() if blocks is None else None, blocks=blocks,
            center=self.trajectory[-1].copy() if self.trajectory else np.zeros(3),
            tracks={tid: replace(st) for tid, st in self.tracks.items()},
            trajectory=np.stack(self.trajectory) if self.trajectory else np.zeros((0, 3)),
            poses=list(self.poses), pose_frames=list(self.pose_frames),
            views=dict(self.views), view_points=dict(self.view_points),
            frame_index=self.last_frame_index,
        )  # fmt: skip

    def build_update(self, inp: UpdateInput) -> GraphDelta:
        """The map path's half: the mesh of ``inp.blocks``, segments and re-identification on
        it, the surface sample, places and rooms, the delta (which reflects frame
        ``inp.frame_index``). It touches only map-path state (segments, surface, hierarchy,
        graph), never the TSDF."""
        if inp.mesh is not None:
            mesh = inp.mesh
        elif isinstance(inp.blocks, BlockUpdate):
            mesh = self.tsdf.mesh_of_update(inp.blocks)
        else:
            mesh = self.tsdf.mesh_of(inp.blocks)
        self.mesh = mesh
        window = (inp.center, self.cfg.tsdf.active_window_m)
        changes = self.segments.update(mesh, inp.tracks, window=window)
        self.surface.add(mesh.vertices, mesh.vertex_anchors())
        places = rooms = None
        points = self.surface_points()
        if len(points) and len(inp.trajectory):
            try:
                h = self.hierarchy.build(points, inp.trajectory, active=window)
                places, rooms = h.places, h.rooms
                self.last_hierarchy = h
            except ValueError as exc:
                # Too little of the floor is mapped yet to find free space; keep the last layers.
                log.debug("places and rooms not rebuilt: %s", exc)
        moved = {s for s in self._moved if s in self.segments.segments}
        self._moved = set()
        ids = sorted(set(changes.added) | set(changes.changed) | moved)
        self.updates += 1
        with_mesh = self.updates % self.cfg.mesh_delta_every_n_updates == 0
        return self.graph.apply_update(
            segments_changed=self.segments.nodes(ids),
            segments_removed=changes.removed,
            places=places,
            rooms=rooms,
            mesh=self.mesh_chunk() if with_mesh else None,
            frame_index=inp.frame_index,
            describe_rooms=lambda segments, new, previous: self._describe_rooms(segments, new, previous, inp),
        )

    def _view_shares(self, order: list[int], inp: UpdateInput) -> tuple[Annotated[np.ndarray, "(K, R) float64"], Annotated[np.ndarray, "(K, D) float32"]]:
        """What share of each keyframe view (as of ``inp``) falls in each room of ``order``, and the views."""
        h = self.last_hierarchy
        none = np.zeros((0, len(order))), np.zeros((0, 0), np.float32)
        if h is None or not inp.views or not order:
            return none
        at = {f: k for k, f in enumerate(inp.pose_frames)}
        frames = [f for f in sorted(inp.views) if f in at]
        dims = {inp.views[f].shape[0] for f in frames}
        if len(dims) > 1:
            log.warning("keyframe views of %s dimensions; room features use none of them", sorted(dims))
            return none
        fs = h.layout.freespace
        lab, ids = h.room_layout.labels, self.hierarchy.room_ids
        lookup = RoomLookup(lab, ids, fs.resolution)  # one distance transform for every view
        empty = np.zeros((0, 2), np.float32)
        shares = [
            view_shares(lab, ids, order, fs.cell_of(inp.view_points.get(f, empty)), fs.cell_of(inp.poses[at[f]][None, :2])[0], fs.resolution, lookup)
            for f in frames
        ]  # fmt: skip
        if not shares:
            return none
        return np.stack(shares), np.stack([inp.views[f] for f in frames])

    def _describe_rooms(
        self, segments: dict[int, SegmentNode], rooms: dict[int, RoomNode], previous: dict[int, RoomNode], inp: UpdateInput
    ) -> dict[int, RoomNode]:
        shares, views = self._view_shares(sorted(rooms), inp)
        return describe_rooms(rooms, segments, shares, views, self.room_vocabulary, self.cfg.graph.room_view_weight, previous)

    def finish(self) -> GraphDelta:
        """A last update after the final frame, so nothing fused is left out of the graph;
        after pose corrections, with the kept frames re-fused first (:meth:`refuse`)."""
        refused = self.refuse()
        if refused is not None and refused.delta is not None:
            return refused.delta
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

    # ------------------------------------------------------------------ pose corrections

    def apply_correction(self, c: PoseCorrection) -> CorrectionOutcome:
        """Move the map to where correction ``c`` puts the frames it was fused from.

        The estimates of every fused frame are recomputed from the raw poses and ``c`` alone
        (:class:`~services.fusion.corrections.poses.PoseBook`); each piece of the map moves rigidly with
        the frame it was last fused from: TSDF voxels (``HypothesisTSDF.move``), segment
        positions, the whole-map surface sample, keyframe views, the trajectory. Then one
        graph update rebuilds the mesh, segments (re-identification on the corrected
        geometry), places and rooms, and its delta reports every segment that moved, under
        its own id. Raises :class:`~services.fusion.corrections.poses.CorrectionError`, with nothing
        changed, for a correction that is older than the newest applied, names frames the map
        has not fused, or none it has. The same correction again moves nothing."""
        t0 = time.perf_counter()
        try:
            motion = self.book.correct(c)
        except CorrectionError:
            self.corrections.refused += 1
            raise
        if len(motion) == 0:
            self.corrections.unchanged += 1
            return CorrectionOutcome(c.correction_id, "unchanged", None, 0, 0.0, 0.0, 0.0)
        tsdf = self.tsdf.move(motion, self.book.epoch)
        self._moved |= set(self.segments.move(motion))
        self.surface.move(motion)
        if self.view_points:
            frames = sorted(self.view_points)
            sizes = [len(self.view_points[f]) for f in frames]
            pts, _ = motion.apply(np.concatenate([self.view_points[f] for f in frames]), np.repeat(frames, sizes))
            self.view_points = dict(zip(frames, np.split(pts, np.cumsum(sizes)[:-1]), strict=True))
        est = self.book.est
        self.trajectory = [T[:3, 3].copy() for T in est]
        self.poses = [pose_row(T) for T in est]
        t_move = time.perf_counter() - t0
        moved = len(self._moved)
        t1 = time.perf_counter()
        delta = self.update() if self.frames else None
        t_update = time.perf_counter() - t1
        self.corrections.applied += 1
        self.corrections.last_id = c.correction_id
        self.corrections.seconds_move = round(t_move, 4)
        self.corrections.seconds_update = round(t_update, 4)
        log.info(
            "correction %d (frames up to %d): %d frames moved, up to %.3f m; %d segments, %d voxels moved (%d gaps filled); "
            "%.3f s to move, %.3f s to update the graph",
            c.correction_id, c.frame_index, len(motion), motion.max_shift_m, moved, tsdf.voxels_moved, tsdf.gaps_filled, t_move, t_update,
        )  # fmt: skip
        return CorrectionOutcome(c.correction_id, "applied", delta, len(motion), motion.max_shift_m, t_move, t_update)

    def refuse(self) -> RefuseStats | None:
        """Re-fuse every kept frame at its current estimate into a fresh TSDF (the active
        window moving along the corrected trajectory as it did), then rebuild every segment's
        geometry and the surface sample from the whole re-fused map, and update the graph.
        Segment ids stay: the tracks, and so the segments they belong to, are unchanged.

        Undoes what moving the map cannot: the blur of surfaces fused from frames that had
        drifted apart before a correction came. None (nothing done) when no correction was
        applied since the last re-fusion, or when the log lacks frames the map fused."""
        if self.observations is None or self.book.epoch == self._refused_epoch or not self.frames:
            return None
        if not self.observations.covers(self.book.frames):
            log.warning("re-fusion skipped: the kept observations hold %d frames, the map fused %d (a resume from "
                        "before they were kept?); the map stays as the corrections moved it",
                        len(self.observations), len(self.book.frames))  # fmt: skip
            return None
        t0 = time.perf_counter()
        old = self.tsdf
        same_vote = self.cfg.tsdf.model_copy(update={"vote_backend": old.backend})
        fresh = HypothesisTSDF(same_vote, device=old.device_name.lower(), mesh_weight_threshold=old.mesh_weight_threshold)
        fresh.epoch, fresh.epoch_motion = self.book.epoch, self.book.epoch_motion
        for tf in self.observations:
            fr = tf.frame
            ids, gamma = self._votes(tf)
            T = self.book.estimate(int(fr.frame_index))
            depth, rgb, K, fused_ids = self._fused_pixels(fr, ids)
            fresh.integrate(depth, rgb, K, T, fused_ids, gamma, frame_index=int(fr.frame_index))
            fresh.update_window(T[:3, 3])
        self.tsdf = fresh
        t_fuse = time.perf_counter() - t0
        t1 = time.perf_counter()
        whole = _concat_meshes(fresh.extract_mesh(), fresh.extract_archived_mesh())
        self._moved |= set(self.segments.replace_geometry(whole))
        self.surface.clear()
        self.surface.add(whole.vertices, whole.vertex_anchors())
        delta = self.update()
        self._refused_epoch = self.book.epoch
        stats = RefuseStats(frames=len(self.observations), seconds_fuse=round(t_fuse, 3), seconds_update=round(time.perf_counter() - t1, 3),
                            kept_mb=round(self.observations.nbytes / 2**20, 1), delta=delta)  # fmt: skip
        self.corrections.refused_frames = stats.frames
        self.corrections.seconds_refuse = round(t_fuse + stats.seconds_update, 3)
        log.info("re-fused %d frames at their corrected poses: %.2f s to fuse, %.2f s to rebuild segments and graph; "
                 "observations kept: %.1f MB", stats.frames, t_fuse, stats.seconds_update, stats.kept_mb)  # fmt: skip
        return stats

    def surface_points(self) -> Annotated[np.ndarray, "(N, 3) float32"]:
        """One point per ``fusion.graph.surface_cell_m`` cell of everything ever meshed:
        places and rooms must cover the whole map, not only the active window."""
        return self.surface.points

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
            "surface_anchors": self.surface.anchors.copy(),
            "pose_book": self.book.state_dict(),
            "views": {
                "frames": np.asarray(sorted(self.views), np.int64),
                "features": np.stack([self.views[f] for f in sorted(self.views)]) if self.views else np.zeros((0, 0), np.float32),
                "seen_frames": np.asarray(sorted(self.view_points), np.int64),
                "seen_counts": np.asarray([len(self.view_points[f]) for f in sorted(self.view_points)], np.int64),
                "seen_xyz": np.concatenate([self.view_points[f] for f in sorted(self.view_points)]) if self.view_points else np.zeros((0, 3), np.float32),
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
        if "pose_book" in state:
            self.book = PoseBook()
            self.book.load_state_dict(state["pose_book"])
        else:
            # saved before pose corrections: the poses fused with are the raw ones
            valid = len(frames) and frames.min() >= 0 and np.all(np.diff(frames) > 0)
            index = frames if valid else np.arange(len(poses)) - len(poses)
            self.book = PoseBook.from_raw(index.tolist(), [pose_from_row(p) for p in poses])
        self.tsdf.epoch_motion = self.book.epoch_motion
        self._moved = set()
        self.surface.clear()
        surface = np.asarray(state["surface"], np.float32).reshape(-1, 3)
        anchors = np.asarray(state.get("surface_anchors", np.full(len(surface), -1)), np.int32).reshape(-1)
        self.surface.add(surface, anchors if len(anchors) == len(surface) else np.full(len(surface), -1, np.int32))
        # Maps saved before keyframe views were kept resume without them.
        views = state.get("views") or {}
        vf = np.asarray(views.get("frames", np.zeros(0)), np.int64).reshape(-1)
        feats = np.asarray(views.get("features", np.zeros((0, 0))), np.float32)
        self.views = {int(f): feats[k].copy() for k, f in enumerate(vf.tolist())} if len(vf) == len(feats) else {}
        sf = np.asarray(views.get("seen_frames", np.zeros(0)), np.int64).reshape(-1)
        counts = np.asarray(views.get("seen_counts", np.zeros(0)), np.int64).reshape(-1)
        if "seen_xyz" in views:
            xy = np.asarray(views["seen_xyz"], np.float32).reshape(-1, 3)
        else:  # saved before corrections kept the height
            xy = np.asarray(views.get("seen_xy", np.zeros((0, 2))), np.float32).reshape(-1, 2)
            xy = np.column_stack([xy, np.zeros(len(xy), np.float32)])
        self.view_points = {}
        if len(sf) == len(counts) and counts.sum() == len(xy):
            for f, part in zip(sf.tolist(), np.split(xy, np.cumsum(counts)[:-1]) if len(counts) else [], strict=True):
                self.view_points[int(f)] = part.copy()
        self.frames, self.updates, self.last_frame_index = (int(x) for x in np.asarray(state["counters"]))
        self.graph = SceneGraph.from_snapshot(snapshot)
        self.hierarchy.restore(snapshot.places, snapshot.rooms)
        self.mesh = None


def _concat_meshes(a: HypothesisMesh, b: HypothesisMesh) -> HypothesisMesh:
    """One mesh of two (vertex indices of ``b``'s faces shifted)."""
    if len(b) == 0:
        return a
    if len(a) == 0:
        return b
    return HypothesisMesh(
        np.concatenate([a.vertices, b.vertices]), np.concatenate([a.colors, b.colors]),
        np.concatenate([a.faces, b.faces + len(a)]).astype(np.int32),
        np.concatenate([a.hyp_ids, b.hyp_ids]), np.concatenate([a.hyp_weights, b.hyp_weights]),
        np.concatenate([a.vertex_anchors(), b.vertex_anchors()]),
    )  # fmt: skip


def _seen_points(fr, T: Annotated[np.ndarray, "(4, 4) world-from-camera"]) -> Annotated[np.ndarray, "(N, 3) float32 world"]:
    """World points of every ``VIEW_SAMPLE_STRIDE``-th pixel of the frame with depth."""
    s, K = VIEW_SAMPLE_STRIDE, fr.intrinsics
    depth = fr.depth_m()[::s, ::s]
    # backproject's formula on the sampled pixels only (a 1200x680 frame has 3,000 of 816,000)
    u = np.arange(0, K.width, s, dtype=np.float64)
    v = np.arange(0, K.height, s, dtype=np.float64)
    pts = np.stack([(u[None, :] - K.cx) / K.fx * depth, (v[:, None] - K.cy) / K.fy * depth, depth.astype(np.float64)], axis=-1).reshape(-1, 3)
    pts = pts[(depth.reshape(-1) > 0) & np.isfinite(depth.reshape(-1))]
    T = np.asarray(T, np.float64)
    return (pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


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
