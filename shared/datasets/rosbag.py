"""ROS 2 bags through ``rosbags`` (pure Python, no ROS install).

At open the bag is scanned once: the header stamps of the colour, depth and pose messages,
the first CameraInfo, and the whole TF tree (small). Images are not kept; ``frame(i)`` reads
its two messages back by their bag time. Colour and depth are paired one-to-one by header
stamp within ``max_time_diff_s`` (TUM's rule); the pose is the nearest ``pose_topic`` sample
within the same limit, or the TF chain world_frame -> camera_frame interpolated at the colour
stamp. Frames lacking depth or pose are skipped and counted in the log.

A ``pose_topic`` (nav_msgs/Odometry, geometry_msgs/PoseStamped or PoseWithCovarianceStamped)
must give the pose of the camera's optical frame itself: no extrinsic is applied to it.
A message whose header stamp is zero (some drivers) is timed by its bag record time.
"""

from __future__ import annotations

import logging
import threading
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_typestore

from shared.config.source import RosbagConfig
from shared.datasets.base import DatasetError, SequenceReader
from shared.datasets.files import check_index, checked_pose
from shared.datasets.rosimage import decode_colour, decode_depth, depth_scale_of, image_size
from shared.datasets.tf import TfBuffer, normalize_frame
from shared.datasets.timestamps import associate, nearest
from shared.geometry import Intrinsics, Pose, pose_from_quat
from shared.messages.frames import Frame

log = logging.getLogger(__name__)

_POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)


@dataclass(frozen=True)
class _Ref:
    """Where a message sits in the bag: its connection, record time and rank at that time."""

    conn: Connection
    bag_ns: int
    rank: int
    stamp_ns: int


def _stamp_ns(msg: Any, bag_ns: int) -> int:
    st = msg.header.stamp
    ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return ns if ns > 0 else bag_ns


def _pose_of(msg: Any) -> Pose:
    p = msg.pose if msg.__msgtype__ == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
    o = p.orientation
    return pose_from_quat(np.array([p.position.x, p.position.y, p.position.z]), np.array([o.w, o.x, o.y, o.z]))


