"""Synthetic sequences as ROS 2 bags recorded the way a robot records them, and bags read back
as the raw message stream a player republishes.

Writing (:func:`write_sequence_bag`) turns a synthetic (Replica-layout) sequence into what
``ros2 bag record`` would store from a RealSense-style driver plus a localisation stack:

- ``/camera/color/image_raw``: sensor_msgs/msg/Image, rgb8, every frame; with
  ``compressed_rgb``, ``/camera/color/image_raw/compressed`` (sensor_msgs/msg/CompressedImage,
  JPEG) instead, as image_transport names it;
- ``/camera/aligned_depth_to_color/image_raw``: sensor_msgs/msg/Image, 16UC1, every frame;
- ``/camera/color/camera_info``: sensor_msgs/msg/CameraInfo (plumb_bob, no distortion), every
  frame, as drivers publish it;
- ``/tf_static``: tf2_msgs/msg/TFMessage, once at the start, offered transient-local;
- ``/tf``: tf2_msgs/msg/TFMessage, every frame, and once after the last.

The TF tree is ``map -> odom -> base_link -> camera_link -> camera_color_optical_frame``:
``/tf_static`` holds the camera mount (:data:`T_BASE_LINK`) and the REP 103 optical rotation
(:data:`T_LINK_OPTICAL`); ``/tf`` holds ``odom -> base_link`` at every frame stamp (and one
sample half a period after the last frame, the odometry going on after the camera stops) and
``map -> odom`` (a fixed localisation offset, :data:`T_MAP_ODOM`) every
:data:`MAP_ODOM_EVERY` frames and at the first and last. ``odom -> base_link`` is solved so that
the chain ``map -> camera_color_optical_frame`` is the sequence's ``T_world_cam`` (to rounding:
about 1e-15). Images and CameraInfo are in ``camera_color_optical_frame``.

Frame ``i`` is stamped ``t0 + i / rate``; each topic is recorded a few milliseconds after its
stamp (:data:`LATENCY_NS`, shrunk at high rates so frames never interleave), as a recorder on
the robot receives them, and messages are written in record-time order.

Depth. A synthetic sequence stores 6553.5 units per metre; drivers publish millimetres. With
``depth_units="mm"`` (the default: a bag any ROS 2 tool and the default ``RosbagConfig`` read
correctly) each value becomes ``rint(value * 1000 / depth_scale)``: exact for a sequence in
millimetres, else rounded to the nearest millimetre (at most 0.5 mm off). With
``depth_units="sequence"`` the values are copied unchanged (lossless) and a reader must be told
the scale (``source.rosbag.depth_scale``: :attr:`BagSummary.depth_scale`).

Ground truth never travels in the bag. The bag's ``custom_data`` (metadata.yaml) names the
sequence it came from (:data:`CUSTOM_SEQUENCE`, read back by :func:`bag_source_sequence`), so a
tool mapping the bag with the simulated perception backends can find its instance images.
``trackgraph map BAG --dataset rosbag`` does not look there (yet): it finds ground truth only in
the folder it maps, so give it a config whose ``ground_truth`` keys name the sequence
(``load_config(...).with_ground_truth(seq)`` saved with ``save_resolved``).

Reading (:func:`read_bag_messages`) yields every message as stored (CDR bytes, no decoding) in
record-time order; :class:`PlaySchedule` says when a player should send each one.
"""

from __future__ import annotations

import io
import logging
import math
import os
import shutil
import sqlite3
import tempfile
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer, WriterError

from shared.config.source import RosbagConfig, SourceConfig
from shared.datasets import open_sequence
from shared.datasets.base import DatasetError
from shared.datasets.replica import NOMINAL_HZ
from shared.geometry import Intrinsics, Pose, invert, matrix_to_quat
from shared.ros2.types import encode, msg_class, typestore

log = logging.getLogger(__name__)

