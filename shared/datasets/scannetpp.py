"""ScanNet++ iPhone sequences.

::

    SCENE/iphone/rgb/frame_NNNNNN.jpg    colour, 1920x1440
    SCENE/iphone/depth/frame_NNNNNN.png  uint16 depth in millimetres, usually 256x192
    SCENE/iphone/colmap/cameras.txt      PINHOLE / OPENCV intrinsics of the colour camera
    SCENE/iphone/colmap/images.txt       world-to-camera poses, quaternion w first

The frames are the images registered in ``images.txt`` (a subset of the extracted video).
Colour and depth differ in resolution. By default (``resize_to="depth"``) the colour image is
area-averaged down to the depth size and the intrinsics scaled to match: depth is never
invented, and a 256x192 frame is 56 times lighter to carry through the pipeline. With
``resize_to="rgb"`` depth is upsampled by nearest neighbour (no blending across object edges)
and the colour keeps its full resolution.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from PIL import Image

from shared.datasets.base import DatasetError
from shared.datasets.colmap import read_cameras, read_images
from shared.datasets.files import (
    check_index,
    check_size,
    image_size,
    natural_key,
    read_rgb,
    read_uint16,
    require_dir,
    require_file,
)
from shared.datasets.folder import FolderReader

log = logging.getLogger(__name__)

SCANNETPP_DEPTH_SCALE = 1000.0
VIDEO_HZ = 60.0
"""iPhone capture rate; frame_NNNNNN is video frame NNNNNN, hence ``time_s``."""

_NUMBER = re.compile(r"(\d+)")


def upsample_nearest(
    depth: Annotated[np.ndarray, "(h, w)"], width: int, height: int
) -> Annotated[np.ndarray, "(height, width)"]:
    """Nearest-neighbour resize matching pixel centres (the same mapping as Intrinsics.scaled)."""
    h, w = depth.shape
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return depth[rows[:, None], cols[None, :]]


def _iphone_dir(root: Path) -> Path:
    """Accept the scene folder or its ``iphone`` folder."""
    return root / "iphone" if (root / "iphone").is_dir() else root


class ScanNetppReader(FolderReader):
    """ScanNet++ iPhone sequence; see the module docstring for layout and resizing."""

    def __init__(self, root: Path | str, resize_to: Literal["depth", "rgb"] = "depth") -> None:
        if resize_to not in ("depth", "rgb"):
            raise ValueError(f"resize_to must be 'depth' or 'rgb', got {resize_to!r}")
        self.root = Path(root)
        self.resize_to = resize_to
        iphone = _iphone_dir(self.root)
        rgb_dir = require_dir(iphone / "rgb", "ScanNet++ iPhone colour (iphone/rgb)")
        depth_dir = require_dir(iphone / "depth", "ScanNet++ iPhone depth (iphone/depth)")
        colmap = require_dir(iphone / "colmap", "ScanNet++ iPhone COLMAP (iphone/colmap)")
        cams = read_cameras(colmap / "cameras.txt")
        images_txt = colmap / "images.txt"
        images = sorted(read_images(images_txt), key=lambda im: natural_key(Path(im.name)))
        used = {im.camera_id for im in images}
        if missing := used - cams.keys():
            raise DatasetError(f"{images_txt}: camera ids {sorted(missing)} are not in {colmap / 'cameras.txt'}")
        if len(used) > 1:
            raise DatasetError(f"{images_txt}: images use {len(used)} cameras; the iPhone sequence has one")
        self._rgb_intrinsics = cams[used.pop()]
        self._rgb = [require_file(rgb_dir / im.name, "colour image") for im in images]
        self._depth = [require_file(depth_dir / f"{Path(im.name).stem}.png", "depth image") for im in images]
        self._poses = [im.T_world_cam for im in images]
        self._times = [self._time(im.name, k) for k, im in enumerate(images)]
        self._depth_size = self._check_depth_size()
        K = self._rgb_intrinsics
        if resize_to == "depth" and self._depth_size != (K.width, K.height):
            K = K.scaled(*self._depth_size)
        self.intrinsics = K
        self.depth_scale = SCANNETPP_DEPTH_SCALE
        log.info(
            "ScanNet++ %s: %d registered frames, colour %dx%d, depth %dx%d, frames at %dx%d",
            self.root, len(self), self._rgb_intrinsics.width, self._rgb_intrinsics.height,
            *self._depth_size, K.width, K.height,
        )  # fmt: skip

    @staticmethod
    def _time(name: str, k: int) -> float:
        digits = _NUMBER.findall(name)
        return int(digits[-1]) / VIDEO_HZ if digits else k / VIDEO_HZ

    def _check_depth_size(self) -> tuple[int, int]:
        wd, hd = image_size(self._depth[0])
        K = self._rgb_intrinsics
        if wd * K.height != hd * K.width:
            raise DatasetError(
                f"{self._depth[0]}: depth is {wd}x{hd}, not the aspect ratio of the {K.width}x{K.height} colour camera"
            )
        return wd, hd

    def rgb(self, i: int) -> Annotated[np.ndarray, "(H, W, 3) uint8"]:
        check_index(i, len(self))
        Kc, K = self._rgb_intrinsics, self.intrinsics
        rgb = read_rgb(self._rgb[i])
        check_size(self._rgb[i], rgb, Kc.width, Kc.height, "the COLMAP camera in cameras.txt")
        if rgb.shape[:2] != (K.height, K.width):
            rgb = np.array(Image.fromarray(rgb).resize((K.width, K.height), Image.Resampling.BOX))
        return rgb

    def depth(self, i: int) -> Annotated[np.ndarray, "(H, W) uint16"]:
        check_index(i, len(self))
        (wd, hd), K = self._depth_size, self.intrinsics
        depth = read_uint16(self._depth[i])
        check_size(self._depth[i], depth, wd, hd, f"the sequence's depth size (from {self._depth[0].name})")
        if depth.shape != (K.height, K.width):
            depth = upsample_nearest(depth, K.width, K.height)
        return depth
