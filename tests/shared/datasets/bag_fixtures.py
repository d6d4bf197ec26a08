"""The test scene as a ROS 2 bag, written with rosbags' Writer and Humble message types."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from dataset_fixtures import H, Scene, W, matrix_to_quat
from PIL import Image
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from shared.config.source import RosbagConfig
from shared.geometry import invert

TS = get_typestore(Stores.ROS2_HUMBLE)
T_ = TS.types
CAMERA_FRAME = "camera_color_optical_frame"
DEPTH_JITTER_NS = [3_000_000, -4_000_000, 2_000_000, -1_000_000, 5_000_000]

# camera_link (x forward, z up) -> optical frame (z forward, y down), as in REP 103 drivers
R_LINK_OPT = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
T_MAP_ODOM = np.array([[0.0, -1, 0, 0.3], [1, 0, 0, -0.2], [0, 0, 1, 0.05], [0, 0, 0, 1]])


def _header(stamp_ns: int, frame_id: str):
    t = T_["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return T_["std_msgs/msg/Header"](stamp=t, frame_id=frame_id)


def _pose(T: np.ndarray):
    w, x, y, z = matrix_to_quat(T[:3, :3])
    return T_["geometry_msgs/msg/Pose"](
        position=T_["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        orientation=T_["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def _transform(T: np.ndarray, parent: str, child: str, stamp_ns: int):
    w, x, y, z = matrix_to_quat(T[:3, :3])
    tf = T_["geometry_msgs/msg/Transform"](
        translation=T_["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        rotation=T_["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )
    return T_["geometry_msgs/msg/TransformStamped"](header=_header(stamp_ns, parent), child_frame_id=child, transform=tf)


def image_msg(a: np.ndarray, encoding: str, stamp_ns: int, pad: int = 0, frame_id: str = CAMERA_FRAME):
    """Raw Image with ``pad`` bytes of row padding (drivers align rows)."""
    h, w = a.shape[:2]
    row_bytes = w * a.itemsize * (a.shape[2] if a.ndim == 3 else 1)
    rows = np.ascontiguousarray(a).view(np.uint8).reshape(h, row_bytes)
    step = rows.shape[1] + pad
    data = np.zeros((h, step), np.uint8)
    data[:, : rows.shape[1]] = rows
    return T_["sensor_msgs/msg/Image"](
        header=_header(stamp_ns, frame_id), height=h, width=w, encoding=encoding,
        is_bigendian=0, step=step, data=data.reshape(-1),
    )  # fmt: skip


def compressed_msg(a: np.ndarray, fmt: str, stamp_ns: int):
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="JPEG" if fmt == "jpeg" else "PNG", quality=95)
    return T_["sensor_msgs/msg/CompressedImage"](
        header=_header(stamp_ns, CAMERA_FRAME), format=f"rgb8; {fmt} compressed bgr8",
        data=np.frombuffer(buf.getvalue(), np.uint8),
    )  # fmt: skip


def camera_info_msg(s: Scene, stamp_ns: int, width: int = W, height: int = H):
    K = s.K
    return T_["sensor_msgs/msg/CameraInfo"](
        header=_header(stamp_ns, CAMERA_FRAME), height=height, width=width, distortion_model="plumb_bob",
        d=np.zeros(5), k=np.array([K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1.0]), r=np.eye(3).reshape(-1),
        p=np.array([K.fx, 0, K.cx, 0, 0, K.fy, K.cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
        roi=T_["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )  # fmt: skip


def pose_msg(kind: str, T: np.ndarray, stamp_ns: int):
    if kind == "posestamped":
        return T_["geometry_msgs/msg/PoseStamped"](header=_header(stamp_ns, "map"), pose=_pose(T))
    cov = np.zeros(36)
    zero = T_["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T_["nav_msgs/msg/Odometry"](
        header=_header(stamp_ns, "map"), child_frame_id=CAMERA_FRAME,
        pose=T_["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(T), covariance=cov),
        twist=T_["geometry_msgs/msg/TwistWithCovariance"](
            twist=T_["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=cov
        ),
    )  # fmt: skip


Msg = tuple[str, str, int, object]  # topic, type, header stamp (ns), message


def scene_messages(s: Scene, *, pose: str = "odometry", rgb: str = "rgb8", depth: str = "16UC1") -> tuple[RosbagConfig, list[Msg]]:
    """The scene as bag messages, and the config that reads them. ``pose``: odometry,
    posestamped or tf. ``rgb``: rgb8, bgr8, jpeg or png. ``depth``: 16UC1 or 32FC1."""
    cfg = RosbagConfig(pose_topic=None if pose == "tf" else "/odom")
    stamps = [int(round(t * 1e9)) for t in s.times]
    msgs: list[Msg] = [(cfg.camera_info_topic, "sensor_msgs/msg/CameraInfo", stamps[0], camera_info_msg(s, stamps[0]))]
    for i, st in enumerate(stamps):
        if rgb in ("rgb8", "bgr8"):
            a = s.rgb[i] if rgb == "rgb8" else s.rgb[i][:, :, ::-1]
            msgs.append((cfg.rgb_topic, "sensor_msgs/msg/Image", st, image_msg(a, rgb, st, pad=4)))
        else:
            msgs.append((cfg.rgb_topic, "sensor_msgs/msg/CompressedImage", st, compressed_msg(s.rgb[i], rgb, st)))
        sd = st + DEPTH_JITTER_NS[i]
        if depth == "16UC1":
            d = np.rint(s.depth_m[i] * 1000).astype(np.uint16)
        else:
            d = np.where(s.depth_m[i] > 0, s.depth_m[i], np.nan).astype(np.float32)
        msgs.append((cfg.depth_topic, "sensor_msgs/msg/Image", sd, image_msg(d, depth, sd)))
        if pose != "tf":
            msgtype = "geometry_msgs/msg/PoseStamped" if pose == "posestamped" else "nav_msgs/msg/Odometry"
            msgs.append(("/odom", msgtype, st, pose_msg(pose, s.poses[i], st)))
    if pose == "tf":
        msgs.append(("/tf_static", "tf2_msgs/msg/TFMessage", stamps[0], T_["tf2_msgs/msg/TFMessage"](transforms=[
            _transform(T_MAP_ODOM, "map", "odom", stamps[0]),
            _transform(R_LINK_OPT, "camera_link", CAMERA_FRAME, stamps[0]),
        ])))  # fmt: skip
        for i, st in enumerate(stamps):
            T_odom_link = invert(T_MAP_ODOM) @ s.poses[i] @ invert(R_LINK_OPT)
            tfm = T_["tf2_msgs/msg/TFMessage"](transforms=[_transform(T_odom_link, "odom", "camera_link", st)])
            msgs.append(("/tf", "tf2_msgs/msg/TFMessage", st, tfm))
    return cfg, msgs


def write_messages(path: Path, msgs: list[Msg], storage: StoragePlugin = StoragePlugin.SQLITE3) -> Path:
    with Writer(path, version=9, storage_plugin=storage) as w:
        conns = {}
        for topic, msgtype, _, _ in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=TS)
        # Record time lags the header stamp by 2 ms, as a real recorder's would.
        for topic, msgtype, st, msg in sorted(msgs, key=lambda m: m[2]):
            w.write(conns[topic], st + 2_000_000, TS.serialize_cdr(msg, msgtype))
    return path


def write_rosbag(s: Scene, path: Path, *, storage: StoragePlugin = StoragePlugin.SQLITE3, **kinds: str) -> RosbagConfig:
    """Write the scene as a bag (``kinds`` as for :func:`scene_messages`); returns its config."""
    cfg, msgs = scene_messages(s, **kinds)
    write_messages(path, msgs, storage)
    return cfg