__all__ = [
    "BagError",
    "BagMessage",
    "BagSummary",
    "PlaySchedule",
    "bag_custom_data",
    "bag_duration_ns",
    "bag_source_sequence",
    "bag_topics",
    "latched_topics",
    "play_times",
    "read_bag_messages",
    "write_sequence_bag",
]

# -- the recorded layout ------------------------------------------------------------------------

_DEFAULTS = RosbagConfig()
RGB_TOPIC = _DEFAULTS.rgb_topic
COMPRESSED_RGB_TOPIC = f"{RGB_TOPIC}/compressed"
"""image_transport's name for the JPEG stream of ``RGB_TOPIC``."""
DEPTH_TOPIC = _DEFAULTS.depth_topic
CAMERA_INFO_TOPIC = _DEFAULTS.camera_info_topic
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

MAP_FRAME = _DEFAULTS.world_frame
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
LINK_FRAME = "camera_link"
OPTICAL_FRAME = "camera_color_optical_frame"

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"


def _rigid(R: Annotated[np.ndarray, "(3, 3)"], t: Annotated[np.ndarray, "(3,)"]) -> Pose:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _rot_z(deg: float) -> Annotated[np.ndarray, "(3, 3)"]:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(deg: float) -> Annotated[np.ndarray, "(3, 3)"]:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


T_LINK_OPTICAL: Pose = _rigid(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), np.zeros(3))
"""camera_link (x forward, y left, z up) -> optical frame (x right, y down, z forward), REP 103."""
T_BASE_LINK: Pose = _rigid(_rot_y(8.0), np.array([0.12, 0.0, 0.35]))
"""The camera's mount on the robot: 12 cm ahead of and 35 cm above base_link, pitched 8 degrees
down (a rotation, so a reader that drops the static chain gets the pose visibly wrong)."""
T_MAP_ODOM: Pose = _rigid(_rot_z(25.0), np.array([1.5, -0.75, 0.0]))
"""The localisation offset between the map and the odometry origin (fixed: no drift)."""
MAP_ODOM_EVERY = 1
"""``map -> odom`` is published on ``/tf`` every this many frames (and at the first and last).
SLAM back ends publish it at least at the camera's rate (slam_toolbox every 0.02 s), and a
live consumer cannot interpolate a camera pose until the sample after its stamp is in: a
sparser map -> odom would hold every frame until the next one."""

EPOCH_NS = 1_700_000_000 * 1_000_000_000
"""Stamp of frame 0 (November 2023): a wall-clock time, as a robot's clock gives, not zero."""
LATENCY_NS = {
    TF_TOPIC: 500_000,
    CAMERA_INFO_TOPIC: 4_000_000,
    RGB_TOPIC: 4_200_000,
    COMPRESSED_RGB_TOPIC: 4_200_000,
    DEPTH_TOPIC: 4_600_000,
}
"""Record time minus header stamp per topic (the driver's transfer and the recorder's receive);
depth comes last since aligning it to colour takes the driver a moment."""

CUSTOM_SEQUENCE = "trackgraph.source_sequence"
"""custom_data key: absolute path of the sequence folder the bag was written from."""
CUSTOM_DEPTH_SCALE = "trackgraph.depth_scale"
"""custom_data key: depth units per metre of the 16UC1 depth topic."""

_ZERO = QosTime(0, 0)
_RELIABLE = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE, _ZERO, _ZERO,
                QosLiveliness.AUTOMATIC, _ZERO, False)  # fmt: skip
_TF_QOS = _RELIABLE._replace(depth=100)  # tf2_ros' broadcaster
_LATCHED = _RELIABLE._replace(depth=1, durability=QosDurability.TRANSIENT_LOCAL)  # tf2_ros' static broadcaster

_DISTRO_STORAGE = {"humble": "sqlite3"}
"""rosbag2's default storage per distro: sqlite3 up to Humble, MCAP since Iron."""


