"""Room footprints of a saved map: a 2D grid of room ids, ``MAP_DIR/rooms.npz``.

The grid is fusion's free-space grid (``services.fusion.layers.places.FreeSpaceMap``): axis 0 is
world x, axis 1 world y, and cell ``(i, j)`` covers ``x in [origin_x + i * res, origin_x +
(i + 1) * res)`` and ``y in [origin_y + j * res, origin_y + (j + 1) * res)``, so its centre
is ``origin + (i + 0.5, j + 0.5) * res``. Each cell holds the id of the room that owns it
(a ``RoomNode.id`` of the graph saved beside it) or -1.

File keys (``np.savez_compressed``, no pickles): ``format`` and ``version`` (a string and an
int, checked on load), ``labels`` (H, W) int32, ``origin`` (2,) float64, ``resolution`` ()
float64, ``room_ids`` (R,) int64 and ``names`` (R,) unicode (empty string: unnamed).
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np

from shared.io import atomic_write_bytes

ROOMS_FILE = "rooms.npz"
"""Where a map folder keeps its room grid."""
FORMAT = "trackgraph-room-grid"
VERSION = 1
KEYS = ("format", "version", "labels", "origin", "resolution", "room_ids", "names")


class RoomGridError(ValueError):
    """A room grid file is missing, unreadable or inconsistent; the message starts with it."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


def _lossless(a: np.ndarray, dtype: type) -> np.ndarray:
    """``a`` as ``dtype`` when it is an integer array (or empty) that fits, else unchanged."""
    if a.dtype == dtype:
        return a
    if a.size == 0 and a.dtype.kind in "iuf":  # np.array([]) is float64
        return a.astype(dtype)
    info = np.iinfo(dtype)
    if a.dtype.kind in "iu" and a.size and info.min <= a.min() and a.max() <= info.max:
        return a.astype(dtype)
    return a


@dataclass
class RoomGrid:
    """Room ids of the cells of a 2D grid over world xy (see the module docstring)."""

    labels: Annotated[np.ndarray, "(H, W) int32 room id of each cell, -1 for none"]
    origin: Annotated[np.ndarray, "(2,) float64 world xy of the corner of cell (0, 0)"]
    resolution: float
    """Cell size (m)."""
    room_ids: Annotated[np.ndarray, "(R,) int64 the rooms, RoomNode ids"]
    names: list[str] = field(default_factory=list)
    """(R,) each room's name (its RoomNode ``name``; empty when unnamed), or empty for none."""

    def __post_init__(self) -> None:
        # Integer arrays of another width are taken when the cast loses nothing; anything else
        # is left for validate() to name.
        self.labels = _lossless(np.asarray(self.labels), np.int32)
        self.origin = np.asarray(self.origin, np.float64)
        self.room_ids = _lossless(np.asarray(self.room_ids), np.int64)
        self.resolution = float(self.resolution)
        self.names = [str(n) for n in self.names]

    @property
    def shape(self) -> tuple[int, int]:
        return self.labels.shape  # type: ignore[return-value]

    def centers(self) -> Annotated[np.ndarray, "(H, W, 2) float64 world xy of each cell centre"]:
        h, w = self.shape
        i, j = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        return self.origin + (np.stack([i, j], axis=-1) + 0.5) * self.resolution

    def cell_counts(self) -> Annotated[np.ndarray, "(R,) int64 cells of each room, in room_ids order"]:
        order = np.argsort(self.room_ids)
        inside = self.labels[self.labels >= 0]
        pos = order[np.searchsorted(self.room_ids[order], inside)]
        return np.bincount(pos, minlength=len(self.room_ids)).astype(np.int64)

    def validate(self, where: str | Path = "<room grid>") -> None:
        """Raise :class:`RoomGridError` naming ``where`` and the field unless the grid is
        well formed: dtypes and shapes as declared, a positive finite resolution, unique
        non-negative room ids, every label -1 or one of them, one name per room (or none)."""
        lab, ids = self.labels, self.room_ids
        if lab.ndim != 2 or lab.dtype != np.int32:
            raise RoomGridError(where, f"labels: expected an (H, W) int32 array, got {lab.dtype} {lab.shape}")
        if self.origin.shape != (2,) or not np.isfinite(self.origin).all():
            raise RoomGridError(where, f"origin: expected 2 finite floats (world xy), got {self.origin.tolist()}")
        if not np.isfinite(self.resolution) or self.resolution <= 0:
            raise RoomGridError(where, f"resolution: expected a positive cell size in metres, got {self.resolution}")
        if ids.ndim != 1 or ids.dtype != np.int64:
            raise RoomGridError(where, f"room_ids: expected an (R,) int64 array, got {ids.dtype} {ids.shape}")
        if (ids < 0).any() or len(np.unique(ids)) != len(ids):
            raise RoomGridError(where, f"room_ids: expected unique non-negative RoomNode ids, got {ids.tolist()}")
        if self.names and len(self.names) != len(ids):
            raise RoomGridError(where, f"names: {len(self.names)} names for {len(ids)} rooms (give one per room, or none)")
        used = np.unique(lab)
        stray = used[(used != -1) & ~np.isin(used, ids)]
        if len(stray):
            raise RoomGridError(where, f"labels: ids {stray[:10].tolist()} are neither -1 nor in room_ids {ids.tolist()}")

    def name_of(self, room_id: int) -> str:
        """The room's name ('' when the grid carries no names)."""
        if not self.names:
            return ""
        return self.names[int(np.flatnonzero(self.room_ids == room_id)[0])]


