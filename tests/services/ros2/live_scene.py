"""A synthetic robot for the FrameAssembler tests: its ROS 2 messages and their arrival.

A tiny scene (64x48) moves along a line; its colour, depth, CameraInfo, TF (map -> odom ->
base_link dynamic, base_link -> optical frame static) or pose topic are encoded as ROS 2
messages with jittered stamps and shuffled arrival, and the ground truth to check frames by.
"""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from PIL import Image

from services.ros2.live import REASONS, FrameAssembler
from shared.config.ros2 import Ros2InputConfig
from shared.geometry import matrix_to_quat
from shared.messages.frames import Frame
from shared.ros2.types import encode, msg_class

W, H = 64, 48
T0_NS = 1_700_000_000 * 10**9  # an epoch-like stamp: float seconds would lose the jitter
FPS = 30
CAM = "camera_color_optical_frame"
FX, FY, CX, CY = 50.0, 51.0, 31.7, 23.2

# base_link (x forward, z up) -> optical frame (z forward, x right, y down), 10 cm up
T_BASE_OPT = np.array([[0.0, 0, 1, 0.1], [-1, 0, 0, 0], [0, -1, 0, 0.1], [0, 0, 0, 1]])


def M(name: str) -> Any:
    return msg_class(name)


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def T_map_odom(t: float) -> np.ndarray:
    """Localisation drifts slowly: linear translation, fixed rotation (interpolates exactly)."""
    T = np.eye(4)
    T[:3, :3] = rot_z(0.3)
    T[:3, 3] = [1.0 + 0.01 * t, -0.5, 0.0]
    return T


def T_odom_base(t: float) -> np.ndarray:
    """The robot drives along a line and turns at a constant rate (lerp and slerp are exact)."""
    T = np.eye(4)
    T[:3, :3] = rot_z(0.2 * t)
    T[:3, 3] = [0.5 * t, 0.1 * t, 0.0]
    return T


def T_world_cam(t: float) -> np.ndarray:
    return T_map_odom(t) @ T_odom_base(t) @ T_BASE_OPT


def rgb_at(i: int) -> np.ndarray:
    u, v = np.arange(W)[None, :], np.arange(H)[:, None]
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = 3 * u + 10
    img[..., 1] = 4 * v + 5
    img[..., 2] = (7 * i + 40) % 256
    return img


def depth_m_at(i: int) -> np.ndarray:
    u, v = np.arange(W)[None, :], np.arange(H)[:, None]
    d = 1.5 + 0.02 * u + 0.01 * v + 0.001 * (i % 50)
    d[10:20, 20:30] = 0.9
    d[0, 0] = d[H - 1, W - 1] = 0.0  # holes: no reading
    return d


# -- messages ------------------------------------------------------------------------------