class BagError(DatasetError):
    """A ROS 2 bag that is missing, unreadable, or lacks what was asked; the message names the
    bag (a :class:`DatasetError`, so commands report it as bad input)."""


@dataclass(frozen=True)
class BagSummary:
    """What :func:`write_sequence_bag` wrote."""

    path: Path
    frames: int
    topics: dict[str, tuple[str, int]]
    """topic -> (ROS type, message count)."""
    seconds: float
    """Wall time the writing took."""
    duration_s: float = 0.0
    """Record time from the first message to the last."""
    depth_scale: float = 1000.0
    """Units per metre of the 16UC1 depth (1000: millimetres); ``source.rosbag.depth_scale``."""
    storage: str = "mcap"
    distro: str = "jazzy"


# -- writing ------------------------------------------------------------------------------------


class _Messages:
    """Builds the messages of one distro's definitions."""

    def __init__(self, distro: str) -> None:
        self.distro = distro
        self.T = {name: msg_class(name, distro) for name in (
            "builtin_interfaces/msg/Time", "std_msgs/msg/Header", "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
            "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/RegionOfInterest", "geometry_msgs/msg/TransformStamped",
            "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion", "tf2_msgs/msg/TFMessage",
        )}  # fmt: skip

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return self.T["std_msgs/msg/Header"](stamp=self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id)

    def image(self, a: np.ndarray, encoding: str, stamp_ns: int) -> Any:
        a = np.ascontiguousarray(a)
        h, w = a.shape[:2]
        # Little-endian on the wire, whatever this machine is (is_bigendian = 0 below).
        data = a.astype(a.dtype.newbyteorder("<"), copy=False).view(np.uint8).reshape(-1)
        return self.T[IMAGE_TYPE](
            header=self.header(stamp_ns, OPTICAL_FRAME), height=h, width=w, encoding=encoding, is_bigendian=0,
            step=data.size // h, data=data,
        )  # fmt: skip

    def jpeg(self, rgb: np.ndarray, stamp_ns: int, quality: int) -> Any:
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
        # image_transport's format string for a JPEG made from an rgb8 frame.
        return self.T[COMPRESSED_TYPE](
            header=self.header(stamp_ns, OPTICAL_FRAME), format="rgb8; jpeg compressed bgr8",
            data=np.frombuffer(buf.getvalue(), np.uint8),
        )  # fmt: skip

    def camera_info(self, K: Intrinsics, stamp_ns: int) -> Any:
        return self.T[CAMERA_INFO_TYPE](
            header=self.header(stamp_ns, OPTICAL_FRAME), height=K.height, width=K.width, distortion_model="plumb_bob",
            d=np.zeros(5), k=np.array([K.fx, 0.0, K.cx, 0.0, K.fy, K.cy, 0.0, 0.0, 1.0]), r=np.eye(3).reshape(-1),
            p=np.array([K.fx, 0.0, K.cx, 0.0, 0.0, K.fy, K.cy, 0.0, 0.0, 0.0, 1.0, 0.0]), binning_x=0, binning_y=0,
            roi=self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )  # fmt: skip

    def transform(self, T: Pose, parent: str, child: str, stamp_ns: int) -> Any:
        w, x, y, z = matrix_to_quat(T[:3, :3])
        tf = self.T["geometry_msgs/msg/Transform"](
            translation=self.T["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=self.T["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w)),
        )
        return self.T["geometry_msgs/msg/TransformStamped"](header=self.header(stamp_ns, parent), child_frame_id=child, transform=tf)

    def tf(self, transforms: list[Any]) -> Any:
        return self.T[TF_TYPE](transforms=transforms)


