"""Pose corrections from a pose-graph back end (``poses/correction``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from shared.arrays import ArraySpec
from shared.geometry import is_rigid
from shared.messages.base import Message, Units, register

FrameIndices = Annotated[np.ndarray, ArraySpec(("int64",), (None,))]
Poses4 = Annotated[np.ndarray, ArraySpec(("float64",), (None, 4, 4))]


@register
class PoseCorrection(Message):
    """Corrected camera poses of past frames, as a SLAM back end publishes them after a loop
    closure. Corrections are absolute: they state poses, not deltas, so one applied twice
    moves nothing the second time, and one older than the newest applied is refused."""

    correction_id: int = Field(ge=0)
    """Grows with each correction the back end sends; fusion refuses an id below the newest it
    applied (an older correction after a newer one), and ignores the same id sent again."""
    frame_index: int = Field(ge=0)
    """The frame the poses are valid up to (the loop closure). Frames fused after it follow
    the corrected pose of the last listed frame by their own odometry (a map -> odom fix)."""
    frames: FrameIndices
    """(N,) int64 frame indices, strictly increasing, none past ``frame_index``. Frames of the
    map between two listed ones follow the nearer listed one by their odometry."""
    poses: Annotated[Poses4, Units("m (translation)")]
    """(N, 4, 4) float64 corrected camera-to-world poses (``T_world_cam``), one per frame."""
    apply_after_frame: int | None = Field(None, ge=0)
    """Fusion holds the correction until it has fused this frame, so a replay gives the same
    map every time (``trackgraph map --corrections``, the source's replay). None: applied on
    arrival, as from a live back end."""

    @field_validator("frames")
    @classmethod
    def _increasing(cls, v: np.ndarray) -> np.ndarray:
        """``frames`` is not empty, non-negative and strictly increasing."""
        if len(v) == 0:
            raise ValueError("a correction lists at least one frame")
        if int(v.min()) < 0 or np.any(np.diff(v) <= 0):
            raise ValueError("frames must be non-negative and strictly increasing")
        return v

    @field_validator("poses")
    @classmethod
    def _rigid(cls, v: np.ndarray) -> np.ndarray:
        """Every pose is finite and rigid (orthonormal rotation, determinant 1, last row 0 0 0 1, within 1e-3)."""
        if not np.all(np.isfinite(v)):
            bad = int(np.flatnonzero(~np.isfinite(v).reshape(len(v), -1).all(axis=1))[0])
            raise ValueError(f"pose {bad} is not finite (NaN or inf)")
        for k, T in enumerate(v):
            if not is_rigid(T):
                raise ValueError(f"pose {k} is not a rigid transform")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> PoseCorrection:
        """One pose per frame, and no frame past ``frame_index``."""
        if len(self.poses) != len(self.frames):
            raise ValueError(f"{len(self.frames)} frames but {len(self.poses)} poses")
        if int(self.frames[-1]) > self.frame_index:
            raise ValueError(f"frame {int(self.frames[-1])} is past frame_index {self.frame_index}")
        return self

    def to_json(self) -> str:
        """One line of a corrections file (:func:`read_corrections`)."""
        body = {
            "correction_id": self.correction_id,
            "frame_index": self.frame_index,
            "frames": self.frames.tolist(),
            "poses": [[float(x) for x in T.reshape(-1)] for T in self.poses],
        }
        if self.apply_after_frame is not None:
            body["apply_after_frame"] = self.apply_after_frame
        return json.dumps(body, separators=(",", ":"))


class CorrectionsFileError(ValueError):
    """A corrections file that cannot be read; the message names the file and the line."""


def parse_correction(obj: dict) -> PoseCorrection:
    """A correction from its JSON form: ``poses`` as N rows of 16 row-major values (or N
    nested 4x4 lists)."""
    data = dict(obj)
    poses = np.asarray(data.get("poses", []), dtype=np.float64)
    if poses.ndim == 2 and poses.shape[1] == 16:
        poses = poses.reshape(-1, 4, 4)
    data["poses"] = poses
    data["frames"] = np.asarray(data.get("frames", []), dtype=np.int64)
    return PoseCorrection.model_validate(data)


def read_corrections(path: str | Path) -> list[PoseCorrection]:
    """Every correction of a JSON-lines file (one :class:`PoseCorrection` per line, blank
    lines skipped), in file order."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CorrectionsFileError(f"{path}: cannot read the corrections file ({exc.strerror or exc})") from exc
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            if not isinstance(obj, dict):
                raise ValueError("expected a JSON object")
            out.append(parse_correction(obj))
        except (ValueError, ValidationError, TypeError) as exc:
            first = str(exc).strip().splitlines()
            why = exc.errors()[0]["msg"] if isinstance(exc, ValidationError) and exc.errors() else (first[0] if first else type(exc).__name__)
            where = ".".join(str(p) for p in exc.errors()[0]["loc"]) if isinstance(exc, ValidationError) and exc.errors() else ""
            raise CorrectionsFileError(f"{path}:{n}: bad correction{' (' + where + ')' if where else ''}: {why}") from exc
    return out
