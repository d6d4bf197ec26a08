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

from shared.datasets.base import DatasetError, SequenceReader
from shared.datasets.files import (
    check_index,
    check_size,
    checked_pose,
    load_intrinsics_json,
    parse_floats,
    read_rgb,
    read_uint16,
    require_dir,
    require_file,
)
from shared.geometry import Intrinsics, Pose
from shared.messages.frames import Frame

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


class ReplicaReader(SequenceReader):
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
        self._numbers = [n for n, _, _ in found]
        self._rgb = [p for _, _, p in found]
        self._depth = [results / f"depth{digits}.png" for _, digits, _ in found]
        for p in self._depth:
            require_file(p, "depth image")
        traj = self.root / "traj.txt"
        self._poses = read_traj(traj)
        if len(self._poses) <= self._numbers[-1]:
            raise DatasetError(
                f"{traj}: {len(self._poses)} poses but the frames go up to number "
                f"{self._numbers[-1]} ({len(found)} frames in {results})"
            )
        self._instances: list[Path] | None = None
        inst_dir = self.root / "instances"
        if inst_dir.is_dir():
            self._instances = [inst_dir / f"instance{digits}.png" for _, digits, _ in found]
        self.intrinsics, self.depth_scale, self._intrinsics_from = self._load_intrinsics()
        log.info(
            "Replica %s: %d frames, intrinsics from %s%s",
            self.root, len(self), self._intrinsics_from, ", with instances" if self._instances else "",
        )  # fmt: skip

    def _load_intrinsics(self) -> tuple[Intrinsics, float, str]:
        path = self.root / "intrinsics.json"
        if path.is_file():
            K, scale = load_intrinsics_json(path)
            return K, scale or REPLICA_DEPTH_SCALE, str(path)
        return REPLICA_INTRINSICS, REPLICA_DEPTH_SCALE, "the Replica defaults"

    def __len__(self) -> int:
        return len(self._rgb)

    def pose(self, i: int) -> Pose:
        pose = self._poses[self._numbers[check_index(i, len(self))]]
        if isinstance(pose, DatasetError):
            raise DatasetError(str(pose))
        return pose

    @property
    def has_instances(self) -> bool:
        """True if the sequence has ground-truth instance images (``instances/``)."""
        return self._instances is not None

    def rgb(self, i: int) -> Annotated[np.ndarray, "(H, W, 3) uint8"]:
        """The colour image of frame ``i`` alone (the ground-truth image index reads no depth)."""
        check_index(i, len(self))
        rgb = read_rgb(self._rgb[i])
        check_size(self._rgb[i], rgb, self.intrinsics.width, self.intrinsics.height, f"the intrinsics' size (from {self._intrinsics_from})")
        return rgb

    def frame(self, i: int) -> Frame:
        check_index(i, len(self))
        pose = self.pose(i)
        K = self.intrinsics
        rgb = self.rgb(i)
        depth = read_uint16(self._depth[i])
        check_size(self._depth[i], depth, K.width, K.height, f"the colour image {self._rgb[i].name}")
        return Frame(
            frame_index=i,
            time_s=self._numbers[i] / NOMINAL_HZ,
            rgb=rgb,
            depth=depth,
            depth_scale=self.depth_scale,
            intrinsics=K,
            T_world_cam=pose,
        )

    def instances(self, i: int) -> Annotated[np.ndarray, "(H, W) int32 object id, -1 = none"] | None:
        check_index(i, len(self))
        if self._instances is None:
            return None
        K = self.intrinsics
        ids = read_uint16(self._instances[i], "instance")
        check_size(self._instances[i], ids, K.width, K.height, f"the colour image {self._rgb[i].name}")
        return ids.astype(np.int32) - 1