def save_room_grid(path: str | Path, grid: RoomGrid) -> Path:
    """Validate ``grid`` and write it to ``path`` atomically (a crash leaves the old file)."""
    path = Path(path)
    grid.validate(path)
    names = grid.names or [""] * len(grid.room_ids)
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        format=np.array(FORMAT),
        version=np.array(VERSION, np.int64),
        labels=grid.labels,
        origin=grid.origin,
        resolution=np.array(grid.resolution, np.float64),
        room_ids=grid.room_ids,
        names=np.array(names, dtype=np.str_).reshape(len(names)),
    )
    return atomic_write_bytes(path, buf.getvalue())


def load_room_grid(path: str | Path) -> RoomGrid:
    """Read and validate a room grid; :class:`RoomGridError` names the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise RoomGridError(path, "no such room grid file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise RoomGridError(path, f"not a readable .npz file ({exc})") from None
    missing = [k for k in KEYS if k not in arrays]
    if missing:
        raise RoomGridError(path, f"missing keys {missing} (expected {list(KEYS)})")
    fmt, version = arrays["format"], arrays["version"]
    if fmt.shape != () or fmt.dtype.kind != "U" or str(fmt) != FORMAT:
        raise RoomGridError(path, f"format: expected {FORMAT!r}, got {fmt!r}")
    if version.shape != () or version.dtype.kind not in "iu" or int(version) != VERSION:
        raise RoomGridError(path, f"version: this build reads version {VERSION}, the file has {version!r}")
    res = arrays["resolution"]
    if res.shape != () or res.dtype.kind != "f":
        raise RoomGridError(path, f"resolution: expected a float scalar, got {res.dtype} {res.shape}")
    origin = arrays["origin"]
    if origin.dtype != np.float64:
        raise RoomGridError(path, f"origin: expected float64, got {origin.dtype}")
    names = arrays["names"]
    if names.ndim != 1 or (names.size and names.dtype.kind != "U"):
        raise RoomGridError(path, f"names: expected an (R,) string array, got {names.dtype} {names.shape}")
    name_list = [str(n) for n in names]
    # The constructor would widen or narrow integer arrays; a file must hold the declared types.
    for key, dtype in (("labels", np.int32), ("room_ids", np.int64)):
        if arrays[key].dtype != dtype:
            raise RoomGridError(path, f"{key}: expected {np.dtype(dtype)}, got {arrays[key].dtype}")
    grid = RoomGrid(
        labels=arrays["labels"],
        origin=origin,
        resolution=float(res),
        room_ids=arrays["room_ids"],
        names=name_list if any(name_list) else [],
    )
    grid.validate(path)
    return grid


__all__ = ["FORMAT", "ROOMS_FILE", "VERSION", "RoomGrid", "RoomGridError", "load_room_grid", "save_room_grid"]
