"""A small ray-cast RGB-D room (floor, two walls, boxes) with ground-truth instances, so the
segmenter tests need neither the synthetic generator nor any weights. (A module with a unique
name rather than conftest.py: test folders have no __init__.py, and several hold a conftest.)"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.datasets.ground_truth import StaticGroundTruth
from shared.geometry import Intrinsics
from shared.perception import KeyframeImage

# (min corner, max corner, RGB) in the camera frame: x right, y down, z forward; floor at y = 1.2.
BOXES = [
    ((-1.2, 0.4, 2.2), (-0.5, 1.2, 2.8), (180, 60, 50)),
    ((0.3, 0.7, 1.8), (0.8, 1.2, 2.2), (60, 90, 170)),
    ((0.9, -0.2, 3.6), (1.8, 1.2, 4.2), (200, 180, 90)),
    ((-0.3, 0.9, 3.0), (0.2, 1.2, 3.4), (70, 150, 80)),
    ((0.45, 0.45, 1.9), (0.7, 0.7, 2.1), (230, 230, 230)),  # standing on box 1
]
STRUCTURE = [(150, 140, 130), (200, 195, 185), (170, 175, 190)]  # floor, back wall, left wall


@dataclass(frozen=True)
class RoomImage(KeyframeImage):
    """The rendered keyframe and, for scoring and for the simulated segmenter's
    :func:`truth`, its ground-truth ids (which no KeyframeImage carries)."""

    instances: np.ndarray | None = None


def truth(room: RoomImage, frames: int = 32) -> StaticGroundTruth:
    """The room's ids as the ground truth of frames 0 to ``frames - 1``."""
    return StaticGroundTruth({i: room.instances for i in range(frames)})


def _box_hits(d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slab test of rays from the origin: entry distance (inf if missed) and the entry axis."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = lo / d
        t2 = hi / d
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    enter = np.nanmax(tmin, axis=-1)
    leave = np.nanmin(tmax, axis=-1)
    hit = (leave >= enter) & (enter > 0)
    return np.where(hit, enter, np.inf), np.nanargmax(tmin, axis=-1)


def render_room(width: int = 320, height: int = 240, seed: int = 0, frame_index: int = 0) -> RoomImage:
    f = width / 2 / np.tan(np.radians(35))
    K = Intrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height)
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], axis=-1)
    with np.errstate(divide="ignore"):
        planes = [
            np.where(d[..., 1] > 0, 1.2 / d[..., 1], np.inf),
            np.full(d.shape[:2], 4.5),
            np.where(d[..., 0] < 0, -2.5 / d[..., 0], np.inf),
        ]
    normals = [np.array([0, -1.0, 0]), np.array([0, 0, -1.0]), np.array([1.0, 0, 0])]
    t = np.stack(planes + [np.full(d.shape[:2], np.inf)] * len(BOXES))
    normal = np.zeros((*d.shape[:2], len(planes) + len(BOXES), 3))
    for i, n in enumerate(normals):
        normal[:, :, i] = n
    for j, (lo, hi, _) in enumerate(BOXES):
        tj, axis = _box_hits(d, np.array(lo), np.array(hi))
        t[len(planes) + j] = tj
        n = np.zeros((*d.shape[:2], 3))
        np.put_along_axis(n, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None], -1)), -1)
        normal[:, :, len(planes) + j] = n
    inst = np.argmin(t, axis=0).astype(np.int32)
    depth = np.take_along_axis(t, inst[None], 0)[0].astype(np.float32)
    n = np.take_along_axis(normal, inst[:, :, None, None], 2)[:, :, 0]
    base = np.array(STRUCTURE + [b[2] for b in BOXES], float)[inst]
    light = np.array([0.4, -0.8, -0.45])
    light /= np.linalg.norm(light)
    shade = 0.55 + 0.45 * np.clip(n @ light, 0, 1)
    rng = np.random.default_rng(seed)
    rgb = base * shade[..., None] + rng.normal(0, 3.0, base.shape)
    rgb = np.clip(rgb, 0, 255).astype(np.uint8)
    return RoomImage(frame_index=frame_index, rgb=rgb, depth_m=depth, intrinsics=K, instances=inst)
