"""Pinhole intrinsics, SE(3) poses, projection and back-projection (vectorised, OpenCV axes:
x right, y down, z forward)."""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

Pose = Annotated[np.ndarray, "(4, 4) float64 rigid transform"]
Points = Annotated[np.ndarray, "(N, 3) float"]
Pixels = Annotated[np.ndarray, "(N, 2) float (u, v)"]


class Intrinsics(BaseModel):
    """Pinhole camera: focal lengths and principal point in pixels, and the image size."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    fx: float = Field(gt=0)
    """Focal length along x (pixels)."""
    fy: float = Field(gt=0)
    """Focal length along y (pixels)."""
    cx: float
    """Principal point x (pixels)."""
    cy: float
    """Principal point y (pixels)."""
    width: int = Field(gt=0, le=65536)
    """Image width (pixels)."""
    height: int = Field(gt=0, le=65536)
    """Image height (pixels)."""

    @field_validator("fx", "fy", "cx", "cy")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("must be finite")
        return v

    def matrix(self) -> Annotated[np.ndarray, "(3, 3) float64"]:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    def strided(self, step: int) -> Intrinsics:
        """The camera of ``image[::step, ::step]``: its pixel (u, v) is this camera's pixel
        (step u, step v)."""
        return Intrinsics(
            fx=self.fx / step,
            fy=self.fy / step,
            cx=self.cx / step,
            cy=self.cy / step,
            width=-(-self.width // step),
            height=-(-self.height // step),
        )

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=width,
            height=height,
        )


def pixel_stride(stride: int | str, width: int) -> int:
    """A ``pixel_stride`` setting (a number, or ``auto``: about 640 pixels across) for an
    image ``width`` pixels wide."""
    if stride == "auto":
        return max(1, round(width / 640))
    return int(stride)


def is_rigid(T: Pose, tol: float = 1e-3) -> bool:
    """True if T is a finite 4x4 rotation + translation with last row (0, 0, 0, 1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(T[3], [0, 0, 0, 1], atol=tol)
        and np.allclose(R @ R.T, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
    )


def invert(T: Pose) -> Pose:
    """Inverse of a rigid transform, without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4, dtype=np.float64)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def transform(T: Pose, points: Points) -> Points:
    """Apply T to each row of ``points``."""
    return points @ T[:3, :3].T + T[:3, 3]


def project(K: Intrinsics, points_cam: Points) -> tuple[Pixels, Annotated[np.ndarray, "(N,) z"]]:
    """Camera-frame points to pixel coordinates (u, v) and depth z. Points with z <= 0 get NaN."""
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(z > 0, 1.0 / z, np.nan)
    u = points_cam[:, 0] * inv * K.fx + K.cx
    v = points_cam[:, 1] * inv * K.fy + K.cy
    return np.stack([u, v], axis=1), z


def backproject(
    K: Intrinsics, depth_m: Annotated[np.ndarray, "(H, W) float metres"]
) -> Annotated[np.ndarray, "(H, W, 3) float camera-frame points"]:
    """Each pixel's 3D point in the camera frame; zero depth gives a zero point."""
    h, w = depth_m.shape
    if (w, h) != (K.width, K.height):
        raise ValueError(f"depth is {w}x{h} but intrinsics are for {K.width}x{K.height}")
    u = np.arange(w, dtype=np.float64)
    v = np.arange(h, dtype=np.float64)
    x = (u[None, :] - K.cx) / K.fx * depth_m
    y = (v[:, None] - K.cy) / K.fy * depth_m
    return np.stack([x, y, depth_m.astype(np.float64)], axis=-1)


def quat_to_matrix(q_wxyz: Annotated[np.ndarray, "(4,) w, x, y, z"]) -> Annotated[np.ndarray, "(3, 3)"]:
    """Rotation matrix of a (not necessarily unit) quaternion, scalar first."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {q.tolist()} has zero or non-finite norm")
    w, x, y, z = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_from_quat(
    t_xyz: Annotated[np.ndarray, "(3,)"], q_wxyz: Annotated[np.ndarray, "(4,) w, x, y, z"]
) -> Pose:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q_wxyz)
    T[:3, 3] = t_xyz
    return T


def matrix_to_quat(R: Annotated[np.ndarray, "(3, 3) rotation"]) -> Annotated[np.ndarray, "(4,) w, x, y, z unit, w >= 0"]:
    """Unit quaternion of a rotation matrix (Shepperd's method: the largest of the four
    squared components is taken first, so no division is by a small number)."""
    m = np.asarray(R, np.float64)
    tr = np.trace(m)
    d = np.array([tr, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(d))
    if k == 0:
        w = 0.5 * np.sqrt(max(1.0 + tr, 0.0))
        q = np.array([w, (m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w)])
    else:
        i, j, n = (k - 1), k % 3, (k + 1) % 3
        v = np.zeros(3)
        v[i] = 0.5 * np.sqrt(max(1.0 + 2 * m[i, i] - tr, 0.0))
        v[j] = (m[j, i] + m[i, j]) / (4 * v[i])
        v[n] = (m[n, i] + m[i, n]) / (4 * v[i])
        w = (m[n, j] - m[j, n]) / (4 * v[i])
        q = np.array([w, *v])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def pose_row(T: Pose) -> Annotated[np.ndarray, "(7,) x y z qx qy qz qw"]:
    """A pose as translation and scalar-last unit quaternion (the ROS / spark_dsg order)."""
    q = matrix_to_quat(np.asarray(T, np.float64)[:3, :3])
    return np.array([*np.asarray(T, np.float64)[:3, 3], q[1], q[2], q[3], q[0]])


def pose_from_row(row: Annotated[np.ndarray, "(7,) x y z qx qy qz qw"]) -> Pose:
    """The inverse of :func:`pose_row`."""
    r = np.asarray(row, np.float64).reshape(7)
    return pose_from_quat(r[:3], np.array([r[6], r[3], r[4], r[5]]))


OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiply a camera-to-world pose in OpenGL axes (y up, z back) to get OpenCV axes."""
