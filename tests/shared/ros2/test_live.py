"""FrameAssembler: the robot's live ROS 2 messages (as CDR payloads) to TrackGraph frames.

A tiny synthetic scene (64x48) moves along a line; its colour, depth, CameraInfo, TF
(map -> odom -> base_link dynamic, base_link -> optical frame static) or pose topic are
encoded as ROS 2 messages, fed with jittered stamps and shuffled arrival, and every frame
out is checked against the ground truth.
"""

from __future__ import annotations

import io
import logging
import math
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from PIL import Image

from shared.config.ros2 import Ros2InputConfig
from shared.geometry import matrix_to_quat
from shared.messages.frames import Frame
from shared.ros2.live import REASONS, FrameAssembler
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


# -- the happy paths -----------------------------------------------------------------------


def test_tf_chain_gives_interpolated_poses_intrinsics_and_depth() -> None:
    s = scene(30)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert [f.frame_index for f in frames] == list(range(30))
    assert frame_numbers(frames) == list(range(30))
    for i, f in enumerate(frames):
        check_frame(f, i)
        np.testing.assert_array_equal(f.rgb, rgb_at(i))
        np.testing.assert_array_equal(f.depth, np.rint(depth_m_at(i) * 1000).astype(np.uint16))
        assert f.depth_scale == 1000.0
    assert rejected(asm) == {}
    st = asm.stats
    assert st.emitted == 30 and st.pending == 0 and asm.last_stamp_s == pytest.approx(stamp_of(29) / 1e9)
    assert st.as_dict()["received"][s.cfg.rgb_topic] == 30
    assert asm.error is None
    assert_accounted(asm)


def test_frames_wait_for_lagging_tf_and_leave_at_once_when_it_comes() -> None:
    s = scene(3, tf_until_s=-0.05)  # TF starts, then nothing for the frames yet
    asm = FrameAssembler(s.cfg)
    assert s.feed(asm, until=0.12) == []
    assert asm.stats.pending == 3
    add_tf(s, 0.0, 0.2, arrival_lag=0.0)  # TF for the frames arrives 0.12 s late, well within max_wait_s
    for e in s.events:
        asm.on_message(e[2], e[3], 0.13, e[4])
    s.events.clear()
    frames = asm.poll(0.13)
    assert frame_numbers(frames) == [0, 1, 2]
    for i, f in enumerate(frames):
        check_frame(f, i)
    assert_accounted(asm)


@pytest.mark.parametrize("kind", ["odometry", "posestamped"])
def test_pose_topic_gives_the_nearest_pose_within_slop(kind: str, caplog: pytest.LogCaptureFixture) -> None:
    s = scene(20, pose=kind)
    # the pose topic's frame_id differs from world_frame once: a single warning, poses still used
    s.add(0.0, "/odom", odometry(T_world_cam(-1.0), T0_NS - 10**9, frame_id="odom") if kind == "odometry"
          else pose_stamped(T_world_cam(-1.0), T0_NS - 10**9))  # fmt: skip
    asm = FrameAssembler(s.cfg)
    with caplog.at_level(logging.WARNING, logger="shared.ros2.live"):
        frames = s.feed(asm)
    assert frame_numbers(frames) == list(range(20))
    for i, f in enumerate(frames):
        # the pose sample is stamped within 3 ms of the colour: that sample's pose, not interpolated
        np.testing.assert_allclose(f.T_world_cam, T_world_cam(rel(stamp_of(i))), atol=0.01)
        assert f.intrinsics.fx == FX
    assert rejected(asm) == {}
    assert ("taken as world_frame" in caplog.text) == (kind == "odometry")
    assert_accounted(asm)


@pytest.mark.parametrize("rgb", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "jpeg", "png"])
def test_colour_encodings(rgb: str) -> None:
    s = scene(3, rgb=rgb)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == [0, 1, 2], rejected(asm)
    for i, f in enumerate(frames):
        want = rgb_at(i)
        if rgb == "mono8":
            want = np.repeat(want[:, :, :1], 3, axis=2)
        if rgb == "jpeg":
            assert np.abs(f.rgb.astype(int) - want).mean() < 3
        else:
            np.testing.assert_array_equal(f.rgb, want)
        check_frame(f, i)


