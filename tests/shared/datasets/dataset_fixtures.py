"""One tiny RGB-D scene, written out in every folder layout exactly as the real datasets do.

Every reader must give back the same poses and the same 3D points from the same content.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from shared.geometry import OPENGL_TO_OPENCV, Intrinsics, invert

N, W, H = 5, 32, 24
T0 = 1305031102.175304  # a TUM-like epoch stamp, to exercise float precision of stamps


@dataclass
class Scene:
    rgb: np.ndarray  # (N, H, W, 3) uint8
    depth_m: np.ndarray  # (N, H, W) float64 metres, 0 = hole
    poses: np.ndarray  # (N, 4, 4) camera-to-world, OpenCV axes
    K: Intrinsics
    times: np.ndarray  # (N,) seconds


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * S + (1 - np.cos(angle)) * S @ S


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, w >= 0."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2 * np.sqrt(tr + 1)
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def make_scene() -> Scene:
    u = np.arange(W)[None, :]
    v = np.arange(H)[:, None]
    rgb, depth, poses = [], [], []
    for i in range(N):
        img = np.zeros((H, W, 3), np.uint8)
        img[..., 0] = 6 * u + 10
        img[..., 1] = 8 * v + 5
        img[..., 2] = 30 * i + 40
        rgb.append(img)
        d = 2.0 + 0.02 * u - 0.015 * v + 0.1 * i
        d[6:15, 10:21] = 1.3 + 0.05 * i  # a box in front of the wall
        d[0, 0] = d[H - 1, W - 1] = 0.0  # holes: no reading
        depth.append(d)
        T = np.eye(4)
        T[:3, :3] = rotation([0.2, 1.0, 0.1 * i], 0.3 * i + 0.1)
        T[:3, 3] = [0.5 * i, -0.2 * i + 1.0, 0.1 * i * i]
        poses.append(T)
    K = Intrinsics(fx=28.0, fy=27.0, cx=15.3, cy=11.7, width=W, height=H)
    return Scene(np.stack(rgb), np.stack(depth), np.stack(poses), K, T0 + np.arange(N) / 30.0)


def quantize(depth_m: np.ndarray, scale: float) -> np.ndarray:
    return np.rint(depth_m * scale).astype(np.uint16)


def save_png16(path: Path, a: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a.astype(np.uint16)).save(path)


def save_rgb(path: Path, a: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a).save(path, quality=95) if path.suffix == ".jpg" else Image.fromarray(a).save(path)


def intrinsics_json(path: Path, K: Intrinsics, depth_scale: float | None = None) -> None:
    data = K.model_dump()
    if depth_scale is not None:
        data["depth_scale"] = depth_scale
    path.write_text(json.dumps(data))


def row(values: np.ndarray) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(values))


# -- writers, one per layout -------------------------------------------------------------------


def write_replica(s: Scene, root: Path, *, with_intrinsics: bool = True, instances: np.ndarray | None = None) -> Path:
    for i in range(N):
        save_rgb(root / "results" / f"frame{i:06d}.jpg", s.rgb[i])
        save_png16(root / "results" / f"depth{i:06d}.png", quantize(s.depth_m[i], 6553.5))
        if instances is not None:
            save_png16(root / "instances" / f"instance{i:06d}.png", instances[i] + 1)
    (root / "traj.txt").write_text("".join(row(T) + "\n" for T in s.poses))
    if with_intrinsics:
        intrinsics_json(root / "intrinsics.json", s.K, 6553.5)
    return root


def write_scannetpp(s: Scene, root: Path) -> Path:
    """Colour at twice the depth resolution, COLMAP world-to-camera poses, registered subset."""
    ip = root / "iphone"
    K2 = s.K.scaled(2 * W, 2 * H)
    names = [f"frame_{10 * i:06d}" for i in range(N)]  # every 10th video frame registered
    for i, name in enumerate(names):
        save_rgb(ip / "rgb" / f"{name}.jpg", np.repeat(np.repeat(s.rgb[i], 2, axis=0), 2, axis=1))
        save_png16(ip / "depth" / f"{name}.png", quantize(s.depth_m[i], 1000.0))
    save_rgb(ip / "rgb" / "frame_000005.jpg", s.rgb[0])  # extracted but not registered: ignored
    (ip / "colmap").mkdir(parents=True)
    # COLMAP puts the first pixel centre at (0.5, 0.5): principal point + 0.5.
    (ip / "colmap" / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 OPENCV {2 * W} {2 * H} {K2.fx!r} {K2.fy!r} {K2.cx + 0.5!r} {K2.cy + 0.5!r} 0 0 0 0\n"
    )
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
    for i in reversed(range(N)):  # listed out of order, as COLMAP does
        Tcw = invert(s.poses[i])
        lines.append(f"{i + 1} {row(matrix_to_quat(Tcw[:3, :3]))} {row(Tcw[:3, 3])} 1 {names[i]}.jpg")
        lines.append("" if i % 2 else "12.5 3.25 -1 40.0 7.0 12")  # 2D points, sometimes none
    (ip / "colmap" / "images.txt").write_text("\n".join(lines) + "\n")
    return root


def write_hm3d(s: Scene, root: Path, *, with_intrinsics: bool = True) -> Path:
    """Names not zero-padded (0, 5, 10, ...): only a natural sort keeps them in order."""
    for i in range(N):
        save_rgb(root / "rgb" / f"{5 * i}.png", s.rgb[i])
        save_png16(root / "depth" / f"{5 * i}.png", quantize(s.depth_m[i], 1000.0))
        (root / "pose").mkdir(exist_ok=True)
        (root / "pose" / f"{5 * i}.txt").write_text(row(s.poses[i] @ OPENGL_TO_OPENCV) + "\n")
    if with_intrinsics:
        intrinsics_json(root / "intrinsics.json", s.K)
    return root


def write_tum(s: Scene, root: Path, *, with_intrinsics: bool = True) -> Path:
    """Depth stamps jittered by a few ms; one extra colour frame without depth (skipped)."""
    rgb_lines = ["# color images", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    jitter = [0.004, -0.006, 0.008, -0.003, 0.005]
    for i in range(N):
        t, td = s.times[i], s.times[i] + jitter[i]
        save_rgb(root / "rgb" / f"{t:.6f}.png", s.rgb[i])
        save_png16(root / "depth" / f"{td:.6f}.png", quantize(s.depth_m[i], 5000.0))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
        for dt, T in ((-0.011, s.poses[(i + 1) % N]), (0.0, s.poses[i]), (0.011, s.poses[(i + 2) % N])):
            w, x, y, z = matrix_to_quat(T[:3, :3])
            gt.append(f"{t + dt:.6f} {row(T[:3, 3])} {row([x, y, z, w])}")
    t_extra = s.times[-1] + 0.5
    save_rgb(root / "rgb" / f"{t_extra:.6f}.png", s.rgb[0])
    rgb_lines.append(f"{t_extra:.6f} rgb/{t_extra:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if with_intrinsics:
        intrinsics_json(root / "intrinsics.json", s.K)
    return root


def backprojected_world(frame) -> np.ndarray:
    """(H*W, 3) world points of a frame, zeros where depth is missing."""
    from shared.geometry import backproject, transform

    pts = backproject(frame.intrinsics, frame.depth_m().astype(np.float64)).reshape(-1, 3)
    valid = frame.depth.reshape(-1) > 0
    out = np.zeros_like(pts)
    out[valid] = transform(frame.T_world_cam, pts[valid])
    return out
