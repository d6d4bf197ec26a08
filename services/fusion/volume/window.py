"""Archive of voxel blocks that left the active window (III-A).

Blocks whose centre is farther than ``active_window_m`` from the pose leave the Open3D grid, so
integration, marching cubes and memory on the device scale with the window, not the map. Their
arrays are kept here, in host memory and bit for bit, keyed by block key; a block comes back
when its centre is within the radius again, or as soon as a frame's frustum touches it (so a
block never exists twice, whatever depth_max is). The whole block is archived, rather than
only its surface voxels, so a restored block continues exactly where it left off.

Storage is one array per attribute with a free-row list, plus a sorted index of packed keys for
vectorised lookup (``np.searchsorted``); archiving and restoring are a few numpy operations per
call, not per block.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np

_BIAS = 1 << 20
_MASK = (1 << 21) - 1


def pack_keys(
    keys: Annotated[np.ndarray, "(N, 3) int block keys"],
) -> Annotated[np.ndarray, "(N,) int64"]:
    """Injective int64 code of block keys in [-2^20, 2^20) per axis (250 km at 3 cm voxels)."""
    k = np.asarray(keys, dtype=np.int64) + _BIAS
    if k.size and (k.min() < 0 or k.max() > _MASK):
        raise ValueError("block key out of the packable range [-2^20, 2^20)")
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def block_centres(
    keys: Annotated[np.ndarray, "(N, 3) int block keys"], res: int, voxel_size: float
) -> Annotated[np.ndarray, "(N, 3) float64 metres"]:
    """Centre of each block's voxels; voxel i of a block sits at (key * res + i) * voxel_size."""
    return (np.asarray(keys, dtype=np.float64) * res + (res - 1) / 2) * voxel_size