def _depth_out(depth: np.ndarray, scale: float, units: str, where: str) -> tuple[np.ndarray, int]:
    """The depth to record and how many readings did not fit 16 bits (written as 0, no reading)."""
    if units == "sequence" or scale == 1000.0:
        return depth, 0
    mm = np.rint(depth.astype(np.float64) * (1000.0 / scale))
    over = mm > 65535
    n = int(over.sum())
    if n:
        mm[over] = 0
        log.debug("%s: %d depth readings beyond 65.535 m written as 0", where, n)
    return mm.astype(np.uint16), n


def _check_out(out: Path, overwrite: bool) -> None:
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise BagError(f"{out}: exists and is not a folder; choose another output path for the bag")
    if not out.is_dir() or not any(out.iterdir()):
        return
    if not overwrite:
        raise BagError(f"{out}: output folder exists and is not empty; choose another path, or overwrite it (--overwrite)")
    if not (out / "metadata.yaml").is_file():
        # Overwriting deletes the folder: only ever one that is itself a bag.
        raise BagError(f"{out}: refusing to overwrite a folder that is not a ROS 2 bag (no metadata.yaml)")


def _latency(period_ns: int) -> dict[str, int]:
    """Per-topic record delays, scaled down so the last one stays under half a frame period."""
    scale = min(1.0, 0.5 * period_ns / max(LATENCY_NS.values()))
    return {topic: int(ns * scale) for topic, ns in LATENCY_NS.items()}


def write_sequence_bag(
    seq_dir: Path | str,
    out: Path | str,
    *,
    distro: str = "jazzy",
    rate_hz: float | None = None,
    storage: Literal["sqlite3", "mcap"] | None = None,
    compressed_rgb: bool = False,
    jpeg_quality: int = 95,
    depth_units: Literal["mm", "sequence"] = "mm",
    max_frames: int | None = None,
    t0_ns: int = EPOCH_NS,
    overwrite: bool = False,
    progress: bool = False,
) -> BagSummary:
    """Write the synthetic (Replica-layout) sequence ``seq_dir`` as a ROS 2 bag folder ``out``;
    the layout is in the module docstring.

    ``rate_hz``: frame rate of the stamps (default: the sequence's nominal 30 Hz).
    ``storage``: rosbag2 storage plugin (default: the distro's, MCAP since Iron, sqlite3 on
    Humble). ``compressed_rgb``: JPEG colour on :data:`COMPRESSED_RGB_TOPIC` instead of raw rgb8.
    ``depth_units``: see the module docstring. ``max_frames``: only the first N frames.
    The bag is written in a temporary folder beside ``out`` and renamed into place at the end,
    so ``out`` never holds a partial bag. A non-empty ``out`` is refused (:class:`BagError`)
    unless ``overwrite`` and it is a bag. DatasetError for a bad sequence.
    """
    seq_dir, out = Path(seq_dir), Path(out)
    if rate_hz is not None and not (math.isfinite(rate_hz) and 0 < rate_hz <= 1e6):
        raise ValueError(f"rate_hz must be a positive number of frames per second (at most 1e6), got {rate_hz}")
    if depth_units not in ("mm", "sequence"):
        raise ValueError(f"depth_units must be 'mm' or 'sequence', got {depth_units!r}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be at least 1, got {max_frames}")
    if not 1 <= jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
    storage = storage or _DISTRO_STORAGE.get(distro, "mcap")
    plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
    if storage not in plugins:
        raise ValueError(f"storage must be one of {', '.join(plugins)}, got {storage!r}")
    typestore(distro)  # ValueError naming the distros for an unknown one, before any work
    _check_out(out, overwrite)

    started = time.perf_counter()
    with open_sequence(seq_dir, "replica", SourceConfig()) as reader:
        n = len(reader) if max_frames is None else min(max_frames, len(reader))
        depth_scale = 1000.0 if depth_units == "mm" else float(reader.depth_scale)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
        try:
            # The writer names its storage file after the folder: write under the final name.
            counts = _write(reader, tmp / out.name, distro, n, rate_hz or NOMINAL_HZ, t0_ns, plugins[storage],
                            compressed_rgb, jpeg_quality, depth_units, depth_scale, seq_dir, progress)  # fmt: skip
            if out.is_dir():
                # Empty, or a bag the caller asked to overwrite (checked above): the new one is complete.
                shutil.rmtree(out)
            os.replace(tmp / out.name, out)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    seconds = time.perf_counter() - started
    duration_ns = bag_duration_ns(out)
    log.info("wrote %d frames of %s as a %s %s bag in %.1f s -> %s", n, seq_dir, distro, storage, seconds, out)
    return BagSummary(path=out, frames=n, topics=counts, seconds=seconds, duration_s=duration_ns * 1e-9,
                      depth_scale=depth_scale, storage=storage, distro=distro)  # fmt: skip