class RosbagReader(SequenceReader):
    """RGB-D frames with poses from a ROS 2 bag folder; see the module docstring."""

    options = "rosbag"

    def __init__(self, path: Path | str, config: RosbagConfig | None = None) -> None:
        self.root = Path(path)
        self.config = cfg = config or RosbagConfig()
        if not self.root.exists():
            raise DatasetError(f"{self.root}: ROS bag not found")
        self._lock = threading.Lock()
        try:
            bag = AnyReader([self.root], default_typestore=get_typestore(Stores.LATEST))
            bag.open()
        except (AnyReaderError, OSError, ValueError) as e:
            raise DatasetError(f"{self.root}: cannot open ROS bag ({e})") from e
        self._bag: AnyReader | None = bag
        try:
            self._index(cfg)
        except BaseException:
            self.close()
            raise

    # -- indexing ---------------------------------------------------------------------------

    def _connections(self, topic: str, role: str) -> list[Connection]:
        assert self._bag is not None
        conns = [c for c in self._bag.connections if c.topic == topic]
        if not conns:
            available = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in self._bag.connections)) or "none"
            raise DatasetError(f"{self.root}: {role} topic {topic!r} is not in the bag; available topics: {available}")
        return conns

    def _scan(self, conns: list[Connection], keep: bool = False) -> tuple[list[_Ref], list[Any]]:
        """References sorted by header stamp, and the messages if ``keep`` (small ones only:
        a deserialized image holds its whole payload)."""
        assert self._bag is not None
        refs, msgs, seen = [], [], {}
        for conn, bag_ns, raw in self._bag.messages(connections=conns):
            msg = self._bag.deserialize(raw, conn.msgtype)
            rank = seen[(conn.id, bag_ns)] = seen.get((conn.id, bag_ns), -1) + 1
            refs.append(_Ref(conn, bag_ns, rank, _stamp_ns(msg, bag_ns)))
            msgs.append(msg if keep else None)
        order = sorted(range(len(refs)), key=lambda k: refs[k].stamp_ns)
        return [refs[k] for k in order], [msgs[k] for k in order]

    def _first(self, conns: list[Connection], role: str) -> Any:
        assert self._bag is not None
        with closing(self._bag.messages(connections=conns)) as msgs:
            for conn, _, raw in msgs:
                return self._bag.deserialize(raw, conn.msgtype)
        raise DatasetError(f"{self.root}: {role} topic {conns[0].topic!r} has no messages")

    def _index(self, cfg: RosbagConfig) -> None:
        rgb_c = self._connections(cfg.rgb_topic, "colour")
        depth_c = self._connections(cfg.depth_topic, "depth")
        info_c = self._connections(cfg.camera_info_topic, "camera info")
        pose_c = self._connections(cfg.pose_topic, "pose") if cfg.pose_topic else None
        first_rgb = self._first(rgb_c, "colour")
        self.intrinsics = self._intrinsics(self._first(info_c, "camera info"), first_rgb)
        self.depth_scale = depth_scale_of(self._first(depth_c, "depth"), cfg.depth_scale)
        self.camera_frame = normalize_frame(cfg.camera_frame or first_rgb.header.frame_id)
        rgb, _ = self._scan(rgb_c)
        depth, _ = self._scan(depth_c)
        max_dt = cfg.max_time_diff_s
        pairs = associate(np.array([r.stamp_ns for r in rgb]) * 1e-9, np.array([d.stamp_ns for d in depth]) * 1e-9, max_dt)
        poses = self._poses_pose_topic(pose_c, [rgb[i] for i, _ in pairs]) if pose_c else self._poses_tf([rgb[i] for i, _ in pairs])
        self._frames = [(rgb[i], depth[j], T) for (i, j), T in zip(pairs, poses, strict=True) if T is not None]
        n_no_depth, n_no_pose = len(rgb) - len(pairs), len(pairs) - len(self._frames)
        source = cfg.pose_topic or f"TF {cfg.world_frame} -> {self.camera_frame}"
        if n_no_depth or n_no_pose:
            log.warning(
                "ROS bag %s: skipped %d of %d colour frames (%d without depth, %d without a pose from %s within %.3f s)",
                self.root, n_no_depth + n_no_pose, len(rgb), n_no_depth, n_no_pose, source, max_dt,
            )  # fmt: skip
        if not self._frames:
            raise DatasetError(
                f"{self.root}: no colour message on {cfg.rgb_topic!r} has both depth on {cfg.depth_topic!r} "
                f"and a pose from {source} within {max_dt} s"
            )
        log.info("ROS bag %s: %d frames, poses from %s", self.root, len(self._frames), source)

    def _intrinsics(self, info: Any, first_rgb: Any) -> Intrinsics:
        topic = self.config.camera_info_topic
        w, h = image_size(first_rgb, f"{self.root}: topic {self.config.rgb_topic!r}")
        iw, ih = int(info.width) or w, int(info.height) or h
        if (iw, ih) != (w, h):
            raise DatasetError(
                f"{self.root}: camera info on {topic!r} is for {iw}x{ih}, images on {self.config.rgb_topic!r} are {w}x{h}"
            )
        k = [float(x) for x in info.k]
        try:
            return Intrinsics(fx=k[0], fy=k[4], cx=k[2], cy=k[5], width=w, height=h)
        except ValueError as e:
            raise DatasetError(f"{self.root}: invalid camera matrix K on {topic!r} ({e})") from None

    def _poses_pose_topic(self, conns: list[Connection], frames: list[_Ref]) -> list[Pose | None]:
        topic = conns[0].topic
        if bad := [c.msgtype for c in conns if c.msgtype not in _POSE_TYPES]:
            raise DatasetError(f"{self.root}: pose topic {topic!r} has type {bad[0]}; supported: {', '.join(_POSE_TYPES)}")
        refs, msgs = self._scan(conns, keep=True)
        frame_ids = {normalize_frame(m.header.frame_id) for m in msgs}
        if frame_ids - {self.config.world_frame}:
            log.warning("ROS bag %s: poses on %s are in frame(s) %s, taken as world frame", self.root, topic, sorted(frame_ids))
        stamps = np.array([r.stamp_ns for r in refs]) * 1e-9
        k = nearest(np.array([f.stamp_ns for f in frames]) * 1e-9, stamps, self.config.max_time_diff_s)
        where = f"{self.root}: pose topic {topic!r}"
        return [checked_pose(_pose_of(msgs[j]), f"{where} at stamp {refs[j].stamp_ns} ns") if j >= 0 else None for j in k]

    def _tf_buffer(self) -> TfBuffer:
        assert self._bag is not None
        tf = TfBuffer()
        topics = [c for c in self._bag.connections if c.topic in ("/tf", "/tf_static")]
        if not topics:
            self._connections("/tf", "TF (no pose_topic configured)")
        for conn, _, raw in self._bag.messages(connections=topics):
            for t in self._bag.deserialize(raw, conn.msgtype).transforms:
                tr, q = t.transform.translation, t.transform.rotation
                stamp = int(t.header.stamp.sec) * 1_000_000_000 + int(t.header.stamp.nanosec)
                tf.add(t.header.frame_id, t.child_frame_id, stamp, np.array([tr.x, tr.y, tr.z]),
                       np.array([q.w, q.x, q.y, q.z]), static=conn.topic == "/tf_static")  # fmt: skip
        return tf

    def _poses_tf(self, frames: list[_Ref]) -> list[Pose | None]:
        tf = self._tf_buffer()
        world, cam = normalize_frame(self.config.world_frame), self.camera_frame
        known = tf.frames()
        for name, role in ((world, "world_frame"), (cam, "camera frame")):
            if name not in known:
                raise DatasetError(
                    f"{self.root}: {role} {name!r} not found in /tf or /tf_static; TF frames: {', '.join(sorted(known))}"
                )
        gap = int(self.config.max_time_diff_s * 1e9)
        out = []
        for f in frames:
            try:
                T = tf.lookup(world, cam, f.stamp_ns, gap)
            except LookupError as e:
                raise DatasetError(f"{self.root}: {e}") from None
            out.append(None if T is None else checked_pose(T, f"{self.root}: TF {world} -> {cam} at {f.stamp_ns} ns"))
        return out

    # -- frames -----------------------------------------------------------------------------

    def _read(self, ref: _Ref) -> Any:
        if self._bag is None:
            raise DatasetError(f"{self.root}: ROS bag reader is closed")
        with self._lock:
            with closing(self._bag.messages(connections=[ref.conn], start=ref.bag_ns, stop=ref.bag_ns + 1)) as msgs:
                for rank, (conn, _, raw) in enumerate(msgs):
                    if rank == ref.rank:
                        return self._bag.deserialize(raw, conn.msgtype)
        raise DatasetError(f"{self.root}: message on {ref.conn.topic!r} at {ref.bag_ns} ns vanished from the bag")

    def __len__(self) -> int:
        return len(self._frames)

    def pose(self, i: int) -> Pose:
        return self._frames[check_index(i, len(self))][2]

    def frame(self, i: int) -> Frame:
        rgb_ref, depth_ref, T = self._frames[check_index(i, len(self))]
        K = self.intrinsics
        where = f"{self.root}: topic {rgb_ref.conn.topic!r} at stamp {rgb_ref.stamp_ns} ns"
        rgb = decode_colour(self._read(rgb_ref), where)
        if rgb.shape[:2] != (K.height, K.width):
            raise DatasetError(f"{where}: image is {rgb.shape[1]}x{rgb.shape[0]}, camera info says {K.width}x{K.height}")
        dwhere = f"{self.root}: topic {depth_ref.conn.topic!r} at stamp {depth_ref.stamp_ns} ns"
        depth, scale = decode_depth(self._read(depth_ref), self.config.depth_scale, dwhere)
        if depth.shape != rgb.shape[:2]:
            raise DatasetError(
                f"{dwhere}: depth is {depth.shape[1]}x{depth.shape[0]}, colour is {K.width}x{K.height} "
                "(record depth aligned to colour)"
            )
        return Frame(
            frame_index=i,
            time_s=rgb_ref.stamp_ns * 1e-9,
            rgb=rgb,
            depth=depth,
            depth_scale=scale,
            intrinsics=K,
            T_world_cam=T,
        )

    def close(self) -> None:
        bag, self._bag = getattr(self, "_bag", None), None
        if bag is not None:
            bag.close()
