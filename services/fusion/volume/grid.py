"""The voxel-block grid the volume lives in: Open3D's ``VoxelBlockGrid`` with a fixed layout of
per-voxel attributes, the host archive of blocks that left the active window
(:mod:`services.fusion.volume.window`), and the rigid move of blocks after a pose correction
(:mod:`services.fusion.volume.move`). What the attributes mean is the business of
:class:`services.fusion.volume.tsdf.HypothesisTSDF`, built on this.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from services.fusion.corrections.poses import Motion
from services.fusion.volume.mesh import attribute_array, index_like, like, to_host
from services.fusion.volume.move import MoveCounts, move_blocks, moving_voxels
from services.fusion.volume.window import BlockArchive, block_centres, pack_keys
from shared.config.fusion import TSDFConfig
from shared.o3d import import_open3d

log = logging.getLogger(__name__)

Layout = dict[str, tuple[Any, int]]
"""Attribute name -> (numpy dtype, channels), in the grid's attribute order."""


@dataclass
class MoveStats(MoveCounts):
    """What one :meth:`BlockGrid.move` did: the voxel counts of the move and these."""

    blocks_read: int = 0
    """Active blocks rewritten: those holding a moving voxel and those moved voxels landed in."""
    blocks_written: int = 0
    archived_moved: int = 0
    """Archived blocks moved now (only with ``restore_archived``; otherwise when read)."""
    seconds: float = 0.0


@dataclass
class WindowStats:
    archived: int
    restored: int
    active_blocks: int
    archived_blocks: int



def resolve_device(device: str) -> str:
    """Open3D device name for ``device``: 'auto' (CUDA when both open3d and torch have it),
    'cpu' or 'cuda[:N]'."""
    o3d = import_open3d()
    d = device.lower()
    if d == "auto":
        try:
            import torch

            torch_cuda = torch.cuda.is_available()
        except ImportError:
            torch_cuda = False
        return "CUDA:0" if o3d.core.cuda.is_available() and torch_cuda else "CPU:0"
    if d.startswith("cpu"):
        return "CPU:0"
    if d.startswith("cuda"):
        index = d.split(":", 1)[1] if ":" in d else "0"
        if not o3d.core.cuda.is_available():
            raise RuntimeError(
                f"device {device!r}: this open3d build has no CUDA (install `open3d`, not `open3d-cpu`)"
            )
        return f"CUDA:{int(index)}"
    raise ValueError(f"unknown device {device!r}; use 'auto', 'cpu' or 'cuda[:N]'")


