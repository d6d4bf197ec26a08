"""TSDF volume with K source-track hypotheses per voxel, over Open3D's VoxelBlockGrid (III-A, III-C).

Deviation from the paper (docs/method.md, F1): the paper runs Hydra as its reconstruction and
scene-graph backbone; here the TSDF, the mesh and the graph are this project's own, so the
hypotheses live in the voxel grid itself, and maps are also written as spark_dsg files
(``shared.graph.dsg``) that Hydra's tools open.

The grid holds Open3D's ``tsdf``, ``weight`` and ``color`` plus two extra attributes,
``hyp_id`` (K int32 track codes, ``track_id + 1``, 0 = empty slot, so the zero memory of a new
block is a voxel with no hypothesis) and ``hyp_w`` (K float32 accumulated weights l). Each frame:

1. the frame's blocks (``compute_unique_block_coordinates``), restoring any of them that sits in
   the window archive;
2. the pixel pass of the hypothesis vote (:mod:`services.fusion.volume.hypotheses`), which validates
   the track ids before anything changes;
3. Open3D's plain ``integrate`` (weight 1 per observation: w_TSDF = 1 in eq. 5);
4. the slot pass: eq. 5 and the slot rule, in place on the grid's memory.

The grid contains only the active window; :meth:`HypothesisTSDF.update_window` moves blocks
out to and back from a host archive (:mod:`services.fusion.volume.grid`, over
:mod:`services.fusion.volume.window`). On CUDA the grid lives on
the GPU and the vote runs in torch on the same memory (DLPack); on CPU it runs in numba
(``fusion.tsdf.vote_backend``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from services.fusion.types import HypothesisMesh
from services.fusion.volume.anchors import anchor_in_place, anchor_rule
from services.fusion.volume.cubes import BlockCopy, block_copy, hypothesis_mesh
from services.fusion.volume.cubes import available as cubes_available
from services.fusion.volume.grid import BlockGrid, resolve_device
from services.fusion.volume.hypotheses import (
    FrameGeometry,
    NumbaVote,
    TorchVote,
    VoteResult,
    gamma_table,
    numba_available,
)
from services.fusion.volume.incremental import BlockUpdate, MeshCache, changed_rows
from services.fusion.volume.mesh import (
    attribute_array,
    extract_hypothesis_mesh,
    gather_rows,
    index_like,
    like,
    to_host,
    voxel_flat_index,
)
from services.fusion.volume.window import pack_keys
from shared.config.fusion import TSDFConfig
from shared.geometry import Intrinsics, Pose, invert, is_rigid

log = logging.getLogger(__name__)

MESH_WEIGHT_THRESHOLD = 1.0
"""Marching cubes uses voxels with TSDF weight above this: surfaces seen in at least two frames,
which drops single-frame depth noise."""

STATE_VERSION = 2
"""2: the ``anchor`` and ``offset`` attributes (version 1 states load with every anchor unknown
and no offset)."""


@dataclass
class IntegrateStats(VoteResult):
    """What one :meth:`HypothesisTSDF.integrate` did: the vote's counts and these."""

    frame_blocks: int = 0
    """Blocks the frame's truncation band touches."""
    active_blocks: int = 0
    """Blocks in the grid after integration."""
    restored_blocks: int = 0
    """Archived blocks that the frame touched and were brought back first."""
    seconds_tsdf: float = 0.0
    seconds_hypotheses: float = 0.0