def header(stamp_ns: int, frame_id: str) -> Any:
    t = M("builtin_interfaces/msg/Time")(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return M("std_msgs/msg/Header")(stamp=t, frame_id=frame_id)


def raw_image(a: np.ndarray, encoding: str, stamp_ns: int, frame_id: str = CAM, pad: int = 0) -> Any:
    h, w = a.shape[:2]
    rows = np.ascontiguousarray(a).view(np.uint8).reshape(h, -1)
    data = np.zeros((h, rows.shape[1] + pad), np.uint8)
    data[:, : rows.shape[1]] = rows
    return M("sensor_msgs/msg/Image")(
        header=header(stamp_ns, frame_id), height=h, width=w, encoding=encoding, is_bigendian=0,
        step=data.shape[1], data=data.reshape(-1),
    )  # fmt: skip


def compressed(data: bytes, fmt: str, stamp_ns: int, frame_id: str = CAM) -> Any:
    return M("sensor_msgs/msg/CompressedImage")(
        header=header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(data, np.uint8)
    )


def file_bytes(a: np.ndarray, fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format=fmt, quality=95)
    return buf.getvalue()


def compressed_depth(depth_m: np.ndarray, enc: str, stamp_ns: int, depth_max: float = 10.0, z0: float = 100.0) -> Any:
    """What compressed_depth_image_transport publishes (its encoder, in numpy)."""
    if enc == "16UC1":
        png, a, b = file_bytes(np.rint(depth_m * 1000).astype(np.uint16), "PNG"), 0.0, 0.0
    else:
        a = np.float32(z0 * (z0 + 1.0))
        b = np.float32(1.0 - a / np.float32(depth_max))
        d = depth_m.astype(np.float32)
        with np.errstate(divide="ignore"):
            inv = np.where((d > 0) & (d < depth_max), a / d + b, 0).astype(np.uint16)
        png = file_bytes(inv, "PNG")
    return compressed(struct.pack("<iff", 0, a, b) + png, f"{enc}; compressedDepth png", stamp_ns)


def camera_info(stamp_ns: int, width: int = W, height: int = H) -> Any:
    return M("sensor_msgs/msg/CameraInfo")(
        header=header(stamp_ns, CAM), height=height, width=width, distortion_model="plumb_bob",
        d=np.zeros(5), k=np.array([FX, 0, CX, 0, FY, CY, 0, 0, 1.0]), r=np.eye(3).reshape(-1),
        p=np.array([FX, 0, CX, 0, 0, FY, CY, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
        roi=M("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )  # fmt: skip


def ros_pose(T: np.ndarray) -> Any:
    w, x, y, z = matrix_to_quat(T[:3, :3])
    return M("geometry_msgs/msg/Pose")(
        position=M("geometry_msgs/msg/Point")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        orientation=M("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w),
    )


def transform(parent: str, child: str, stamp_ns: int, T: np.ndarray, q: np.ndarray | None = None) -> Any:
    w, x, y, z = matrix_to_quat(T[:3, :3]) if q is None else q
    tf = M("geometry_msgs/msg/Transform")(
        translation=M("geometry_msgs/msg/Vector3")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        rotation=M("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w),
    )
    return M("geometry_msgs/msg/TransformStamped")(header=header(stamp_ns, parent), child_frame_id=child, transform=tf)


def tf_message(*transforms: Any) -> Any:
    return M("tf2_msgs/msg/TFMessage")(transforms=list(transforms))


def odometry(T: np.ndarray, stamp_ns: int, frame_id: str = "map") -> Any:
    cov = np.zeros(36)
    zero = M("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
    return M("nav_msgs/msg/Odometry")(
        header=header(stamp_ns, frame_id), child_frame_id=CAM,
        pose=M("geometry_msgs/msg/PoseWithCovariance")(pose=ros_pose(T), covariance=cov),
        twist=M("geometry_msgs/msg/TwistWithCovariance")(twist=M("geometry_msgs/msg/Twist")(linear=zero, angular=zero), covariance=cov),
    )  # fmt: skip


def pose_stamped(T: np.ndarray, stamp_ns: int) -> Any:
    return M("geometry_msgs/msg/PoseStamped")(header=header(stamp_ns, "map"), pose=ros_pose(T))


# -- a stream of messages ------------------------------------------------------------------


@dataclass
class Stream:
    """Messages with arrival times; ``feed`` plays them into an assembler in arrival order,
    polling after each, and keeps the frames."""

    cfg: Ros2InputConfig
    events: list[tuple[float, int, str, bytes, str | None]] = field(default_factory=list)

    def add(self, now: float, topic: str, msg: Any, ros_type: str | None = None) -> None:
        self.events.append((now, len(self.events), topic, encode(msg), ros_type or msg.__msgtype__))

    def add_raw(self, now: float, topic: str, payload: bytes, ros_type: str | None = None) -> None:
        self.events.append((now, len(self.events), topic, payload, ros_type))

    def feed(self, asm: FrameAssembler, until: float | None = None) -> list[Frame]:
        frames = []
        for now, _, topic, payload, ros_type in sorted(self.events):
            asm.on_message(topic, payload, now, ros_type)
            frames += asm.poll(now)
        last = max(e[0] for e in self.events) if self.events else 0.0
        frames += asm.poll(until if until is not None else last + 10.0)
        self.events.clear()
        return frames


def stamp_of(i: int) -> int:
    return T0_NS + i * 10**9 // FPS


def rel(stamp_ns: int) -> float:
    """Scene time (s) of a stamp."""
    return (stamp_ns - T0_NS) / 1e9


def scene(
    n: int,
    *,
    cfg: Ros2InputConfig | None = None,
    rgb: str = "rgb8",
    depth: str = "16UC1",
    pose: str = "tf",
    seed: int = 0,
    skip_depth: set[int] | None = None,
    tf_until_s: float | None = None,
    info: bool = True,
) -> Stream:
    """``n`` frames at 30 Hz: colour (rgb8, bgr8, rgba8, bgra8, mono8, jpeg, png), depth
    (16UC1, 32FC1, cd16, cd32: compressedDepth), pose from ``tf``, ``odometry`` or
    ``posestamped``. Depth stamps jitter by up to 6 ms, arrivals by up to 10 ms; TF comes
    at 50 Hz (odom -> base_link) and 20 Hz (map -> odom) 60 ms after its stamp."""
    cfg = cfg or Ros2InputConfig(pose_topic=None if pose == "tf" else "/odom",
                                 pose_type="geometry_msgs/msg/PoseStamped" if pose == "posestamped" else "nav_msgs/msg/Odometry",
                                 rgb_type="sensor_msgs/msg/CompressedImage" if rgb in ("jpeg", "png") else "sensor_msgs/msg/Image",
                                 depth_type="sensor_msgs/msg/CompressedImage" if depth.startswith("cd") else "sensor_msgs/msg/Image")  # fmt: skip
    rng = np.random.default_rng(seed)
    s = Stream(cfg)
    skip_depth = skip_depth or set()
    for i in range(n):
        st = stamp_of(i)
        now = rel(st) + 0.03 + rng.uniform(0, 0.01)
        if info:  # drivers publish CameraInfo with every image, just before it
            s.add(now - 0.001, cfg.camera_info_topic, camera_info(st))
        a = rgb_at(i)
        if rgb in ("rgb8", "bgr8", "rgba8", "bgra8"):
            b = a[:, :, ::-1] if rgb.startswith("bgr") else a
            if rgb.endswith("a8"):
                b = np.concatenate([b, np.full((H, W, 1), 255, np.uint8)], axis=2)
            m = raw_image(b, rgb, st, pad=4)
        elif rgb == "mono8":
            m = raw_image(a[:, :, 0], "mono8", st)
        else:
            m = compressed(file_bytes(a, "JPEG" if rgb == "jpeg" else "PNG"), f"rgb8; {rgb} compressed bgr8", st)
        s.add(now, cfg.rgb_topic, m)
        if i in skip_depth:
            continue
        sd = st + int(rng.integers(-6, 7)) * 10**6
        d = depth_m_at(i)
        if depth == "16UC1":
            dm = raw_image(np.rint(d * 1000).astype(np.uint16), "16UC1", sd)
        elif depth == "32FC1":
            dm = raw_image(np.where(d > 0, d, np.nan).astype(np.float32), "32FC1", sd)
        else:
            dm = compressed_depth(d, "16UC1" if depth == "cd16" else "32FC1", sd)
        s.add(rel(sd) + 0.03 + rng.uniform(0, 0.01), cfg.depth_topic, dm)
        if pose != "tf":
            sp = st + int(rng.integers(-3, 4)) * 10**6
            pm = pose_stamped(T_world_cam(rel(sp)), sp) if pose == "posestamped" else odometry(T_world_cam(rel(sp)), sp)
            s.add(rel(sp) + 0.005, cfg.pose_topic, pm)
    if pose == "tf":
        s.add(0.0, cfg.tf_static_topic, tf_message(transform("base_link", CAM, stamp_of(0), T_BASE_OPT)))
        end = tf_until_s if tf_until_s is not None else rel(stamp_of(n - 1)) + 0.2
        add_tf(s, 0.0 - 0.1, end)
    return s


def add_tf(s: Stream, start: float, end: float, *, offset_s: float = 0.0, arrival_lag: float = 0.06) -> None:
    """TF of the scene for scene times [start, end]; ``offset_s`` shifts the stamps (not the
    arrival), as a clock that jumped would."""
    for k in range(int(math.floor(start * 50)), int(math.ceil(end * 50)) + 1):
        t = k / 50
        st = T0_NS + round((t + offset_s) * 1e9)
        s.add(t + arrival_lag, s.cfg.tf_topic, tf_message(transform("odom", "base_link", st, T_odom_base(t))))
    for k in range(int(math.floor(start * 20)), int(math.ceil(end * 20)) + 1):
        t = k / 20
        st = T0_NS + round((t + offset_s) * 1e9)
        s.add(t + arrival_lag + 0.001, s.cfg.tf_topic, tf_message(transform("map", "odom", st, T_map_odom(t))))


def assert_accounted(asm: FrameAssembler) -> None:
    """Every message ends in exactly one place: taken in, rejected with a reason, or pending."""
    st = asm.stats
    assert set(st.rejected) == set(REASONS)
    assert sum(st.received.values()) == sum(st.accepted.values()) + sum(st.rejected.values()) + st.pending, st.as_dict()


def rejected(asm: FrameAssembler) -> dict[str, int]:
    return {k: v for k, v in asm.stats.rejected.items() if v}


def check_frame(f: Frame, i: int) -> None:
    assert f.time_s == pytest.approx(stamp_of(i) / 1e9, abs=1e-6)
    np.testing.assert_allclose(f.T_world_cam, T_world_cam(rel(stamp_of(i))), atol=1e-9)
    K = f.intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (FX, FY, CX, CY, W, H)


def frame_numbers(frames: list[Frame]) -> list[int]:
    return [round((f.time_s - T0_NS / 1e9) * FPS) for f in frames]