class BlockArchive:
    """Host-side store of whole voxel blocks, each attribute an array (capacity, res, res, res, C)."""

    def __init__(self, layout: dict[str, tuple[np.dtype, int]], res: int) -> None:
        """``layout``: attribute name -> (dtype, channels)."""
        self.layout = {k: (np.dtype(d), int(c)) for k, (d, c) in layout.items()}
        self.res = res
        self._keys = np.zeros((0, 3), np.int32)
        self._epoch = np.zeros(0, np.int32)
        """Per row: the pose-correction epoch whose estimates placed the block."""
        self._used = np.zeros(0, bool)
        self._attrs = {k: np.zeros((0, res, res, res, c), d) for k, (d, c) in self.layout.items()}
        self._index_codes = np.zeros(0, np.int64)
        self._index_rows = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self._index_rows)

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self._attrs.values()) + self._keys.nbytes)

    def keys(self) -> Annotated[np.ndarray, "(M, 3) int32 archived block keys, sorted"]:
        return self._keys[self._index_rows]

    def _grow(self, extra: int) -> np.ndarray:
        free = np.flatnonzero(~self._used)
        if len(free) >= extra:
            return free[:extra]
        old = len(self._used)
        new_cap = max(old + extra - len(free), 2 * old, 64)
        self._keys = np.concatenate([self._keys, np.zeros((new_cap - old, 3), np.int32)])
        self._epoch = np.concatenate([self._epoch, np.zeros(new_cap - old, np.int32)])
        self._used = np.concatenate([self._used, np.zeros(new_cap - old, bool)])
        for name, a in self._attrs.items():
            pad = np.zeros((new_cap - old, *a.shape[1:]), a.dtype)
            self._attrs[name] = np.concatenate([a, pad])
        return np.flatnonzero(~self._used)[:extra]

    def add(
        self,
        keys: Annotated[np.ndarray, "(N, 3) int32 block keys, none already archived"],
        attrs: dict[str, Annotated[np.ndarray, "(N, res, res, res, C)"]],
        epoch: int = 0,
    ) -> None:
        """Archive blocks placed by the estimates of pose-correction ``epoch``."""
        if len(keys) == 0:
            return
        codes = pack_keys(keys)
        if len(np.unique(codes)) != len(codes) or np.any(self.lookup(keys) >= 0):
            raise ValueError("block archived twice")
        rows = self._grow(len(keys))
        self._keys[rows] = keys
        self._epoch[rows] = epoch
        self._used[rows] = True
        for name, a in self._attrs.items():
            a[rows] = attrs[name]
        all_codes = np.concatenate([self._index_codes, codes])
        all_rows = np.concatenate([self._index_rows, rows])
        order = np.argsort(all_codes, kind="stable")
        self._index_codes, self._index_rows = all_codes[order], all_rows[order]

    def lookup(
        self, keys: Annotated[np.ndarray, "(N, 3) int block keys"]
    ) -> Annotated[np.ndarray, "(N,) int64 row, -1 = not archived"]:
        if len(self._index_codes) == 0 or len(keys) == 0:
            return np.full(len(keys), -1, np.int64)
        codes = pack_keys(keys)
        pos = np.searchsorted(self._index_codes, codes).clip(max=len(self._index_codes) - 1)
        hit = self._index_codes[pos] == codes
        return np.where(hit, self._index_rows[pos], -1)

    def rows_within(
        self, center: Annotated[np.ndarray, "(3,)"], radius: float, voxel_size: float
    ) -> Annotated[np.ndarray, "(M,) int64 rows"]:
        rows = self._index_rows
        if len(rows) == 0:
            return rows
        d = np.linalg.norm(block_centres(self._keys[rows], self.res, voxel_size) - center, axis=1)
        return rows[d <= radius]

    def epochs_of(self, rows: Annotated[np.ndarray, "(M,) int64 archive rows"]) -> Annotated[np.ndarray, "(M,) int32"]:
        return self._epoch[np.asarray(rows, np.int64)].copy()

    def rows_before(self, epoch: int) -> Annotated[np.ndarray, "(M,) int64 rows placed before ``epoch``"]:
        rows = self._index_rows
        return rows[self._epoch[rows] < epoch]

    def peek(
        self, rows: Annotated[np.ndarray, "(M,) int64 archive rows"]
    ) -> tuple[Annotated[np.ndarray, "(M, 3) int32"], dict[str, np.ndarray]]:
        """The rows' keys and attribute arrays (copies), leaving them archived."""
        rows = np.asarray(rows, dtype=np.int64)
        return self._keys[rows].copy(), {name: a[rows].copy() for name, a in self._attrs.items()}

    def take(
        self, rows: Annotated[np.ndarray, "(M,) int64 archive rows"]
    ) -> tuple[Annotated[np.ndarray, "(M, 3) int32"], dict[str, np.ndarray]]:
        """Remove the rows from the archive and return their keys and attribute arrays."""
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        keys = self._keys[rows].copy()
        attrs = {name: a[rows].copy() for name, a in self._attrs.items()}
        self._used[rows] = False
        for a in self._attrs.values():
            a[rows] = 0  # free rows hold no stale data that a bug could resurrect
        keep = ~np.isin(self._index_rows, rows)
        self._index_codes, self._index_rows = self._index_codes[keep], self._index_rows[keep]
        return keys, attrs

    def state_dict(self) -> dict[str, np.ndarray]:
        rows = self._index_rows
        out = {"archive_keys": self._keys[rows].copy(), "archive_epoch": self._epoch[rows].copy()}
        for name, a in self._attrs.items():
            out[f"archive_{name}"] = a[rows].copy()
        return out

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.__init__(self.layout, self.res)
        keys = np.asarray(state["archive_keys"], dtype=np.int32).reshape(-1, 3)
        attrs = {name: state[f"archive_{name}"] for name in self._attrs}
        # saved before pose corrections: every block of epoch 0
        epochs = np.asarray(state.get("archive_epoch", np.zeros(len(keys), np.int32)), np.int32).reshape(-1)
        for e in np.unique(epochs).tolist():
            part = np.flatnonzero(epochs == e)
            self.add(keys[part], {n: np.asarray(a)[part] for n, a in attrs.items()}, epoch=int(e))