def _write(reader: Any, path: Path, distro: str, n: int, rate_hz: float, t0_ns: int, plugin: StoragePlugin, compressed_rgb: bool,
           jpeg_quality: int, depth_units: str, depth_scale: float, seq_dir: Path, progress: bool) -> dict[str, tuple[str, int]]:  # fmt: skip
    m, ts = _Messages(distro), typestore(distro)
    period_ns = round(1e9 / rate_hz)
    stamps = [t0_ns + round(i * 1e9 / rate_hz) for i in range(n)]
    lat = _latency(period_ns)
    rgb_topic = COMPRESSED_RGB_TOPIC if compressed_rgb else RGB_TOPIC
    topics = {
        TF_STATIC_TOPIC: (TF_TYPE, _LATCHED), TF_TOPIC: (TF_TYPE, _TF_QOS), CAMERA_INFO_TOPIC: (CAMERA_INFO_TYPE, _RELIABLE),
        rgb_topic: (COMPRESSED_TYPE if compressed_rgb else IMAGE_TYPE, _RELIABLE), DEPTH_TOPIC: (IMAGE_TYPE, _RELIABLE),
    }  # fmt: skip
    T_base_opt = T_BASE_LINK @ T_LINK_OPTICAL
    T_odom_map = invert(T_MAP_ODOM)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="frame", desc="bag")
    n_far = 0
    try:
        writer = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin)
        writer.set_custom_data(CUSTOM_SEQUENCE, str(seq_dir.resolve()))
        writer.set_custom_data(CUSTOM_DEPTH_SCALE, repr(depth_scale))
        with writer:
            conns = {t: writer.add_connection(t, ty, typestore=ts, offered_qos_profiles=[q]) for t, (ty, q) in topics.items()}
            counts = dict.fromkeys(topics, 0)

            def put(topic: str, record_ns: int, msg: Any) -> None:
                writer.write(conns[topic], record_ns, encode(msg, topics[topic][0], m.distro))
                counts[topic] += 1

            put(TF_STATIC_TOPIC, stamps[0], m.tf([
                m.transform(T_BASE_LINK, BASE_FRAME, LINK_FRAME, stamps[0]),
                m.transform(T_LINK_OPTICAL, LINK_FRAME, OPTICAL_FRAME, stamps[0]),
            ]))  # fmt: skip
            for i, st in enumerate(stamps):
                frame = reader.frame(i)
                T_odom_base = T_odom_map @ frame.T_world_cam @ invert(T_base_opt)
                tfs = [m.transform(T_odom_base, ODOM_FRAME, BASE_FRAME, st)]
                if i % MAP_ODOM_EVERY == 0 or i == n - 1:
                    tfs.insert(0, m.transform(T_MAP_ODOM, MAP_FRAME, ODOM_FRAME, st))
                depth, far = _depth_out(frame.depth, frame.depth_scale, depth_units, f"{seq_dir} frame {i}")
                n_far += far
                colour = m.jpeg(frame.rgb, st, jpeg_quality) if compressed_rgb else m.image(frame.rgb, "rgb8", st)
                batch = [
                    (st + lat[TF_TOPIC], TF_TOPIC, m.tf(tfs)),
                    (st + lat[CAMERA_INFO_TOPIC], CAMERA_INFO_TOPIC, m.camera_info(frame.intrinsics, st)),
                    (st + lat[rgb_topic], rgb_topic, colour),
                    (st + lat[DEPTH_TOPIC], DEPTH_TOPIC, m.image(depth.astype(np.uint16, copy=False), "16UC1", st)),
                ]
                for record_ns, topic, msg in sorted(batch, key=lambda b: b[0]):
                    put(topic, record_ns, msg)
                if bar is not None:
                    bar.update(1)
            # Odometry goes on after the camera stops: a sample after the last frame lets a TF
            # buffer interpolate at the last stamp (tf2 will not extrapolate past its newest).
            after = stamps[-1] + period_ns // 2
            put(TF_TOPIC, after + lat[TF_TOPIC], m.tf([m.transform(T_odom_base, ODOM_FRAME, BASE_FRAME, after)]))
    except WriterError as e:
        raise BagError(f"{seq_dir}: cannot write the ROS 2 bag {path.name} ({e})") from e
    finally:
        if bar is not None:
            bar.close()
    if n_far:
        log.warning("%s: %d depth readings beyond 65.535 m were written as 0 (no reading)", seq_dir, n_far)
    return {t: (topics[t][0], c) for t, c in counts.items()}


