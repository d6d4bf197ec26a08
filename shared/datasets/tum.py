"""TUM RGB-D sequences.

::

    ROOT/rgb.txt, ROOT/depth.txt  "timestamp filename" per line, '#' comments
    ROOT/groundtruth.txt          "timestamp tx ty tz qx qy qz qw" (quaternion scalar LAST),
                                  camera-to-world of the colour camera's optical centre
    ROOT/intrinsics.json          optional, same keys as for Replica

Colour and depth are paired one-to-one by nearest time stamp within ``max_time_diff_s``, the
rule of TUM's ``associate.py``. The pose is the ground-truth sample nearest to the colour stamp
within the same limit (not interpolated: at 100 Hz the nearest sample is within 5 ms).
Frames missing either are skipped and counted in the log.

TUM's three sensors have different calibrations and folder names are not a reliable guide,
so without ``intrinsics.json`` the freiburg1 calibration is used (with a warning when the
folder name says otherwise).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from shared.config.source import TumConfig
from shared.datasets.base import DatasetError
from shared.datasets.files import checked_pose, parse_floats, require_file
from shared.datasets.folder import FolderReader, intrinsics_or_default
from shared.datasets.timestamps import associate, nearest
from shared.geometry import Intrinsics, Pose, pose_from_quat

log = logging.getLogger(__name__)

TUM_FR1_INTRINSICS = Intrinsics(fx=517.3, fy=516.5, cx=318.6, cy=255.3, width=640, height=480)
TUM_DEPTH_SCALE = 5000.0


def _data_lines(path: Path, what: str) -> list[tuple[str, list[str]]]:
    require_file(path, what)
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if line.strip() and not line.lstrip().startswith("#"):
            out.append((f"{path}:{lineno}", line.split()))
    return out


def read_file_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    """Stamps (seconds) and files (relative to the list's folder) of rgb.txt / depth.txt."""
    stamps, files = [], []
    for where, parts in _data_lines(path, "TUM file list"):
        if len(parts) < 2:
            raise DatasetError(f"{where}: expected 'timestamp filename'")
        stamps.append(parse_floats(parts[0], where)[0])
        files.append(path.parent / parts[1])
    return np.array(stamps, dtype=np.float64), files


def read_groundtruth(path: Path) -> tuple[np.ndarray, list[Pose]]:
    """Stamps sorted in time, and camera-to-world poses."""
    rows = []
    for where, parts in _data_lines(path, "TUM ground truth (groundtruth.txt)"):
        values = parse_floats(" ".join(parts), where)
        if len(values) != 8:
            raise DatasetError(f"{where}: expected 'timestamp tx ty tz qx qy qz qw', found {len(values)} numbers")
        t, tx, ty, tz, qx, qy, qz, qw = values
        try:
            T = pose_from_quat(np.array([tx, ty, tz]), np.array([qw, qx, qy, qz]))
        except ValueError as e:
            raise DatasetError(f"{where}: invalid quaternion ({e})") from None
        rows.append((t, checked_pose(T, where)))
    rows.sort(key=lambda r: r[0])
    return np.array([r[0] for r in rows], dtype=np.float64), [r[1] for r in rows]


class TumReader(FolderReader):
    """TUM RGB-D sequence; see the module docstring for association and intrinsics."""

    options = "tum"

    def __init__(self, root: Path | str, config: TumConfig | None = None) -> None:
        self.root = Path(root)
        max_dt = (config or TumConfig()).max_time_diff_s
        rgb_t, rgb_files = read_file_list(self.root / "rgb.txt")
        depth_t, depth_files = read_file_list(self.root / "depth.txt")
        gt_t, gt_poses = read_groundtruth(self.root / "groundtruth.txt")
        pairs = associate(rgb_t, depth_t, max_dt)
        pose_k = nearest(np.array([rgb_t[i] for i, _ in pairs]), gt_t, max_dt)
        kept = [(i, j, int(k)) for (i, j), k in zip(pairs, pose_k, strict=True) if k >= 0]
        n_no_depth, n_no_pose = len(rgb_t) - len(pairs), len(pairs) - len(kept)
        if n_no_depth or n_no_pose:
            log.warning(
                "TUM %s: skipped %d of %d colour frames (%d without depth, %d without ground truth within %.3f s)",
                self.root, n_no_depth + n_no_pose, len(rgb_t), n_no_depth, n_no_pose, max_dt,
            )  # fmt: skip
        if not kept:
            raise DatasetError(
                f"{self.root / 'rgb.txt'}: no colour frame has both a depth image ({self.root / 'depth.txt'}) "
                f"and a ground-truth pose ({self.root / 'groundtruth.txt'}) within {max_dt} s"
            )
        self._rgb = [rgb_files[i] for i, _, _ in kept]
        self._depth = [depth_files[j] for _, j, _ in kept]
        self._times = [float(rgb_t[i]) for i, _, _ in kept]
        self._poses = [gt_poses[k] for _, _, k in kept]
        self.intrinsics, self.depth_scale, self._intrinsics_from = self._load_intrinsics()
        log.info("TUM %s: %d frames, intrinsics from %s", self.root, len(self), self._intrinsics_from)

    def _load_intrinsics(self) -> tuple[Intrinsics, float, str]:
        named = any(tag in self.root.name.lower() for tag in ("freiburg2", "freiburg3", "fr2", "fr3"))
        if named and not (self.root / "intrinsics.json").is_file():
            log.warning(
                "TUM %s: the name suggests another sensor than freiburg1, but without intrinsics.json "
                "the freiburg1 calibration is used", self.root,
            )  # fmt: skip
        return intrinsics_or_default(self.root, TUM_FR1_INTRINSICS, TUM_DEPTH_SCALE, "the TUM freiburg1 defaults")
