"""The base of the folder readers (Replica, HM3D, TUM, ScanNet++): one colour and one depth
image file per frame, a pose and a time stamp per frame, held in lists the reader fills.

It lives beside :mod:`shared.datasets.base`, not in it, because it reads images through
:mod:`shared.datasets.files`, which itself imports the base's :class:`DatasetError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np

from shared.datasets.base import DatasetError, SequenceReader
from shared.datasets.files import (
    check_index,
    check_size,
    load_intrinsics_json,
    read_rgb,
    read_uint16,
)
from shared.geometry import Intrinsics, Pose
from shared.messages.frames import Frame


def intrinsics_or_default(
    root: Path, default: Intrinsics, default_scale: float, default_from: str
) -> tuple[Intrinsics, float, str]:
    """``root/intrinsics.json`` where there is one (its depth scale, if it gives none, is
    ``default_scale``), else the format's defaults; with where they came from, for messages."""
    path = root / "intrinsics.json"
    if path.is_file():
        K, scale = load_intrinsics_json(path)
        return K, scale or default_scale, str(path)
    return default, default_scale, default_from


class FolderReader(SequenceReader):
    """Frame ``i`` is ``_rgb[i]`` and ``_depth[i]`` at ``_poses[i]`` and ``_times[i]``.

    A pose may be held as the :class:`DatasetError` that made it unusable (a NaN line of
    Replica's ``traj.txt``), so only that frame is refused, when it is read. Colour and depth
    must have the intrinsics' size unless a reader overrides :meth:`rgb` and :meth:`depth`.
    """

    _rgb: list[Path]
    _depth: list[Path]
    _poses: list[Pose | DatasetError]
    _times: list[float]
    _intrinsics_from: str
    """Where the intrinsics came from (a file, or "the ... defaults"), named in size errors."""

    def __len__(self) -> int:
        return len(self._rgb)

    def pose(self, i: int) -> Pose:
        pose = self._poses[check_index(i, len(self))]
        if isinstance(pose, DatasetError):
            raise DatasetError(str(pose))
        return pose

    def rgb(self, i: int) -> Annotated[np.ndarray, "(H, W, 3) uint8"]:
        """The colour image of frame ``i`` alone (the ground-truth image index reads no depth)."""
        path = self._rgb[check_index(i, len(self))]
        return self._sized(path, read_rgb(path), f"the intrinsics' size (from {self._intrinsics_from})")

    def depth(self, i: int) -> Annotated[np.ndarray, "(H, W) uint16"]:
        """The depth image of frame ``i`` in units of ``depth_scale``."""
        path = self._depth[check_index(i, len(self))]
        return self._sized(path, read_uint16(path), f"the colour image {self._rgb[i].name}")

    def _sized(self, path: Path, image: Annotated[np.ndarray, "(H, W, ...)"], against: str) -> np.ndarray:
        """``image`` if it has the intrinsics' size, else a DatasetError naming ``path`` and ``against``."""
        check_size(path, image, self.intrinsics.width, self.intrinsics.height, against)
        return image

    def frame(self, i: int) -> Frame:
        # The pose first: a frame with an unusable pose is refused before its images are read.
        pose = self.pose(i)
        return Frame(
            frame_index=i,
            time_s=self._times[i],
            rgb=self.rgb(i),
            depth=self.depth(i),
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            T_world_cam=pose,
        )