# -- reading ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BagMessage:
    """One message as the bag stores it."""

    topic: str
    ros_type: str
    time_ns: int
    """Bag record time (ns since the epoch), not the header stamp."""
    payload: bytes = field(repr=False)
    """CDR bytes with their encapsulation header, as they went over the wire."""


class _Open:
    """A rosbags Reader whose failures are BagErrors naming the bag."""

    def __init__(self, bag: Path | str) -> None:
        self.path = Path(bag)
        if not self.path.exists():
            raise BagError(f"{self.path}: ROS 2 bag not found")
        try:
            self.reader = Reader(self.path)
            self.reader.open()
        except (ReaderError, OSError, ValueError, KeyError, sqlite3.Error) as e:
            raise BagError(f"{self.path}: cannot open as a ROS 2 bag ({type(e).__name__}: {e})") from e

    def __enter__(self) -> Reader:
        return self.reader

    def __exit__(self, *exc: object) -> None:
        self.reader.close()


def bag_topics(bag: Path | str) -> dict[str, str]:
    """topic -> ROS type of every topic in ``bag`` (a bag folder, or one .mcap / .db3 file)."""
    with _Open(bag) as r:
        return _types(r)


def _types(r: Reader) -> dict[str, str]:
    out: dict[str, str] = {}
    for c in r.connections:
        if out.setdefault(c.topic, c.msgtype) != c.msgtype:
            log.warning("ROS 2 bag %s: topic %s is recorded with types %s and %s", r.path, c.topic, out[c.topic], c.msgtype)
    return out


def latched_topics(bag: Path | str) -> set[str]:
    """Topics recorded from a transient-local publisher (``/tf_static``): a player offers
    them the same way, so late subscribers still get them."""
    with _Open(bag) as r:
        return {
            c.topic for c in r.connections
            if any(q.durability == QosDurability.TRANSIENT_LOCAL for q in getattr(c.ext, "offered_qos_profiles", []))
        }  # fmt: skip


def bag_duration_ns(bag: Path | str) -> int:
    """Record time from the first message of ``bag`` to its last (0 for fewer than two)."""
    with _Open(bag) as r:
        if r.message_count == 0:
            return 0
        return max(0, r.end_time - 1 - r.start_time)  # rosbags' end_time is one past the last


def bag_custom_data(bag: Path | str) -> dict[str, str]:
    """The ``custom_data`` of the bag's metadata.yaml (empty when it has none)."""
    with _Open(bag) as r:
        meta = getattr(r.storage, "metadata", None)
        return dict(getattr(meta, "custom", None) or {})


