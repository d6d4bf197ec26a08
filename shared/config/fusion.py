"""TSDF with track hypotheses, 3D segments, re-identification and the scene graph
(paper sections III-A, III-C, III-D, III-E)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from shared.config.base import StrictModel


class TSDFConfig(StrictModel):
    """Volumetric fusion and the per-voxel source-track hypotheses (III-C)."""

    voxel_size: float = Field(0.03, gt=0, le=1.0)
    """Voxel edge in metres (IV-A: 0.03; 0.05 lighter; 0.125 onboard)."""
    trunc_voxels: float = Field(4.0, gt=0)
    """TSDF truncation distance in voxels."""
    depth_min: float = Field(0.1, ge=0)
    """Depth readings nearer than this (m) are ignored."""
    depth_max: float = Field(5.0, gt=0)
    """Depth readings farther than this (m) are ignored."""
    block_resolution: int = Field(8, ge=4, le=32)
    """Voxels per block edge in the voxel block grid."""
    initial_blocks: int = Field(4000, ge=16)
    """Blocks preallocated; the grid grows by doubling."""
    hypotheses: int = Field(4, ge=1, le=16)
    """K, track hypotheses kept per voxel (III-C)."""
    alpha_p: float = Field(0.25, gt=0, le=1)
    """alpha_p, confidence of propagated masks (eq. 6)."""
    beta_p: float = Field(0.1, ge=0)
    """beta_p, decay of that confidence per frame since the last keyframe (eq. 6)."""
    min_label_confidence: float = Field(0.8, ge=0, le=1)
    """Not in the paper: a propagated pixel votes (eq. 5) only if eq. 1 gave its track at
    least this probability (``TrackedFrame.confidence``). Where propagation hesitates, at
    track borders and on small objects it is losing, its argmax mostly names the neighbour,
    and those votes outweigh the keyframe's over a keyframe interval: on the ``small`` preset
    with noise-free masks and classical features the class-agnostic AP50 went from 0.49 to
    0.75 with 0.8. 0 fuses every propagated pixel, as the paper does (docs/method.md, F3)."""
    mesh_min_weight: float = Field(1.0, ge=0)
    """Marching cubes uses voxels whose TSDF weight exceeds this: 1 keeps surfaces seen in at
    least two frames, which drops single-frame depth noise."""
    pixel_stride: Annotated[int, Field(ge=1, le=8)] | Literal["auto"] = 1
    """Not in the paper: fuse (integrate, and vote per eq. 5) every Nth pixel of every Nth row,
    with the intrinsics to match. At 3 cm a voxel 2 m away spans about 12 pixels of a 1200
    pixel wide image (fx 782), and the vote is a share of each voxel's pixels (eq. 5 as
    ``services/fusion/volume/hypotheses.py`` applies it), so the map hardly changes while the
    per-pixel work drops by N squared. ``auto``: about 640 pixels across, ``max(1,
    round(width / 640))`` (1 up to 800 pixels wide, 2 at Replica's 1200x680)."""
    active_window_m: float = Field(8.0, gt=0)
    """Radius of the active window around the pose (III-A); blocks outside are archived."""
    restore_archived: bool = False
    """False (the paper, as Hydra): a revisit reconstructs the surface afresh with new
    hypotheses, and long-term re-identification (III-E) merges the segments; a block archived
    again replaces its older archived copy. True brings archived blocks back into the active
    TSDF instead, hypotheses included."""
    vote_backend: Literal["auto", "numba", "torch"] = "auto"
    """Not in the paper: what runs the eq. 5 hypothesis vote (``services/fusion/volume/hypotheses.py``;
    the two give the same weights bit for bit). ``numba``: a kernel over Open3D's zero-copy
    views, CPU only: 8-9 ms of vote per frame (analytic room of ``benchmarks/fusion.py``,
    640x480, 3 cm voxels, this 2-core CPU at load 3-5), plus about 1.2 s of JIT compilation
    on the first frame of a fresh install (cached on disk after). ``torch``: vectorised torch
    on the grid's device, CUDA through DLPack (about 1.2 ms of GPU work per frame on an H100,
    benchmarks/RESULTS.md); on the same CPU 69 ms a frame on one torch thread and about
    1.1 s on two, where torch's thread pool and Open3D's spin against each other. ``auto``:
    numba on a CPU when it is installed, torch otherwise (numba comes with the ``fusion`` extra)."""

    @model_validator(mode="after")
    def _depth_range(self) -> TSDFConfig:
        if self.depth_min >= self.depth_max:
            raise ValueError(f"depth_min ({self.depth_min}) must be below depth_max ({self.depth_max})")
        return self


class SegmentsConfig(StrictModel):
    """3D segment updater (III-D, eq. 7)."""

    min_vertices: int = Field(20, ge=1)
    """A track needs this many winning vertices to get a segment (IV-A)."""
    min_shared: int = Field(5, ge=1)
    """|V_q ∩ V_i| at least this for a candidate (eq. 7)."""
    theta_rho: float = Field(0.75, ge=0, le=1)
    """Either overlap ratio rho must reach this (eq. 7)."""
    theta_sim: float = Field(0.80, ge=-1, le=1)
    """DINOv3 cosine between track and segment must reach this (III-D)."""
    containment: Literal["evidence", "presence"] = "evidence"
    """How rho_{q->i} of eq. 7 (the track lying inside the segment) counts the shared
    vertices. ``presence`` is the paper's: a vertex of V_q counts when it holds any hypothesis
    of the segment, however weak. ``evidence`` (not in the paper) weighs each vertex by the
    hypothesis weights l (eq. 5), rho_{q->i} = sum_{V_q} min(l_q, l_i) / sum_{V_q} l_q: the share
    of the track's evidence that the segment's evidence matches. Where the segment holds at
    least the track's weight, as over a surface it was fused on before the track appeared,
    it is ``presence``'s ratio with each vertex weighed by l_q; it falls where the new track
    outweighs stray hypotheses the segment left there (a mask that once fused a rug with the floor). On
    ``demo`` seed 0 (synthetic.yaml) the rug's track joined the floor's segment at rho 0.80
    by presence (0.37 by evidence) and "rug" answered the floor (IoU 0.10, now 0.59); the
    same-object joins kept rho >= 0.92. Class-agnostic AP50 on ``demo`` seeds 0 / 1 / 2:
    0.574 / 0.531 / 0.737 by presence, 0.596 / 0.540 / 0.824 by evidence; on ``small``:
    0.725 / 0.732 / 0.680, 0.720 / 0.774 / 0.680. rho_{i->q} (the segment inside a fuller new
    track) counts by presence in both modes: there the young track's weight is naturally the
    lower one (docs/method.md, F6)."""


class ReidConfig(StrictModel):
    """Long-term re-identification against historical segments (III-E, eqs. 8-9)."""

    enabled: bool = True
    """Off gives the ablation without re-identification."""
    r_nn: float = Field(0.10, gt=0)
    """r_nn, vertex neighbour radius of the overlap o_qh (eq. 8), metres."""
    lambda_o: float = Field(0.5, ge=0, le=1)
    """lambda_o, weight of geometric overlap in J_qh (eq. 9)."""
    lambda_a: float = Field(0.5, ge=0, le=1)
    """lambda_a, weight of DINOv3 cosine in J_qh (eq. 9); lambda_o + lambda_a = 1."""
    o_min: float = Field(0.42, ge=0, le=1)
    """Gate on o_qh (eq. 8)."""
    cos_min: float = Field(0.70, ge=-1, le=1)
    """Gate on the DINOv3 cosine (eq. 9)."""
    j_min: float = Field(0.65, ge=0, le=1)
    """Gate on J_qh (eq. 9)."""
    search_radius_m: float = Field(2.0, gt=0)
    """k-d tree centroid radius giving the candidate set H_q."""

    @model_validator(mode="after")
    def _weights_sum(self) -> ReidConfig:
        if abs(self.lambda_o + self.lambda_a - 1.0) > 1e-6:
            raise ValueError(
                f"lambda_o + lambda_a must be 1 (eq. 9), got {self.lambda_o + self.lambda_a}"
            )
        return self


class GraphConfig(StrictModel):
    """Places and rooms above the segment layer (Hydra-style)."""

    place_spacing_m: float = Field(0.5, gt=0)
    """Spacing of sparse free-space place nodes."""
    room_erosion_m: float = Field(0.5, ge=0)
    """Erosion of free space that separates rooms at doorways: it disconnects openings up
    to about twice this wide (1 m doors at 0.5)."""
    min_room_area_m2: float = Field(2.0, ge=0)
    """Free-space components smaller than this are not rooms."""
    room_labels: list[str] = Field(
        default_factory=lambda: [
            "living room", "bedroom", "kitchen", "bathroom", "dining room", "office", "hall", "corridor",
            "laundry room", "garage",
        ]
    )  # fmt: skip
    """The room vocabulary (not in the paper): a room's name is the label whose text embedding
    (keyframe_vl's ``vl/embed``, the map's VL encoder) is nearest its feature. Empty: rooms
    keep features but get no names."""
    room_view_weight: float = Field(0.5, ge=0, le=1)
    """How a room's feature pools its two sources (not in the paper): this weight on the mean
    of the keyframe views taken from inside it, the rest on the mean CLIP feature of its
    segments. Either alone where the other is missing."""
    surface_cell_m: float = Field(0.05, gt=0)
    """Not in the paper: places and rooms are built from a sample of everything ever meshed
    (active window and archive), one point kept per cube of this edge. 0.05 m is half the
    free-space grid's 0.1 m cell (``FreeSpaceParams.resolution_m``,
    ``services/fusion/layers/places.py``), so a surface that crosses a grid cell leaves points in
    it, and is the 0.05 m the paper downsamples output point clouds to for evaluation. The
    sample, kept whole in memory and in snapshots, grows about four-fold per halving
    (surfaces are 2D)."""


class JournalConfig(StrictModel):
    """Fusion's write-ahead journal (not in the paper; docs/architecture.md, "Durability"):
    every tracked frame and track-feature message the fusion service accepts is appended
    beside its snapshots before it is acknowledged, and replayed after the newest good
    snapshot on ``--resume``, so a SIGKILL loses nothing the tracker was told is safe."""

    enabled: bool = True
    """Keep the journal (the fusion service only: ``trackgraph map`` writes no snapshots
    while it runs and has nothing to replay)."""
    fsync_interval_s: float = Field(1.0, ge=0)
    """Every record reaches the operating system before its ack, which a killed process
    cannot lose; it is forced to the disk (fsync) at most this long after, against a power
    cut. 0: fsync every record (a few ms each on an SD card or eMMC)."""
    max_bytes: int = Field(1 << 30, gt=0)
    """Bound on the journal since the last snapshot: when it passes this, fusion takes a
    snapshot at once, which cuts the journal."""
    zstd_level: int = Field(1, ge=1, le=19)
    """zstd level of each record. 1: the frames' depth and labels are already delta- or
    run-coded, and higher levels cost several times the time for a few percent."""


class FusionConfig(StrictModel):
    """The fusion service and ``trackgraph map``."""

    tsdf: TSDFConfig = Field(default_factory=TSDFConfig)
    """Volumetric fusion."""
    segments: SegmentsConfig = Field(default_factory=SegmentsConfig)
    """Segment updater."""
    reid: ReidConfig = Field(default_factory=ReidConfig)
    """Long-term re-identification."""
    graph: GraphConfig = Field(default_factory=GraphConfig)
    """Places and rooms."""
    mesh_every_n_frames: int = Field(10, ge=1)
    """Marching cubes and the segment update run every N fused frames."""
    incremental_mesh: bool = True
    """Not in the paper: at a graph update, march only the blocks written since the last one
    (and the blocks below them, whose cubes read them) and keep the rest of the mesh
    (:mod:`services.fusion.volume.incremental`): the same mesh as marching every active
    block. At 1200x680 on a walk 40-50% of the window is redone per update: the frame path
    copies half the blocks, the map path meshes in about 0.8 of the time. CPU with numba
    only; on CUDA Open3D meshes the whole grid."""
    map_path: Literal["auto", "sync", "async"] = "auto"
    """Not in the paper: where graph updates run (docs/architecture.md, "Frame path and map
    path"). ``sync``: on the frame path, every ``mesh_every_n_frames`` frames, so updates
    happen at fixed frames and a replay's map equals the in-process one. ``async``: beside
    the frame path (:mod:`services.fusion.mappath`): the frame path only captures the mesh
    and a copy of what the update reads, and a map thread builds segments,
    re-identification, places, rooms and the delta while later frames are fused; an update
    starts when the last one is done and ``mesh_every_n_frames`` frames came since, so under
    load updates come less often instead of holding frames back. ``auto``: ``async`` when
    ``source.mode`` is ``live`` (a camera), ``sync`` otherwise, so ``trackgraph map`` and a
    lossless replay run ``sync``; ``deploy/ros2.yaml`` sets ``async`` for a robot's topics."""
    mesh_delta_every_n_updates: int = Field(5, ge=1)
    """Mesh chunks ride in every Nth graph delta; segments ride in every one."""
    snapshot_interval_s: float = Field(30.0, gt=0)
    """Seconds between on-disk snapshots of the graph."""
    refuse: Literal["auto", "on", "off"] = "auto"
    """Not in the paper (docs/architecture.md, "Pose corrections"): keep every fused frame
    (compressed, beside the snapshots when there is a map store) and, when the sequence ends
    after pose corrections, fuse them again at their corrected poses, which undoes the blur
    of surfaces fused from frames that had drifted apart (moving the map cannot). ``auto``:
    on when corrections are configured (``source.corrections``, ``trackgraph map
    --corrections``, ``ros2.input.corrections``); ``on`` for a back end that publishes
    corrections itself. It costs the kept frames (0.5 MB each at 640x480, on disk beside the
    snapshots, or in a scratch file of ``trackgraph map``) and one pass over them at the end
    (23 s for the 600 frames of ``revisit`` on this 2-core machine)."""
    journal: JournalConfig = Field(default_factory=JournalConfig)
    """The write-ahead journal between snapshots."""
    reorder_wait_s: float = Field(10.0, gt=0)
    """Not in the paper: how long a tracker message that came ahead of its turn (its
    ``order``; a new frame overtaking the ones sent again after a fusion restart) waits for
    those before it. Past this fusion goes on without them (counted). Longer than
    ``tracker.resend_after_s``, so a resend is waited for."""
    reorder_capacity: int = Field(64, ge=1)
    """Not in the paper: the most tracker messages held waiting for their turn (a full-size
    tracked frame is a few MB); past this the missing ones are given up."""
    end_grace_s: float = Field(15.0, gt=0)
    """Not in the paper: after the tracker's ``tracks/end``, how long fusion waits for the
    frames and feature messages it announces that are still on their way; past this the map
    is finished without them, with a warning (``trackgraph map`` waits this long more than
    ``tracker.keyframe_timeout_s`` too). 15 s is chosen, not measured: one resend of a
    message lost on the link (``tracker.resend_after_s``, 5 s) and then the reorder wait for
    it (``reorder_wait_s``, 10 s)."""
