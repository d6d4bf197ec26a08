"""COLMAP text models (``cameras.txt``, ``images.txt``) as ScanNet++ ships them.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); the project (like OpenCV) puts it
at (0, 0), so principal points are shifted by -0.5 here. Lens distortion is not modelled
downstream: it is dropped with a warning when non-zero.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.datasets.base import DatasetError
from shared.datasets.files import checked_pose, parse_floats, require_file
from shared.geometry import Intrinsics, Pose, invert, pose_from_quat

log = logging.getLogger(__name__)

# model -> (index of fx, fy, cx, cy in PARAMS; fy == fx when both are 0), count of params
_MODELS = {
    "SIMPLE_PINHOLE": ((0, 0, 1, 2), 3),
    "PINHOLE": ((0, 1, 2, 3), 4),
    "SIMPLE_RADIAL": ((0, 0, 1, 2), 4),
    "RADIAL": ((0, 0, 1, 2), 5),
    "OPENCV": ((0, 1, 2, 3), 8),
}


@dataclass(frozen=True)
class ColmapImage:
    name: str
    camera_id: int
    T_world_cam: Pose


def _data_lines(path: Path) -> list[tuple[int, str]]:
    return [(n, line) for n, line in enumerate(path.read_text().splitlines(), start=1)]


def read_cameras(path: Path) -> dict[int, Intrinsics]:
    """Camera id -> pinhole intrinsics in OpenCV pixel convention."""
    require_file(path, "COLMAP cameras.txt")
    cams = {}
    for lineno, line in _data_lines(path):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        where = f"{path}:{lineno}"
        parts = line.split()
        if len(parts) < 4 or parts[1] not in _MODELS:
            model = parts[1] if len(parts) > 1 else "?"
            raise DatasetError(f"{where}: unsupported camera model {model!r} (supported: {', '.join(_MODELS)})")
        (ifx, ify, icx, icy), count = _MODELS[parts[1]]
        values = parse_floats(" ".join(parts[2:]), where)
        if len(values) != 2 + count:
            raise DatasetError(f"{where}: {parts[1]} needs {count} parameters, found {len(values) - 2}")
        width, height, params = int(values[0]), int(values[1]), values[2:]
        distortion = params[max(ifx, ify, icx, icy) + 1 :]
        if any(abs(d) > 1e-9 for d in distortion):
            log.warning("%s: camera %s distortion %s is ignored (pinhole model used)", path, parts[0], distortion)
        try:
            cams[int(parts[0])] = Intrinsics(
                fx=params[ifx], fy=params[ify], cx=params[icx] - 0.5, cy=params[icy] - 0.5, width=width, height=height
            )
        except ValueError as e:
            raise DatasetError(f"{where}: invalid camera ({e})") from None
    if not cams:
        raise DatasetError(f"{path}: no cameras")
    return cams


def read_images(path: Path) -> list[ColmapImage]:
    """Registered images with camera-to-world poses (COLMAP stores world-to-camera)."""
    require_file(path, "COLMAP images.txt")
    images = []
    lines = _data_lines(path)
    k = 0
    while k < len(lines):
        lineno, line = lines[k]
        k += 1
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        # The next line lists the image's 2D points and may be empty: skip it unread.
        k += 1
        where = f"{path}:{lineno}"
        parts = line.split()
        if len(parts) < 10:
            raise DatasetError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        values = parse_floats(" ".join(parts[1:9]), where)
        try:
            T_cam_world = pose_from_quat(np.array(values[4:7]), np.array(values[0:4]))
        except ValueError as e:
            raise DatasetError(f"{where}: invalid quaternion ({e})") from None
        T = checked_pose(invert(checked_pose(T_cam_world, where)), where)
        images.append(ColmapImage(name=" ".join(parts[9:]), camera_id=int(values[7]), T_world_cam=T))
    if not images:
        raise DatasetError(f"{path}: no registered images")
    return images