@pytest.mark.parametrize("depth", ["16UC1", "32FC1", "cd16", "cd32"])
def test_depth_encodings(depth: str) -> None:
    s = scene(3, depth=depth)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == [0, 1, 2], rejected(asm)
    for i, f in enumerate(frames):
        want = depth_m_at(i)
        assert f.depth_scale == 1000.0 and f.depth.dtype == np.uint16
        assert (f.depth == 0).tolist() == (want == 0).tolist()  # holes stay holes
        # inverse-depth quantisation (32FC1 compressedDepth) is d^2 / 10100 m: under 1 mm at 3 m
        np.testing.assert_allclose(f.depth_m(), want, atol=0.0011 if depth == "cd32" else 0.0006)


def test_compressed_colour_and_compressed_depth_over_the_key_types() -> None:
    """Under rmw_zenoh the key's type wins over the configured one."""
    s = scene(3, rgb="jpeg", depth="cd16", cfg=Ros2InputConfig())  # config says raw Image for both
    asm = FrameAssembler(s.cfg)
    assert frame_numbers(s.feed(asm)) == [0, 1, 2]
    # without the key's type, the configured (raw Image) one is tried and the payload fails
    s = scene(1, rgb="jpeg", cfg=Ros2InputConfig())
    s.events = [(e[0], e[1], e[2], e[3], None if e[2] == s.cfg.rgb_topic else e[4]) for e in s.events]
    asm = FrameAssembler(s.cfg)
    assert s.feed(asm) == [] and rejected(asm) == {"bad_payload": 1}


# -- faults --------------------------------------------------------------------------------


def test_depth_stops_for_5_s_then_returns() -> None:
    gap = set(range(30, 30 + 5 * FPS))
    n = 30 + 5 * FPS + 30
    s = scene(n, skip_depth=gap)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    got = frame_numbers(frames)
    assert got[:30] == list(range(30)) and got[30:] == list(range(30 + 5 * FPS, n))
    r = rejected(asm)
    # each colour without depth waits max_wait_s and is given up; the last few before depth
    # returns are dropped the moment a newer frame completes instead
    assert r.get("no_depth", 0) + r.get("superseded", 0) == len(gap) and r["no_depth"] >= len(gap) - 20
    assert set(r) <= {"no_depth", "superseded"}
    assert [f.frame_index for f in frames] == list(range(len(frames)))
    assert_accounted(asm)