def bag_source_sequence(bag: Path | str) -> Path | None:
    """The synthetic sequence folder ``bag`` was written from (see :data:`CUSTOM_SEQUENCE`), if
    it names one that exists with ground truth (``instances/``); None otherwise."""
    value = bag_custom_data(bag).get(CUSTOM_SEQUENCE)
    if not value:
        return None
    seq = Path(value)
    if not (seq / "instances").is_dir():
        log.info("ROS 2 bag %s was written from %s, which has no instances/ (moved or deleted?)", bag, seq)
        return None
    return seq


def read_bag_messages(bag: Path | str, *, topics: list[str] | None = None) -> Iterator[BagMessage]:
    """Every message of ``bag`` (or of ``topics``) in record-time order, payloads as stored.

    A missing or unreadable bag, or a topic it lacks (the error lists the ones it has), raises
    :class:`BagError` here, not at the first ``next``. The bag is open while the iterator runs
    and closed when it is exhausted or closed.
    """
    with _Open(bag) as r:
        have = _types(r)
    if topics is not None:
        if missing := [t for t in topics if t not in have]:
            available = ", ".join(f"{t} ({ty})" for t, ty in sorted(have.items())) or "none"
            raise BagError(f"{bag}: topic(s) {', '.join(map(repr, missing))} not in the bag; available topics: {available}")
    return _messages(Path(bag), None if topics is None else set(topics))


def _messages(bag: Path, topics: set[str] | None) -> Iterator[BagMessage]:
    # Opened again here, not in read_bag_messages: a generator that is never started never
    # runs its cleanup, and would leave the bag open.
    with _Open(bag) as r:
        conns = [c for c in r.connections if topics is None or c.topic in topics]
        if not conns:
            return
        try:
            for conn, t_ns, raw in r.messages(connections=conns):
                yield BagMessage(conn.topic, conn.msgtype, int(t_ns), bytes(raw))
        except (ReaderError, OSError, sqlite3.Error) as e:
            raise BagError(f"{bag}: unreadable message data ({type(e).__name__}: {e})") from e


# -- playing ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlaySchedule:
    """When a player sends each message: the bag's record-time gaps divided by ``rate``,
    counted from the first message (``first_ns``) sent at ``t_start`` (monotonic seconds)."""

    first_ns: int
    rate: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"play rate must be a positive finite factor, got {self.rate}")

    @classmethod
    def of_bag(cls, bag: Path | str, *, rate: float = 1.0) -> PlaySchedule:
        """The schedule of ``bag`` from its first message."""
        with _Open(bag) as r:
            if r.message_count == 0:
                raise BagError(f"{bag}: the bag has no messages to play")
            return cls(r.start_time, rate)

    def due_at(self, msg: BagMessage | int, t_start: float) -> float:
        """Monotonic time (s) at which ``msg`` (or a record time in ns) is due."""
        t_ns = msg.time_ns if isinstance(msg, BagMessage) else int(msg)
        return t_start + (t_ns - self.first_ns) * 1e-9 / self.rate


def play_times(messages: Iterable[BagMessage], t_start: float, *, rate: float = 1.0) -> Iterator[tuple[float, BagMessage]]:
    """``(due_at, message)`` for each message, the first due at ``t_start``: a player sleeps
    until each is due, then sends it (``for due, m in play_times(read_bag_messages(bag),
    time.monotonic())``). ValueError at once for a rate that is not positive."""
    PlaySchedule(0, rate)  # refuse a bad rate now, not at the first message
    return _play_times(iter(messages), t_start, rate)


def _play_times(messages: Iterator[BagMessage], t_start: float, rate: float) -> Iterator[tuple[float, BagMessage]]:
    first = next(messages, None)
    if first is None:
        return
    schedule = PlaySchedule(first.time_ns, rate)
    yield t_start, first
    for msg in messages:
        yield schedule.due_at(msg, t_start), msg
