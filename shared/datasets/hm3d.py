"""HM3D walks as used by the OpenLex3D baselines (HOV-SG export).

::

    ROOT/rgb/*.png      colour, 1080x720
    ROOT/depth/*.png    uint16 depth in millimetres
    ROOT/pose/*.txt     16 numbers: row-major 4x4 camera-to-world in OpenGL camera axes
    ROOT/intrinsics.json  optional override, same keys as for Replica

The three folders are paired by natural sort order (names are not zero-padded, and differ
between folders in some exports), as the baselines do. Habitat renders an ideal pinhole with a
90 degree horizontal field of view, so f = W / 2 = 540; its pixel centres sit at half-integers
of the image plane, which in OpenCV's integer-centre convention puts the principal point at
((W - 1) / 2, (H - 1) / 2) = (539.5, 359.5).
"""

from __future__ import annotations

import logging
from pathlib import Path

from shared.datasets.base import DatasetError
from shared.datasets.files import checked_pose, natural_key, read_pose_file, require_dir
from shared.datasets.folder import FolderReader, intrinsics_or_default
from shared.geometry import OPENGL_TO_OPENCV, Intrinsics

log = logging.getLogger(__name__)

HM3D_INTRINSICS = Intrinsics(fx=540.0, fy=540.0, cx=539.5, cy=359.5, width=1080, height=720)
HM3D_DEPTH_SCALE = 1000.0
NOMINAL_HZ = 30.0
"""The walks carry no time stamps; ``time_s`` is the index at this nominal rate."""


def _listing(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in suffixes), key=natural_key)


class Hm3dReader(FolderReader):
    """HM3D walk folder; see the module docstring for the layout."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        rgb_dir = require_dir(self.root / "rgb", "HM3D colour (rgb)")
        depth_dir = require_dir(self.root / "depth", "HM3D depth")
        pose_dir = require_dir(self.root / "pose", "HM3D pose")
        self._rgb = _listing(rgb_dir, (".png", ".jpg", ".jpeg"))
        self._depth = _listing(depth_dir, (".png",))
        pose_files = _listing(pose_dir, (".txt",))
        if not self._rgb:
            raise DatasetError(f"{rgb_dir}: no colour images")
        if len(self._depth) != len(self._rgb):
            raise DatasetError(f"{depth_dir}: {len(self._depth)} depth images for {len(self._rgb)} colour images in {rgb_dir}")
        if len(pose_files) < len(self._rgb):
            raise DatasetError(f"{pose_dir}: {len(pose_files)} poses for {len(self._rgb)} frames")
        self._poses = [
            checked_pose(read_pose_file(p) @ OPENGL_TO_OPENCV, str(p)) for p in pose_files[: len(self._rgb)]
        ]
        self._times = [i / NOMINAL_HZ for i in range(len(self._rgb))]
        self.intrinsics, self.depth_scale, self._intrinsics_from = intrinsics_or_default(
            self.root, HM3D_INTRINSICS, HM3D_DEPTH_SCALE, "the HM3D defaults"
        )
        log.info("HM3D %s: %d frames, intrinsics from %s", self.root, len(self), self._intrinsics_from)