def test_tf_jumping_back_rejects_the_frames_that_would_use_it(caplog: pytest.LogCaptureFixture) -> None:
    n = 60
    s = scene(n, tf_until_s=0.5)
    # 0.5 s .. 0.8 s: odom -> base_link comes stamped 3 s in the past (a stale clock), then is good again
    for k in range(26, 40):
        t = k / 50
        st = T0_NS + round((t - 3.0) * 1e9)
        s.add(t + 0.06, s.cfg.tf_topic, tf_message(transform("odom", "base_link", st, T_odom_base(t - 3.0))))
    for k in range(10, 17):  # map -> odom keeps coming
        s.add(k / 20 + 0.061, s.cfg.tf_topic, tf_message(transform("map", "odom", T0_NS + k * 10**9 // 20, T_map_odom(k / 20))))
    add_tf(s, 0.8, rel(stamp_of(n - 1)) + 0.2)
    asm = FrameAssembler(s.cfg)
    with caplog.at_level(logging.WARNING, logger="shared.ros2.live"):
        frames = s.feed(asm)
    got = frame_numbers(frames)
    lost = [i for i in range(n) if i not in got]
    # the frames between the last good sample (0.50 s) and the next one (0.80 s), and no other
    assert lost == [i for i in range(n) if 0.5 < i / FPS < 0.8], lost
    assert rejected(asm) == {"tf_backwards": len(lost), "out_of_order": 14}
    assert "TF_OLD_DATA ignoring data from the past for frame base_link" in caplog.text
    for f, i in zip(frames, got, strict=True):
        check_frame(f, i)
    assert asm.stats.resets == 0  # 0.28 s of stale stamps is no new timeline
    assert_accounted(asm)


def test_a_bag_loop_resets_the_buffers_and_frames_resume(caplog: pytest.LogCaptureFixture) -> None:
    s = scene(45)  # 1.5 s of scene
    asm = FrameAssembler(s.cfg)
    first = s.feed(asm, until=1.6)
    assert len(first) == 45
    # the bag starts again: the same stamps, arriving from 1.6 s on
    s2 = scene(90, seed=1)
    for now, k, topic, payload, ros_type in s2.events:
        if topic != s.cfg.tf_static_topic:
            s.events.append((now + 1.6, k, topic, payload, ros_type))
    with caplog.at_level(logging.WARNING, logger="shared.ros2.live"):
        again = s.feed(asm)
    assert asm.stats.resets == 1
    assert "went back in time" in caplog.text and "cleared the TF buffer" in caplog.text
    got = frame_numbers(again)
    assert got and got == sorted(got) and got[-1] == 89 and got[0] > 20  # ~1 s of the loop lost to the reset
    for f, i in zip(again, got, strict=True):
        check_frame(f, i)
    assert [f.frame_index for f in first + again] == list(range(len(first) + len(again)))  # indices go on
    assert_accounted(asm)


def test_camera_info_never_comes(caplog: pytest.LogCaptureFixture) -> None:
    s = scene(4 * FPS, info=False)
    asm = FrameAssembler(s.cfg)
    first_colour = min(e[0] for e in s.events if e[2] == s.cfg.rgb_topic)
    errors = []
    for now, _, topic, payload, ros_type in sorted(s.events):
        asm.on_message(topic, payload, now, ros_type)
        assert asm.poll(now) == []
        errors.append((now, asm.error))
    last = max(e[0] for e in s.events)
    s.events.clear()
    with_error = [now for now, e in errors if e is not None]
    assert with_error and with_error[0] - first_colour <= s.cfg.camera_info_timeout_s + 0.05
    assert all(now - first_colour >= s.cfg.camera_info_timeout_s - 0.05 for now in with_error)
    assert asm.error.startswith(f"no sensor_msgs/CameraInfo on {s.cfg.camera_info_topic} after")
    held = asm.stats.pending
    assert 1 <= held <= asm.max_pending  # the newest colour images wait max_wait_s for it
    assert rejected(asm) == {"no_camera_info": 4 * FPS - held}
    assert_accounted(asm)
    assert asm.poll(last + s.cfg.max_wait_s + 0.01) == []
    assert rejected(asm) == {"no_camera_info": 4 * FPS} and asm.stats.pending == 0
    assert s.cfg.camera_info_topic in asm.silent_topics(4.2)
    # it comes after all: the error clears and frames flow
    s.add(4.2, s.cfg.camera_info_topic, camera_info(stamp_of(0)))
    asm.on_message(s.cfg.camera_info_topic, s.events[0][3], 4.2, None)
    assert asm.error is None
    assert_accounted(asm)


def test_colour_before_the_first_camera_info_waits_for_it() -> None:
    """Over a network the first colour image often beats the first CameraInfo: it is held
    (up to max_wait_s), not dropped, and becomes the first frame."""
    s = scene(10, info=False)
    first_colour = min(e[0] for e in s.events if e[2] == s.cfg.rgb_topic)
    s.add(first_colour + 0.02, s.cfg.camera_info_topic, camera_info(stamp_of(0)))
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == list(range(10))
    for i, f in enumerate(frames):
        check_frame(f, i)
    assert rejected(asm) == {} and asm.error is None
    assert_accounted(asm)
    # Later than max_wait_s, the held image is given up, and named as such.
    s = scene(10, info=False)
    s.add(first_colour + s.cfg.max_wait_s + 0.02, s.cfg.camera_info_topic, camera_info(stamp_of(0)))
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    got = frame_numbers(frames)
    assert got and got[0] > 0 and got == list(range(got[0], 10))
    assert rejected(asm) == {"no_camera_info": got[0]}
    assert_accounted(asm)


def test_unknown_encodings_are_counted() -> None:
    s = scene(4)
    topic_rgb, topic_d = s.cfg.rgb_topic, s.cfg.depth_topic
    late = 5.0
    s.add(late, topic_rgb, raw_image(np.zeros((H, W, 2), np.uint8), "yuv422", stamp_of(10)))
    s.add(late, topic_rgb, compressed(b"\x00" * 40, "rgb8; h264 compressed", stamp_of(11)))
    s.add(late, topic_rgb, compressed(b"\x00" * 40, "16UC1; compressedDepth png", stamp_of(12)))
    s.add(late, topic_d, raw_image(rgb_at(0), "rgb8", stamp_of(13)))
    s.add(late, topic_d, compressed(b"\x00" * 40, "16UC1; compressedDepth rvl", stamp_of(14)))
    s.add(late, topic_d, compressed(file_bytes(rgb_at(0), "JPEG"), "16UC1; jpeg compressed", stamp_of(15)))
    asm = FrameAssembler(s.cfg)
    assert frame_numbers(s.feed(asm)) == [0, 1, 2, 3]
    assert rejected(asm) == {"unknown_encoding": 6}
    assert "'16UC1; jpeg compressed' is not supported" in asm.error  # the standing problem, until a frame goes out
    assert_accounted(asm)


def test_size_mismatch_between_image_camera_info_and_depth(caplog: pytest.LogCaptureFixture) -> None:
    s = scene(6)
    small = np.rint(depth_m_at(0)[::2, ::2] * 1000).astype(np.uint16)
    asm = FrameAssembler(s.cfg)
    # frame 2's depth is half size (not aligned to colour); then a camera info for another size
    s.events = [e for e in s.events if not (e[2] == s.cfg.depth_topic and abs(e[0] - (rel(stamp_of(2)) + 0.035)) < 0.01)]
    s.add(rel(stamp_of(2)) + 0.035, s.cfg.depth_topic, raw_image(small, "16UC1", stamp_of(2)))
    with caplog.at_level(logging.WARNING, logger="shared.ros2.live"):
        frames = s.feed(asm, until=1.0)
    assert frame_numbers(frames) == [0, 1, 3, 4, 5]
    assert rejected(asm) == {"size_mismatch": 1} and "depth is 32x24" in caplog.text and "aligned to colour" in caplog.text
    assert asm.error is None  # the frames after it were fine: no standing problem
    s.add(1.1, s.cfg.camera_info_topic, camera_info(stamp_of(6), width=W * 2, height=H * 2))
    s.add(1.11, s.cfg.rgb_topic, raw_image(rgb_at(6), "rgb8", stamp_of(6)))
    assert s.feed(asm) == []
    assert rejected(asm) == {"size_mismatch": 2} and "image is 64x48, camera info on" in asm.error
    assert_accounted(asm)


def test_out_of_order_stamps() -> None:
    s = scene(10)
    asm = FrameAssembler(s.cfg)
    assert len(s.feed(asm, until=1.0)) == 10
    s.add(1.1, s.cfg.rgb_topic, raw_image(rgb_at(3), "rgb8", stamp_of(3)))  # older than frame 9
    s.add(1.1, s.cfg.rgb_topic, raw_image(rgb_at(9), "rgb8", stamp_of(9)))  # a repeat of frame 9
    s.add(1.1, s.cfg.depth_topic, raw_image(np.zeros((H, W), np.uint16), "16UC1", stamp_of(4)))
    t_old = T0_NS + 10**8  # TF 0.1 s: older than the newest odom -> base_link by far more than tolerance
    s.add(1.1, s.cfg.tf_topic, tf_message(transform("odom", "base_link", t_old, np.eye(4))))
    assert s.feed(asm, until=1.2) == []
    assert rejected(asm) == {"out_of_order": 4}
    # arrival order shuffled within the window is no fault: frames come out in stamp order
    s2 = scene(10, seed=3)
    rng = np.random.default_rng(5)
    s2.events = [(e[0] + (rng.uniform(0, 0.05) if e[2] != s2.cfg.tf_topic else 0.0), *e[1:]) for e in s2.events]
    asm2 = FrameAssembler(s2.cfg)
    got = frame_numbers(s2.feed(asm2))
    assert got == sorted(got) and len(got) >= 7
    assert set(rejected(asm2)) <= {"superseded"}
    assert_accounted(asm)
    assert_accounted(asm2)


def test_latest_wins_supersedes_older_waiting_colours() -> None:
    s = scene(5, skip_depth={1, 2})
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == [0, 3, 4]
    assert rejected(asm) == {"superseded": 2}  # frame 3 completed while 1 and 2 still waited
    # their depth turning up later is too late: nothing is emitted out of order
    s.add(10.0, s.cfg.depth_topic, raw_image(np.zeros((H, W), np.uint16), "16UC1", stamp_of(1)))
    assert s.feed(asm) == []
    assert rejected(asm) == {"superseded": 2, "out_of_order": 1}
    assert_accounted(asm)


def test_unsupported_key_types_and_unknown_topics() -> None:
    s = scene(2)
    s.add(1.0, s.cfg.rgb_topic, M("std_msgs/msg/String")(data="hi"))
    s.add(1.0, s.cfg.tf_topic, M("std_msgs/msg/String")(data="hi"))
    s.add_raw(1.0, s.cfg.depth_topic, b"\x00\x01\x00\x00", "sensor_msgs/msg/NoSuchType")
    s.add(1.0, "/elsewhere", M("std_msgs/msg/String")(data="hi"))
    asm = FrameAssembler(s.cfg)
    assert len(s.feed(asm)) == 2
    assert rejected(asm) == {"unsupported_type": 3}
    assert "/elsewhere" not in asm.stats.received
    assert_accounted(asm)


def test_bad_poses_are_refused() -> None:
    s = scene(6, pose="odometry")
    nan = np.eye(4)
    nan[0, 3] = np.nan
    s.add(0.0, "/odom", odometry(nan, stamp_of(0) - 5 * 10**6))
    asm = FrameAssembler(s.cfg)
    assert len(s.feed(asm)) == 6
    assert rejected(asm) == {"bad_pose": 1}
    s2 = scene(3)
    s2.add(0.0, s2.cfg.tf_topic, tf_message(transform("odom", "base_link", stamp_of(0) + 1, np.eye(4), q=np.zeros(4))))
    s2.add(0.0, s2.cfg.tf_topic, tf_message(transform("odom", "odom", stamp_of(0), np.eye(4))))
    asm2 = FrameAssembler(s2.cfg)
    assert len(s2.feed(asm2)) == 3
    assert rejected(asm2) == {"bad_pose": 1, "bad_payload": 1}
    assert_accounted(asm)
    assert_accounted(asm2)


def test_frames_after_tf_stops_are_given_up() -> None:
    s = scene(30, tf_until_s=0.3)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    got = frame_numbers(frames)
    # 0.30 s is the last sample: up to 0.35 s the end sample is near enough (once max_wait_s is up)
    assert got == [i for i in range(30) if i / FPS <= 0.3 + 0.05]
    assert rejected(asm) == {"tf_missing": 30 - len(got)}
    assert asm.error.startswith("/camera/color/image_raw at stamp") and "no TF map <- camera_color_optical_frame" in asm.error
    assert_accounted(asm)


def test_tf_that_cannot_connect_names_the_frames(caplog: pytest.LogCaptureFixture) -> None:
    cfg = Ros2InputConfig(world_frame="world")  # the robot's tree is rooted at map
    s = scene(3, cfg=cfg)
    asm = FrameAssembler(cfg)
    with caplog.at_level(logging.WARNING, logger="shared.ros2.live"):
        assert s.feed(asm) == []
    assert rejected(asm) == {"tf_missing": 3}
    assert asm.error.startswith("TF: no frame 'world'") and "known: base_link" in asm.error
    cfg = Ros2InputConfig(camera_frame="camera_link")
    s = scene(3, cfg=cfg)
    s.add(0.0, cfg.tf_static_topic, tf_message(transform("robot", "camera_link", stamp_of(0), np.eye(4))))
    asm = FrameAssembler(cfg)
    assert s.feed(asm) == []
    assert asm.error.startswith("TF: frames 'map' and 'camera_link' are not connected")
    assert "camera_link" in caplog.text
    assert_accounted(asm)


def test_silent_topics_say_what_is_missing() -> None:
    s = scene(60)
    s.events = [e for e in s.events if e[2] != s.cfg.depth_topic]
    asm = FrameAssembler(s.cfg)
    assert asm.silent_topics(0.0) == []
    s.feed(asm, until=2.0)
    assert asm.silent_topics(2.05) == [s.cfg.depth_topic]
    assert asm.silent_topics(3.0, after_s=0.5) == [s.cfg.rgb_topic, s.cfg.depth_topic, s.cfg.camera_info_topic, s.cfg.tf_topic]
    pose = FrameAssembler(Ros2InputConfig(pose_topic="/odom"))
    assert sorted(pose.subscriptions) == sorted([pose.cfg.rgb_topic, pose.cfg.depth_topic, pose.cfg.camera_info_topic, "/odom"])
    assert pose.silent_topics(10.0) == [] and len(pose.silent_topics(12.5)) == 4


def test_memory_stays_bounded() -> None:
    cfg = Ros2InputConfig(tf_buffer_s=1.0, max_wait_s=0.2)
    asm = FrameAssembler(cfg)
    asm.on_message(cfg.camera_info_topic, encode(camera_info(0)), 0.0)
    img = rgb_at(0)
    for k in range(600):  # 10 s of 60 Hz colour with no depth, and 120 Hz TF on 10 links
        now = k / 60
        st = T0_NS + k * 10**9 // 60
        asm.on_message(cfg.rgb_topic, encode(raw_image(img, "rgb8", st)), now)
        links = [transform("odom", f"link{j}", st + m * 10**9 // 120, np.eye(4)) for j in range(10) for m in range(2)]
        if k < 60:
            links.append(transform("odom", "gone", st, np.eye(4)))  # a publisher that stops after 1 s
        asm.on_message(cfg.tf_topic, encode(tf_message(*links)), now)
        asm.poll(now)
        assert asm.stats.pending <= asm.max_pending
    assert asm._tf.sample_count() <= 10 * (cfg.tf_buffer_s + cfg.max_wait_s + 0.05) * 120
    assert "gone" not in asm._tf.frames()
    assert len(asm._depths) == 0 and asm.stats.rejected["no_depth"] > 0
    assert_accounted(asm)


# -- hostile input -------------------------------------------------------------------------


def _mutations(valid: list[bytes], rng: np.random.Generator, n: int) -> list[bytes]:
    out = []
    for k in range(n):
        p = bytearray(valid[k % len(valid)])
        kind = k % 5
        if kind == 0:  # random bytes, sometimes behind a valid CDR header
            p = bytearray(rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes())
            if k % 2:
                p[:4] = b"\x00\x01\x00\x00"
        elif kind == 1:  # flipped bytes
            for j in rng.integers(0, len(p), int(rng.integers(1, 8))):
                p[j] = int(rng.integers(0, 256))
        elif kind == 2:  # truncated
            p = p[: int(rng.integers(0, len(p)))]
        elif kind == 3:  # a length field blown up (the first four bytes after a 4-aligned offset)
            j = 4 + 4 * int(rng.integers(0, max(1, (len(p) - 8) // 4)))
            p[j : j + 4] = struct.pack("<I", int(rng.choice([2**31 - 1, 2**32 - 1, len(p), 0])))
        else:  # grown with junk
            p += rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        out.append(bytes(p))
    return out


@pytest.mark.parametrize("role", ["rgb", "depth", "camera_info", "tf", "tf_static", "pose"])
def test_hostile_payloads_are_counted_never_raised(role: str, caplog: pytest.LogCaptureFixture) -> None:
    kind = "odometry" if role == "pose" else "tf"
    s = scene(12, pose=kind, rgb="jpeg" if role == "rgb" else "rgb8", depth="cd32" if role == "depth" else "16UC1")
    cfg = s.cfg
    topic = {"rgb": cfg.rgb_topic, "depth": cfg.depth_topic, "camera_info": cfg.camera_info_topic, "tf": cfg.tf_topic,
             "tf_static": cfg.tf_static_topic, "pose": "/odom"}[role]  # fmt: skip
    valid = [e for e in s.events if e[2] == topic]
    rng = np.random.default_rng(123)
    n = 10_000
    hostile = _mutations([e[3] for e in valid], rng, n)
    asm = FrameAssembler(cfg, max_payload_bytes=50_000)
    frames = s.feed(asm, until=1.0)
    assert len(frames) == 12
    base = asm.stats
    ros_type = valid[0][4]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="shared.ros2.live"):
        for k, p in enumerate(hostile):
            asm.on_message(topic, p, 1.0 + k * 1e-4, ros_type)
            if k % 50 == 0:
                asm.poll(1.0 + k * 1e-4)
    assert len(caplog.records) <= 12  # rate-limited: a line per reason (and a few once-warnings), not 10^4
    asm.on_message(topic, b"\x00\x01\x00\x00" + bytes(60_000), 2.0, ros_type)  # oversized: refused before parsing
    asm.poll(100.0)
    st = asm.stats
    assert st.received[topic] == base.received[topic] + n + 1
    assert_accounted(asm)
    new = {k: st.rejected[k] - base.rejected[k] for k in REASONS}
    assert new["bad_payload"] >= n // 2
    taken = st.accepted[topic] - base.accepted[topic]
    assert base.pending == 0 and taken + sum(new.values()) + st.pending == n + 1  # each one is somewhere, once