class HypothesisTSDF(BlockGrid):
    """Active-window TSDF whose voxels keep up to K (track, weight) hypotheses."""

    def __init__(
        self,
        cfg: TSDFConfig,
        device: str = "auto",
        mesh_weight_threshold: float = MESH_WEIGHT_THRESHOLD,
    ) -> None:
        """``device``: 'auto' (CUDA when both open3d and torch have it), 'cpu' or 'cuda[:N]'.
        The vote's backend is ``cfg.vote_backend``: 'auto' (numba on CPU when installed, else
        torch), 'numba' or 'torch'; :attr:`backend` is the one chosen."""
        self.mesh_weight_threshold = float(mesh_weight_threshold)
        device_name = resolve_device(device)
        on_cuda = device_name.startswith("CUDA")
        backend = cfg.vote_backend
        if backend == "auto":
            backend = "numba" if numba_available() and not on_cuda else "torch"
        if backend == "numba":
            if on_cuda:
                raise ValueError("the numba vote runs on CPU; use fusion.tsdf.vote_backend 'torch' or 'auto' on CUDA")
            self._vote: NumbaVote | TorchVote = NumbaVote()
        elif backend == "torch":
            if on_cuda:
                import torch

                if not torch.cuda.is_available():
                    raise RuntimeError("open3d runs on CUDA but torch has no CUDA for the vote")
            self._vote = TorchVote(("cuda:" + device_name.split(":")[1]) if on_cuda else "cpu")
        else:
            raise ValueError(f"unknown fusion.tsdf.vote_backend {backend!r}; use 'auto', 'numba' or 'torch'")
        self.backend = backend
        self.K = cfg.hypotheses
        layout = {
            "tsdf": (np.float32, 1), "weight": (np.float32, 1), "color": (np.float32, 3),
            "hyp_id": (np.int32, self.K), "hyp_w": (np.float32, self.K), "anchor": (np.int32, 1),
            "offset": (np.int8, 3),
        }  # fmt: skip
        super().__init__(cfg, device_name, layout)
        self.frames = 0
        self.mesh_cache = MeshCache(self.K)
        """The map path's pieces of the mesh (:meth:`mesh_of_update`)."""
        self._mesh_seq = 0  # captures by copy_changed

    def _hyp_views(self) -> tuple[Any, Any]:
        """(capacity * res^3, K) views of hyp_id and hyp_w, re-read each frame because a grid
        that grows reallocates."""
        a_id, a_w = self.vbg.attribute("hyp_id"), self.vbg.attribute("hyp_w")
        if isinstance(self._vote, NumbaVote):
            return a_id.numpy().reshape(-1, self.K), a_w.numpy().reshape(-1, self.K)
        from torch.utils.dlpack import from_dlpack

        return (
            from_dlpack(a_id.to_dlpack()).reshape(-1, self.K),
            from_dlpack(a_w.to_dlpack()).reshape(-1, self.K),
        )

    # ---------------------------------------------------------------------------------------
    # integration

    def integrate(
        self,
        depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 or NaN = no reading"],
        rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
        K: Intrinsics,
        T_world_cam: Pose,
        track_ids: Annotated[np.ndarray, "(H, W) int32 source track per pixel, -1 = none"]
        | None = None,
        gamma: dict[int, float] | None = None,
        frame_index: int | None = None,
    ) -> IntegrateStats:
        """Fuse one frame into the TSDF, then add gamma[tau] (eq. 6) to the hypotheses of the
        voxels seen inside the mask of each track tau (eq. 5). Every track id in ``track_ids``
        needs a ``gamma`` entry; a missing one raises ValueError before anything changes.
        The frame's blocks are anchored to ``frame_index`` (default: the count of frames
        integrated so far): a pose correction moves them with that frame."""
        cfg = self.cfg
        h, w = depth_m.shape[:2]
        if (w, h) != (K.width, K.height) or depth_m.ndim != 2:
            raise ValueError(
                f"depth {depth_m.shape} does not match intrinsics {K.width}x{K.height}"
            )
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be ({h}, {w}, 3) uint8, got {rgb.shape} {rgb.dtype}")
        if track_ids is None:
            track_ids = np.full((h, w), -1, np.int32)
        if track_ids.shape != (h, w):
            raise ValueError(f"track_ids {track_ids.shape} does not match depth {depth_m.shape}")
        T_world_cam = np.asarray(T_world_cam, np.float64)
        if not is_rigid(T_world_cam):
            raise ValueError("T_world_cam is not a rigid transform")
        gid, gval = gamma_table(gamma or {})
        track_ids = np.ascontiguousarray(track_ids, dtype=np.int32)

        o3c, o3d = self._o3c, self._o3d
        t0 = time.perf_counter()
        depth = np.asarray(depth_m, np.float32)
        # NaN fails both comparisons, so missing readings become 0 (no reading) here too
        depth = np.where((depth >= cfg.depth_min) & (depth <= cfg.depth_max), depth, np.float32(0))
        dimg = o3d.t.geometry.Image(o3c.Tensor.from_numpy(depth).to(self._dev))
        color = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
        cimg = o3d.t.geometry.Image(o3c.Tensor.from_numpy(color).to(self._dev))
        intr = o3c.Tensor(K.matrix(), o3c.float64)
        extr = o3c.Tensor(invert(T_world_cam), o3c.float64)
        trunc = float(cfg.trunc_voxels)
        bc = self._frame_blocks(dimg, intr, extr, depth)
        bc_np = bc.cpu().numpy().astype(np.int64).reshape(-1, 3)
        t_tsdf = time.perf_counter() - t0

        t0 = time.perf_counter()
        geo = self._frame_geometry(K, T_world_cam, bc_np)
        passed = self._vote.pixel_pass(depth, track_ids, gid, geo, len(bc_np))
        # validated: now bring back archived blocks that this frame touches, so none exists twice
        restored = (
            self._restore_rows(self.archive.lookup(bc_np))
            if len(self.archive) and self.cfg.restore_archived
            else 0
        )
        t_hyp = time.perf_counter() - t0
        if len(bc_np) == 0:  # no valid depth: nothing to fuse
            self.frames += 1
            return IntegrateStats(
                active_blocks=self.active_blocks, seconds_tsdf=t_tsdf, seconds_hypotheses=t_hyp
            )

        t0 = time.perf_counter()
        before = self._weights_of(bc)
        self.vbg.integrate(bc, dimg, cimg, intr, extr, 1.0, cfg.depth_max, trunc)
        t_tsdf += time.perf_counter() - t0
        self._touch(bc_np)

        t0 = time.perf_counter()
        bufs, found = self.vbg.hashmap().find(bc)
        if not bool(found.cpu().numpy().all()):
            raise RuntimeError("integrate left frame blocks unallocated")
        hyp_id, hyp_w = self._hyp_views()
        host_bufs = bufs.cpu().numpy().astype(np.int64)
        vote = self._vote.slot_pass(passed, gid, gval, host_bufs, self.res, hyp_id, hyp_w)
        self._anchor(host_bufs, before, self.frames if frame_index is None else int(frame_index))
        t_hyp += time.perf_counter() - t0
        self.frames += 1
        stats = IntegrateStats(
            **vars(vote), frame_blocks=len(bc_np), active_blocks=int(self.vbg.hashmap().size()),
            restored_blocks=restored, seconds_tsdf=t_tsdf, seconds_hypotheses=t_hyp,
        )  # fmt: skip
        if vote.overflow:
            log.debug(
                "frame %d: %d (voxel, track) pairs over the per-voxel limit",
                self.frames,
                vote.overflow,
            )
        return stats

    def _weights_of(self, bc: Any) -> Annotated[np.ndarray, "(B, res^3) float32, 0 in blocks not yet allocated"]:
        """TSDF weights of the frame's blocks before it is fused (for their anchors)."""
        bufs, found = self.vbg.hashmap().find(bc)
        bufs, found = bufs.cpu().numpy().astype(np.int64), found.cpu().numpy().astype(bool)
        out = np.zeros((len(bufs), self.res**3), np.float32)
        if found.any():
            arr = attribute_array(self.vbg, "weight")
            out[found] = to_host(arr[index_like(arr, bufs[found])]).reshape(int(found.sum()), -1)
        return out

    def _anchor(self, bufs: np.ndarray, before: np.ndarray, frame: int) -> None:
        """Each voxel the frame updated is anchored to the weighted mean of the frames fused
        into it (rounded): a surface averaged over frames with different drift sits where their
        mean puts it, so a correction moves it best by the mean frame's motion, not the last
        one's (:mod:`services.fusion.volume.move`, :mod:`services.fusion.volume.anchors`)."""
        w_arr, a_arr = attribute_array(self.vbg, "weight"), attribute_array(self.vbg, "anchor")
        if anchor_in_place(w_arr, a_arr, bufs, before, frame):
            return
        idx = index_like(w_arr, bufs)
        after = to_host(w_arr[idx]).reshape(len(bufs), -1).astype(np.float64)
        old = to_host(a_arr[idx]).reshape(len(bufs), -1).astype(np.float64)
        anchors = anchor_rule(after, old, before, frame)
        a_arr[idx] = like(a_arr, anchors.reshape(len(bufs), self.res, self.res, self.res, 1))

    def _frame_blocks(self, dimg: Any, intr: Any, extr: Any, depth: np.ndarray) -> Any:
        """Blocks within truncation of the frame's surface points, (B, 3) int32 on the device."""
        empty = self._o3c.Tensor(np.zeros((0, 3), np.int32)).to(self._dev)
        if not np.any(depth > 0):
            return empty
        try:
            return self.vbg.compute_unique_block_coordinates(
                dimg, intr, extr, 1.0, self.cfg.depth_max, float(self.cfg.trunc_voxels)
            )
        except RuntimeError as exc:
            # Open3D samples the depth image with a stride and raises when no sample is valid
            if "No block is touched" in str(exc):
                return empty
            raise

    def _frame_geometry(
        self, K: Intrinsics, T_world_cam: np.ndarray, bc: np.ndarray
    ) -> FrameGeometry:
        """Dense lookup from block key to frame block index over the frame's bounding box of
        blocks: a few ten thousand cells, far cheaper than a hash lookup per pixel."""
        if len(bc):
            bmin = bc.min(axis=0)
            bext = bc.max(axis=0) - bmin + 1
            lut = np.full(int(np.prod(bext)), -1, np.int32)
            off = bc - bmin
            lut[(off[:, 0] * bext[1] + off[:, 1]) * bext[2] + off[:, 2]] = np.arange(
                len(bc), dtype=np.int32
            )
        else:
            bmin, bext, lut = np.zeros(3, np.int64), np.zeros(3, np.int64), np.full(1, -1, np.int32)
        res = self.res
        return FrameGeometry(
            R=np.ascontiguousarray(T_world_cam[:3, :3]), t=np.ascontiguousarray(T_world_cam[:3, 3]),
            xs=(np.arange(K.width, dtype=np.float64) - K.cx) / K.fx,
            ys=(np.arange(K.height, dtype=np.float64) - K.cy) / K.fy,
            inv_voxel=1.0 / float(self.cfg.voxel_size), res=res,
            shift=res.bit_length() - 1 if res & (res - 1) == 0 else -1,
            bmin=bmin.astype(np.int64), bext=bext.astype(np.int64), lut=lut,
        )  # fmt: skip

    # ---------------------------------------------------------------------------------------
    # outputs

    def extract_mesh(self) -> HypothesisMesh:
        """Marching-cubes mesh of the active window with each vertex's colour and hypotheses."""
        blocks = self.copy_active()
        if blocks is not None:
            return self.mesh_of(blocks)
        return extract_hypothesis_mesh(
            self.vbg, self.cfg.voxel_size, self.res, self.K, self.mesh_weight_threshold
        )

    def copy_active(self) -> BlockCopy | None:
        """The active blocks' arrays, copied (:mod:`services.fusion.volume.cubes`): the frame
        path's part of a mesh whose marching cubes run elsewhere (:meth:`mesh_of`). None on
        CUDA or without numba, where Open3D meshes the grid itself."""
        if self.device_name.startswith("CUDA") or not cubes_available():
            return None
        bufs, keys = self._active()
        return block_copy(keys, self._read_blocks(bufs))

    def copy_changed(self) -> BlockUpdate | None:
        """The frame path's part of an incremental mesh (:mod:`services.fusion.volume.incremental`):
        a copy of the blocks whose pieces changed since the last call and the blocks above
        them (all active blocks the first time, after a reload, or when the last update was
        not applied). None on CUDA or without numba, as :meth:`copy_active`."""
        if self.device_name.startswith("CUDA") or not cubes_available():
            return None
        self.track_writes = True
        bufs, keys = self._active()
        packed = pack_keys(keys) if len(keys) else np.zeros(0, np.int64)
        touched = self.touched()
        full = touched is None or self.mesh_cache.seq != self._mesh_seq
        if full:
            rows, redo = np.arange(len(keys)), np.ones(len(keys), bool)
        else:
            rows, redo = changed_rows(packed, touched)
        self._mesh_seq += 1
        return BlockUpdate(blocks=block_copy(keys[rows], self._read_blocks(bufs[rows])), redo=redo, active=packed,
                           full=full, seq=self._mesh_seq)  # fmt: skip

    def mesh_of_update(self, update: BlockUpdate) -> HypothesisMesh:
        """The mesh of the active window after ``update``: its pieces marched, the others kept
        (the map path's part; reads no grid state)."""
        return self.mesh_cache.apply(update, self.cfg.voxel_size, self.mesh_weight_threshold)

    def mesh_of(self, blocks: BlockCopy) -> HypothesisMesh:
        """The hypothesis mesh of copied blocks (no grid state read: safe beside the frame path)."""
        return hypothesis_mesh(blocks, self.cfg.voxel_size, self.K, self.mesh_weight_threshold)

    def extract_archived_mesh(self) -> HypothesisMesh:
        """Marching cubes over the archived blocks the active grid does not hold again: the
        map outside the window, for a whole-map export (seams where it meets the window)."""
        keys = self.archive.keys()
        if len(keys) == 0:
            return HypothesisMesh.empty(self.K)
        _, active = self._active()
        if len(active):
            keys = keys[~np.isin(pack_keys(keys), pack_keys(active))]
        if len(keys) == 0:
            return HypothesisMesh.empty(self.K)
        rows = self.archive.lookup(keys)
        keys, attrs = self.archive.peek(rows)
        keys, attrs = self._archived_now(keys, attrs, self.archive.epochs_of(rows))
        if cubes_available():
            return self.mesh_of(block_copy(keys, attrs))
        grid = self._new_grid(len(keys) + 16)
        self._write_blocks(keys, attrs, grid=grid)
        return extract_hypothesis_mesh(grid, self.cfg.voxel_size, self.res, self.K, self.mesh_weight_threshold)

    def hypotheses_at(
        self, points: Annotated[np.ndarray, "(N, 3) world metres"]
    ) -> tuple[
        Annotated[np.ndarray, "(N, K) int32 track ids, -1 = empty"],
        Annotated[np.ndarray, "(N, K) float32"],
    ]:
        """Hypotheses of the active voxel nearest to each point (empty outside the grid)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros((0, self.K), np.int32), np.zeros((0, self.K), np.float32)
        flat = voxel_flat_index(self.vbg, points, self.cfg.voxel_size, self.res)
        ids = gather_rows(self.vbg, "hyp_id", flat, 0).astype(np.int32) - 1
        return ids, gather_rows(self.vbg, "hyp_w", flat, 0.0).astype(np.float32)
    def nbytes(self) -> dict[str, int]:
        """Bytes held: the grid's preallocated buffers (on its device) and the host archive."""
        per_voxel = sum(np.dtype(d).itemsize * c for d, c in self._layout.values())
        capacity = int(self.vbg.hashmap().capacity())
        return {"grid": capacity * self.res**3 * per_voxel, "archive": self.archive.nbytes}

    # ---------------------------------------------------------------------------------------
    # persistence

    def state_dict(self) -> dict[str, np.ndarray]:
        """Plain numpy arrays (``np.savez``-able): active and archived blocks, sorted by key."""
        bufs, keys = self._active()
        order = np.argsort(pack_keys(keys), kind="stable")
        state = {
            "version": np.int64(STATE_VERSION),
            "voxel_size": np.float64(self.cfg.voxel_size),
            "block_resolution": np.int64(self.res),
            "hypotheses": np.int64(self.K),
            "frames": np.int64(self.frames),
            "epoch": np.int64(self.epoch),
            "keys": keys[order].astype(np.int32),
        }
        state.update(self._read_blocks(bufs[order]))
        state.update(self.archive.state_dict())
        return state

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """Replace the whole volume by a :meth:`state_dict`; the layout must match this config."""
        version = int(state["version"])
        if version not in (1, STATE_VERSION):
            raise ValueError(f"TSDF state version {version}, expected {STATE_VERSION} (or 1)")
        if version == 1:
            # saved before anchors: every block's frame is unknown (-1), and nothing moves it
            state = dict(state)
            for prefix, key in (("", "keys"), ("archive_", "archive_keys")):
                n = len(np.asarray(state[key]).reshape(-1, 3))
                state[f"{prefix}anchor"] = np.full((n, self.res, self.res, self.res, 1), -1, np.int32)
                state[f"{prefix}offset"] = np.zeros((n, self.res, self.res, self.res, 3), np.int8)
        mine = (self.cfg.voxel_size, self.res, self.K)
        theirs = (
            float(state["voxel_size"]),
            int(state["block_resolution"]),
            int(state["hypotheses"]),
        )
        if not np.isclose(mine[0], theirs[0]) or mine[1:] != theirs[1:]:
            raise ValueError(
                f"TSDF state has (voxel_size, block_resolution, K) = {theirs}, config has {mine}"
            )
        keys = np.asarray(state["keys"], np.int32).reshape(-1, 3)
        # a quarter to spare: a grid loaded full rehashes (copies every block) on the first new one
        self.vbg = self._new_grid(max(self.cfg.initial_blocks, len(keys) + len(keys) // 4))
        self._touched, self._touched_all = [], True
        self._write_blocks(keys, {name: state[name] for name in self._layout})
        self.archive.load_state_dict(state)
        self.frames = int(state.get("frames", 0))
        self.epoch = int(state.get("epoch", 0))