class BlockGrid:
    """Active-window voxel blocks of a fixed attribute layout, with their archive."""

    def __init__(self, cfg: TSDFConfig, device_name: str, layout: Layout) -> None:
        """``device_name``: an Open3D device, as :func:`resolve_device` gives it."""
        self.cfg = cfg
        self._o3d = import_open3d()
        self._o3c = self._o3d.core
        self.device_name = device_name
        self._dev = self._o3c.Device(self.device_name)
        self.res = cfg.block_resolution
        self._layout = layout
        self.archive = BlockArchive(self._layout, self.res)
        self.vbg = self._new_grid(cfg.initial_blocks)
        self.epoch = 0
        """Pose corrections applied so far: blocks archived before the newest were placed by
        older estimates, and are moved when they are read
        (:meth:`HypothesisTSDF.extract_archived_mesh`)."""
        self.epoch_motion: Callable[[int], Motion] | None = None
        """From the estimates of an epoch to the current ones (set by the fusion core)."""
        self.track_writes = False
        """Note the blocks written (:meth:`touched`), for an incremental mesh; set by its user."""
        self._touched: list[np.ndarray] = []
        self._touched_all = True  # a new grid: nothing meshed from it yet

    def _touch(self, keys: Annotated[np.ndarray, "(N, 3) int block keys"]) -> None:
        if not self.track_writes or len(keys) == 0:
            return
        self._touched.append(pack_keys(keys))
        if len(self._touched) > 64:  # a long gap between meshes: keep the log short
            self._touched = [np.unique(np.concatenate(self._touched))]

    def touched(self) -> Annotated[np.ndarray, "(T,) int64 packed keys"] | None:
        """The blocks written, created or dropped since the last call (packed keys, sorted), and
        a fresh log; None when every block counts as written (a new or reloaded grid)."""
        out = None if self._touched_all else (np.unique(np.concatenate(self._touched)) if self._touched else np.zeros(0, np.int64))
        self._touched, self._touched_all = [], False
        return out

    # ---------------------------------------------------------------------------------------
    # grid plumbing

    def _new_grid(self, blocks: int) -> Any:
        o3c = self._o3c
        dtypes = {np.float32: o3c.float32, np.int32: o3c.int32, np.int8: o3c.int8}
        names = tuple(self._layout)
        return self._o3d.t.geometry.VoxelBlockGrid(
            attr_names=names,
            attr_dtypes=tuple(dtypes[self._layout[n][0]] for n in names),
            attr_channels=tuple(self._layout[n][1] for n in names),
            voxel_size=self.cfg.voxel_size,
            block_resolution=self.res,
            block_count=int(blocks),
            device=self._dev,
        )

    def _active(
        self,
    ) -> tuple[
        Annotated[np.ndarray, "(N,) int64 buffers"], Annotated[np.ndarray, "(N, 3) int32 keys"]
    ]:
        hm = self.vbg.hashmap()
        bufs = hm.active_buf_indices().cpu().numpy().astype(np.int64)
        # the whole key table is small (12 bytes a block); Open3D's own indexing is slow on CPU
        return bufs, hm.key_tensor().cpu().numpy()[bufs]

    def _read_blocks(self, bufs: np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for name in self._layout:
            arr = attribute_array(self.vbg, name)
            out[name] = to_host(arr[index_like(arr, bufs.astype(np.int64))])
        return out

    def _write_blocks(self, keys: np.ndarray, attrs: dict[str, np.ndarray], grid: Any = None) -> None:
        """Insert blocks (new or existing keys) with exactly these voxel arrays, into the
        active grid or ``grid``."""
        if len(keys) == 0:
            return
        vbg = self.vbg if grid is None else grid
        hm = vbg.hashmap()
        kt = self._o3c.Tensor(np.ascontiguousarray(keys, dtype=np.int32)).to(self._dev)
        hm.activate(kt)
        # activate reports no buffer for keys already present; find covers both, and runs after
        # any rehash that activate caused
        bufs, found = hm.find(kt)
        if not bool(found.cpu().numpy().all()):
            raise RuntimeError("voxel block grid refused blocks")
        bufs = bufs.cpu().numpy().astype(np.int64)
        for name in self._layout:
            arr = attribute_array(vbg, name)
            arr[index_like(arr, bufs)] = like(
                arr, np.asarray(attrs[name], dtype=self._layout[name][0])
            )
        if grid is None:
            self._touch(keys)

    def _erase_blocks(self, bufs: np.ndarray, keys: np.ndarray) -> None:
        # Open3D hands a freed buffer to the next new block without clearing it
        for name in self._layout:
            arr = attribute_array(self.vbg, name)
            arr[index_like(arr, bufs.astype(np.int64))] = 0
        self.vbg.hashmap().erase(
            self._o3c.Tensor(np.ascontiguousarray(keys, np.int32)).to(self._dev)
        )
        self._touch(keys)

    @property
    def active_blocks(self) -> int:
        return int(self.vbg.hashmap().size())

    @property
    def archived_blocks(self) -> int:
        return len(self.archive)

    # ---------------------------------------------------------------------------------------
    # active window

    def update_window(
        self, center: Annotated[np.ndarray, "(3,) world metres, e.g. the camera position"]
    ) -> WindowStats:
        """Archive blocks whose centre is farther than ``active_window_m`` from ``center`` and
        bring back archived blocks within it."""
        center = np.asarray(center, np.float64).reshape(3)
        radius = self.cfg.active_window_m
        bufs, keys = self._active()
        far = (
            np.linalg.norm(block_centres(keys, self.res, self.cfg.voxel_size) - center, axis=1)
            > radius
        )
        n_out = int(far.sum())
        if n_out:
            older = self.archive.lookup(keys[far])
            if np.any(older >= 0):
                # a revisit rebuilt these blocks afresh: the newer reconstruction replaces the older
                self.archive.take(older[older >= 0])
            self.archive.add(keys[far], self._read_blocks(bufs[far]), epoch=self.epoch)
            self._erase_blocks(bufs[far], keys[far])
        n_in = (
            self._restore_rows(self.archive.rows_within(center, radius, self.cfg.voxel_size))
            if self.cfg.restore_archived
            else 0
        )
        if n_out or n_in:
            log.debug(
                "window at %s: archived %d blocks, restored %d", np.round(center, 2), n_out, n_in
            )
        return WindowStats(n_out, n_in, int(self.vbg.hashmap().size()), len(self.archive))

    def _restore_rows(
        self, rows: Annotated[np.ndarray, "(M,) int64 archive rows, -1 = skip"]
    ) -> int:
        rows = rows[rows >= 0]
        if len(rows) == 0:
            return 0
        keys, attrs = self.archive.take(rows)
        self._write_blocks(keys, attrs)
        return len(keys)

    # ---------------------------------------------------------------------------------------
    # pose corrections

    def move(self, motion: Motion, epoch: int) -> MoveStats:
        """Move every voxel by the motion of its anchor frame (a pose correction), in place
        (:mod:`services.fusion.volume.move`).

        Only the blocks holding a moving voxel, and the blocks the moved voxels land in, are
        rewritten. Archived blocks stay as they are, tagged with the epoch they were placed
        in, and move when read (:meth:`extract_archived_mesh`); with ``restore_archived`` they
        move now, since a frame may restore them by key at any time."""
        t0 = time.perf_counter()
        self.epoch = int(epoch)
        stats = MoveStats()
        if len(motion):
            bufs, keys = self._active()
            if len(bufs):
                arr = attribute_array(self.vbg, "anchor")
                anchors = to_host(arr[index_like(arr, bufs)]).reshape(len(bufs), -1)
                src = np.flatnonzero(moving_voxels(motion, anchors).any(axis=1))
                if len(src):
                    stats = self._move_blocks(bufs, keys, src, motion)
            if self.cfg.restore_archived and len(self.archive):
                stats.archived_moved = self._move_archive()
        stats.seconds = time.perf_counter() - t0
        return stats

    def _move_blocks(self, bufs: np.ndarray, keys: np.ndarray, src: np.ndarray, motion: Motion) -> MoveStats:
        """Rewrite active blocks ``src`` (rows of ``bufs``/``keys``) and the blocks their moved
        voxels land in."""
        arrays = {name: attribute_array(self.vbg, name) for name in self._layout}
        if all(isinstance(a, np.ndarray) for a in arrays.values()):
            # CPU: the kernel reads the grid's own memory, no copy of the blocks first
            out_keys, out_attrs, counts = move_blocks(keys[src], arrays, motion, self.res, self.cfg.voxel_size, self._layout, rows=bufs[src])
        else:
            out_keys, out_attrs, counts = move_blocks(keys[src], self._read_blocks(bufs[src]), motion, self.res, self.cfg.voxel_size, self._layout)
        # blocks the voxels landed in that hold voxels of their own: merged, heavier voxel wins
        rest = np.setdiff1d(np.arange(len(keys)), src)
        hit = rest[np.isin(pack_keys(keys[rest]), pack_keys(out_keys))] if len(rest) and len(out_keys) else rest[:0]
        parts = [(out_keys, out_attrs)]
        if len(hit):
            parts = self._merge_parts(out_keys, out_attrs, keys[hit], self._read_blocks(bufs[hit]))
        old = np.concatenate([src, hit])
        self._erase_blocks(bufs[old], keys[old])
        for k, a in parts:
            self._write_blocks(k, a)  # the hash map grows as it needs
        written = sum(len(k) for k, _ in parts)
        return MoveStats(**vars(counts), blocks_read=len(old), blocks_written=written)

    def _merge_parts(self, keys_a: np.ndarray, attrs_a: dict, keys_b: np.ndarray, attrs_b: dict) -> list[tuple[np.ndarray, dict]]:
        """Two sets of blocks as one, in two parts: the blocks of ``a`` with a key of their own,
        and those of one key in both rasterised again (on a shared voxel the heavier stays)."""
        clash = np.isin(pack_keys(keys_a), pack_keys(keys_b))
        keys = np.concatenate([keys_a[clash], keys_b])
        attrs = {n: np.concatenate([attrs_a[n][clash], attrs_b[n]]) for n in self._layout}
        still = Motion(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        merged_keys, merged = move_blocks(keys, attrs, still, self.res, self.cfg.voxel_size, self._layout)[:2]
        return [(keys_a[~clash], {n: attrs_a[n][~clash] for n in self._layout}), (merged_keys, merged)]

    def _merge(self, keys_a: np.ndarray, attrs_a: dict, keys_b: np.ndarray, attrs_b: dict) -> tuple[np.ndarray, dict]:
        """:meth:`_merge_parts` as one set of blocks."""
        parts = self._merge_parts(keys_a, attrs_a, keys_b, attrs_b)
        return np.concatenate([k for k, _ in parts]).astype(np.int32), {n: np.concatenate([a[n] for _, a in parts]) for n in self._layout}

    def _move_archive(self) -> int:
        """Every archived block placed by an older epoch, moved to the current estimates."""
        rows = self.archive.rows_before(self.epoch)
        if len(rows) == 0:
            return 0
        epochs = self.archive.epochs_of(rows)
        keys, attrs = self.archive.take(rows)
        keys, attrs = self._archived_now(keys, attrs, epochs)
        clash = self.archive.lookup(keys)
        if np.any(clash >= 0):
            k2, a2 = self.archive.take(clash[clash >= 0])
            keys, attrs = self._merge(keys, attrs, k2, a2)
        self.archive.add(keys, attrs, epoch=self.epoch)
        return len(rows)

    def _archived_now(
        self, keys: np.ndarray, attrs: dict[str, np.ndarray], epochs: Annotated[np.ndarray, "(M,) int epoch per block"]
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Archived blocks as the current estimates place them (blocks of older epochs moved)."""
        old = np.flatnonzero(epochs < self.epoch)
        if len(old) == 0 or self.epoch_motion is None:
            return keys, attrs
        parts = [(keys[epochs >= self.epoch], {n: a[epochs >= self.epoch] for n, a in attrs.items()})]
        for e in np.unique(epochs[old]).tolist():
            part = old[epochs[old] == e]
            k, a, _ = move_blocks(keys[part], {n: v[part] for n, v in attrs.items()}, self.epoch_motion(int(e)), self.res, self.cfg.voxel_size, self._layout)
            parts.append((k, a))
        keys, attrs = parts[0]
        for k, a in parts[1:]:
            keys, attrs = self._merge(keys, attrs, k, a) if len(keys) else (k, a)
        return keys, attrs
