"""Replica in the NICE-SLAM layout (also what ``trackgraph synth`` writes).

::

    ROOT/results/frameNNNNNN.jpg       colour (png accepted too)
    ROOT/results/depthNNNNNN.png       uint16 depth, 6553.5 units per metre
    ROOT/traj.txt                      line k: row-major 4x4 camera-to-world of frame k (OpenCV axes)
    ROOT/intrinsics.json               optional {"fx","fy","cx","cy","width","height","depth_scale"}
    ROOT/instances/instanceNNNNNN.png  optional uint16, 0 = no object, id + 1 otherwise

Frame NNNNNN takes line NNNNNN of ``traj.txt``, so a folder with frames removed still lines up.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Annotated

import numpy as np

from shared.datasets.base import DatasetError
from shared.datasets.files import (
    check_index,
    checked_pose,
    parse_floats,
    read_uint16,
    require_dir,
    require_file,
)
from shared.datasets.folder import FolderReader, intrinsics_or_default
from shared.geometry import Intrinsics, Pose

log = logging.getLogger(__name__)

REPLICA_INTRINSICS = Intrinsics(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)
REPLICA_DEPTH_SCALE = 6553.5
NOMINAL_HZ = 30.0
"""Replica renders carry no time stamps; ``time_s`` is the index at this nominal rate."""

_FRAME = re.compile(r"^frame(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)


def read_traj(path: Path) -> list[Pose | DatasetError]:
    """All poses of ``traj.txt``. A line that is not 16 numbers makes the file unreadable (a
    DatasetError naming file and line); a NaN or non-rigid pose is kept as its DatasetError,
    so only that frame is refused when it is read."""
    require_file(path, "trajectory (traj.txt)")
    poses: list[Pose | DatasetError] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        values = parse_floats(line, where)
        if len(values) != 16:
            raise DatasetError(f"{where}: expected 16 numbers (a 4x4 pose), found {len(values)}")
        try:
            poses.append(checked_pose(np.array(values).reshape(4, 4), where))
        except DatasetError as exc:
            poses.append(exc)
    return poses


class ReplicaReader(FolderReader):
    """Replica / synthetic sequences; see the module docstring for the layout."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        results = require_dir(self.root / "results", "Replica results")
        found = sorted(
            (int(m.group(1)), m.group(1), p)
            for p in results.iterdir()
            if (m := _FRAME.match(p.name))
        )
        if not found:
            raise DatasetError(f"{results}: no frameNNNNNN.jpg colour images")
        numbers = [n for n, _, _ in found]
        self._rgb = [p for _, _, p in found]
        self._depth = [results / f"depth{digits}.png" for _, digits, _ in found]
        for p in self._depth:
            require_file(p, "depth image")
        traj = self.root / "traj.txt"
        poses = read_traj(traj)
        if len(poses) <= numbers[-1]:
            raise DatasetError(
                f"{traj}: {len(poses)} poses but the frames go up to number "
                f"{numbers[-1]} ({len(found)} frames in {results})"
            )
        self._poses = [poses[n] for n in numbers]
        self._times = [n / NOMINAL_HZ for n in numbers]
        self._instances: list[Path] | None = None
        inst_dir = self.root / "instances"
        if inst_dir.is_dir():
            self._instances = [inst_dir / f"instance{digits}.png" for _, digits, _ in found]
        self.intrinsics, self.depth_scale, self._intrinsics_from = intrinsics_or_default(
            self.root, REPLICA_INTRINSICS, REPLICA_DEPTH_SCALE, "the Replica defaults"
        )
        log.info(
            "Replica %s: %d frames, intrinsics from %s%s",
            self.root, len(self), self._intrinsics_from, ", with instances" if self._instances else "",
        )  # fmt: skip

    @property
    def has_instances(self) -> bool:
        """True if the sequence has ground-truth instance images (``instances/``)."""
        return self._instances is not None

    def instances(self, i: int) -> Annotated[np.ndarray, "(H, W) int32 object id, -1 = none"] | None:
        check_index(i, len(self))
        if self._instances is None:
            return None
        path = self._instances[i]
        ids = self._sized(path, read_uint16(path, "instance"), f"the colour image {self._rgb[i].name}")
        return ids.astype(np.int32) - 1
