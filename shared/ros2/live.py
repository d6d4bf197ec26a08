"""The robot's live camera, TF and pose messages to TrackGraph :class:`Frame` s.

The core of ``trackgraph source --ros2``, with no Zenoh and no clock of its own: the link
hands every raw CDR payload of the configured topics to :meth:`FrameAssembler.on_message`
with the arrival time ``now`` (monotonic seconds), and :meth:`FrameAssembler.poll` returns
the frames that became complete.

A frame is one colour image, the depth image nearest to it in stamp within ``slop_s``
(approximate-time sync, nearest first, each depth used once), the latest CameraInfo's K,
and the camera pose at the colour stamp: TF ``world_frame <- camera frame`` interpolated
between samples each within ``tf_tolerance_s`` of the stamp, or the nearest ``pose_topic``
sample within ``slop_s``. A colour waits up to ``max_wait_s`` of arrival time for its depth
and pose (TF usually lags images); then it is given up and counted. Latest wins: once a
newer colour completes, older ones still waiting are dropped (``superseded``), so frames
leave in stamp order and never late.

Nothing from the network makes this raise. Every message ends in exactly one of: taken in
(:attr:`LiveInputStats.accepted`; for the colour topic, emitted in a frame), rejected with
one reason of :data:`REASONS` (:attr:`LiveInputStats.rejected`), or, for colour images,
still pending. Each reason is logged at most once per :data:`WARN_PERIOD_S` (naming the
topic and what was expected); :attr:`FrameAssembler.error` holds the problem that currently
stops frames, if any, and :meth:`FrameAssembler.silent_topics` the topics that went quiet.

Stamps that go back in time (a bag played in a loop, a simulator reset) are refused as
``out_of_order`` (for TF, like tf2's TF_OLD_DATA); when a stream keeps going back for more
than :data:`RESET_AFTER_S` of arrivals, the TF buffer and the sync state are cleared and the
new timeline is taken from there.

Memory is bounded: a few pending colour and depth messages (decoded CDR, pixels decoded only
when a frame is complete), TF pruned to ``tf_buffer_s + max_wait_s`` per link, links silent
for that long forgotten, and at most :data:`MAX_TF_FRAMES` frame names.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from shared.config.ros2 import COLOUR_TYPES, DEPTH_TYPES, POSE_TYPES, Ros2InputConfig
from shared.datasets.base import DatasetError
from shared.datasets.files import checked_pose
from shared.datasets.rosimage import (
    UnsupportedEncodingError,
    decode_colour,
    decode_depth,
    peek_size,
)
from shared.datasets.tf import TfBuffer, normalize_frame
from shared.geometry import Intrinsics, Pose, pose_from_quat
from shared.messages.frames import Frame
from shared.ros2.types import RosDecodeError, decode

log = logging.getLogger(__name__)

REASONS = (
    "bad_payload",
    "unknown_encoding",
    "unsupported_type",
    "no_camera_info",
    "size_mismatch",
    "out_of_order",
    "no_depth",
    "no_pose",
    "tf_missing",
    "tf_backwards",
    "superseded",
    "bad_pose",
)
"""Why a message (or a colour image's frame) was dropped: the status counters."""

CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
WARN_PERIOD_S = 5.0
"""At most one warning line per reason in this many seconds (of ``now``)."""
MAX_ORIGINS = 4096
"""Emitted frames whose stamp and camera frame :meth:`FrameAssembler.origin` still answers."""
RESET_AFTER_S = 1.0
"""A stream whose stamps keep going back for this long (of arrivals) means a new timeline."""
RESET_MIN_MESSAGES = 3
"""... and at least this many messages in a row went back (one stray message is no reset)."""
MAX_TF_FRAMES = 1024
"""Most TF child frames held (static and dynamic each); a TF message adding more is refused."""
MAX_POSE_SAMPLES = 4096
"""Most ``pose_topic`` samples held (pruned by time before that)."""
QUATERNION_TOLERANCE = 1e-2
"""|q|^2 may differ from 1 by this much (then q is normalised), as tf2 accepts."""

_NS = 1_000_000_000


def _stamp_ns(header: Any) -> int:
    """Header stamp in ns; ValueError for one no ROS clock can produce."""
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec < 0 or not 0 <= nsec < _NS:
        raise ValueError(f"invalid header stamp sec={sec} nanosec={nsec}")
    return sec * _NS + nsec


@dataclass
class LiveInputStats:
    """Counters of the live input, for the status book (:meth:`as_dict`).

    ``received[topic] == accepted[topic] + (rejections of its messages)``, and for the colour
    topic ``accepted`` is the frames emitted; ``pending`` colour images are still waiting."""

    received: dict[str, int] = field(default_factory=dict)
    """Messages handed in, by topic."""
    accepted: dict[str, int] = field(default_factory=dict)
    """Messages taken in, by topic (colour topic: emitted in a frame)."""
    emitted: int = 0
    """Frames returned by ``poll``."""
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REASONS, 0))
    """Messages (colour images: frames) dropped, by reason (:data:`REASONS`)."""
    pending: int = 0
    """Colour images waiting for their depth or pose."""
    last_stamp_s: float | None = None
    """Colour stamp of the last frame emitted (s), None before the first."""
    resets: int = 0
    """Times the stamps went back for good and the buffers were cleared."""

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able copy."""
        return {
            "received": dict(self.received),
            "accepted": dict(self.accepted),
            "emitted": self.emitted,
            "rejected": dict(self.rejected),
            "pending": self.pending,
            "last_stamp_s": self.last_stamp_s,
            "resets": self.resets,
        }


@dataclass(eq=False)  # identity: two messages are never "equal" (and numpy fields cannot say)
class _Image:
    """A decoded colour or depth message waiting to be paired (pixels not decoded yet)."""

    stamp_ns: int
    arrival: float
    msg: Any
    size: tuple[int, int]
    topic: str
    frame_id: str = ""

    @property
    def where(self) -> str:
        return f"{self.topic} at stamp {self.stamp_ns} ns"


@dataclass
class _Streak:
    """A stream whose stamps went back: since when (arrival time) and how many in a row."""

    since: float
    count: int = 0


class FrameAssembler:
    """Raw ROS 2 payloads in, synchronised :class:`Frame` s out; see the module docstring.

    ``distro`` picks the message definitions the payloads are decoded with
    (``Ros2LinkConfig.distro``); ``max_payload_bytes`` refuses a larger payload before
    parsing (``Ros2LinkConfig.max_payload_bytes``). Thread-safe: the link may call
    :meth:`on_message` from its callback threads while another thread polls.
    """

    def __init__(self, cfg: Ros2InputConfig, *, distro: str = "jazzy", max_payload_bytes: int = 64 * 2**20) -> None:
        self.cfg = cfg
        self.distro = distro
        self.max_payload_bytes = int(max_payload_bytes)
        self._lock = threading.RLock()
        # topic -> role; one topic has one role, the first that claims it.
        self._roles: dict[str, str] = {}
        roles = [
            ("rgb", cfg.rgb_topic), ("depth", cfg.depth_topic), ("camera_info", cfg.camera_info_topic),
            ("tf", cfg.tf_topic), ("tf_static", cfg.tf_static_topic), ("pose", cfg.pose_topic),
        ]  # fmt: skip
        for role, topic in roles:
            if topic is not None:
                self._roles.setdefault(topic, role)
        self._types = {
            "rgb": (cfg.rgb_type, *[t for t in COLOUR_TYPES if t != cfg.rgb_type]),
            "depth": (cfg.depth_type, *[t for t in DEPTH_TYPES if t != cfg.depth_type]),
            "camera_info": (CAMERA_INFO_TYPE,),
            "tf": (TF_TYPE,),
            "tf_static": (TF_TYPE,),
            "pose": (cfg.pose_type, *[t for t in POSE_TYPES if t != cfg.pose_type]),
        }
        self._world = normalize_frame(cfg.world_frame)
        self._slop_ns = int(round(cfg.slop_s * _NS))
        self._tol_ns = int(round(cfg.tf_tolerance_s * _NS))
        self._horizon_s = cfg.tf_buffer_s + cfg.max_wait_s
        self._horizon_ns = int(round(self._horizon_s * _NS))
        self.max_pending = max(4, 2 * math.ceil(cfg.max_wait_s * 60))
        """Most colour (and depth) images held waiting; a newer one pushes out the oldest."""
        self._stats = LiveInputStats(
            received=dict.fromkeys(self._roles, 0), accepted=dict.fromkeys(self._roles, 0)
        )
        self._colours: list[_Image] = []  # pending, sorted by stamp
        self._origins: dict[int, tuple[int, str]] = {}  # frame index -> (colour stamp ns, camera frame), the newest
        # Colour images that came before the first CameraInfo, held up to max_wait_s: over a
        # network the first image often beats its camera info by a few ms.
        self._before_info: list[tuple[str, Any, int, float]] = []  # (topic, msg, stamp, arrival)
        self._depths: list[_Image] = []  # unused, sorted by stamp
        self._info: tuple[float, float, float, float, int, int] | None = None  # fx fy cx cy w h
        self._tf = TfBuffer()
        self._tf_arrival: dict[str, float] = {}  # dynamic child -> last arrival
        # dynamic child -> stamp ranges [from, to] (to None: still open) where the link's
        # stamps jumped back and good samples are missing: frames there are tf_backwards.
        self._tf_back: dict[str, list[list[int | None]]] = {}
        self._pose_stamps: list[int] = []
        self._pose_T: list[Pose] = []
        self._streaks: dict[str, _Streak] = {}
        self._last_emitted_ns: int | None = None
        self._next_index = 0
        self._t0: float | None = None
        self._now = 0.0
        self._last_rx: dict[str, float] = {}
        self._colour_without_info_since: float | None = None
        self._errors: dict[str, str] = {}
        self._warned: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._once: set[str] = set()

    # -- public API -------------------------------------------------------------------------

    @property
    def subscriptions(self) -> dict[str, tuple[str, ...]]:
        """Topics to subscribe to and the ROS types accepted on each (configured type first):
        colour, depth, camera info, and the pose topic or else /tf and /tf_static."""
        wanted = ["rgb", "depth", "camera_info"] + (["pose"] if self.cfg.pose_topic else ["tf", "tf_static"])
        return {topic: self._types[role] for topic, role in self._roles.items() if role in wanted}

    def on_message(self, topic: str, payload: bytes | bytearray | memoryview, now: float, ros_type: str | None = None) -> None:
        """Take in one raw CDR payload of a configured topic that arrived at ``now``.

        ``ros_type``: the ROS type the key names (rmw_zenoh), None for the configured one.
        Never raises on what the payload holds: problems are counted and logged."""
        with self._lock:
            self._tick(now)
            role = self._roles.get(topic)
            if role is None:
                self._warn("unknown_topic", f"message on {topic!r}, which is none of the configured topics "
                           f"({', '.join(self._roles)}); ignored")  # fmt: skip
                return
            self._stats.received[topic] += 1
            self._last_rx[topic] = now
            try:
                self._dispatch(role, topic, payload, now, ros_type)
            except Exception as e:  # a bug must not take the source down with one message: count, log, go on
                self._stats.rejected["bad_payload"] += 1
                self._warn("unexpected", f"{topic}: message could not be handled ({type(e).__name__}: {e})", exc_info=True)

    def poll(self, now: float) -> list[Frame]:
        """Frames that became complete by ``now``, in stamp order (usually none or one)."""
        with self._lock:
            self._tick(now)
            frames = self._poll(now) if self._colours else []
            self._prune(now)  # after: how often poll is called must not change what it returns
            self._expire_before_info(now)
            self._stats.pending = len(self._colours) + len(self._before_info)
            return frames

    def _poll(self, now: float) -> list[Frame]:
        """Pair, resolve poses, drop what waited too long or was overtaken, emit."""
        depth_of = self._assign_depths()
        ready: list[tuple[_Image, _Image, Pose]] = []
        waiting: list[_Image] = []
        for c in list(self._colours):
            expired = now - c.arrival > self.cfg.max_wait_s
            d = depth_of.get(id(c))
            if d is None or not (expired or self._depth_final(c, d)):
                if expired:
                    self._drop(c, "no_depth", f"{c.where}: no depth on {self.cfg.depth_topic} within "
                               f"{self.cfg.slop_s} s of its stamp after waiting {self.cfg.max_wait_s} s")  # fmt: skip
                else:
                    waiting.append(c)
                continue
            state, value = self._pose_for(c, expired)
            if state == "ok":
                ready.append((c, d, value))
            elif state == "wait":
                waiting.append(c)
            else:
                self._drop(c, state, value)
        if ready:
            newest = ready[-1][0].stamp_ns
            for c in waiting:
                if c.stamp_ns < newest:
                    self._drop(c, "superseded", f"{c.where}: a newer colour image completed first; dropped (latest wins)")
        frames = []
        for c, d, T in ready:
            try:
                f = self._emit(c, d, T)
            except Exception as e:  # a decoder's surprise on hostile pixels must not end the source
                if c in self._colours:
                    self._colours.remove(c)
                self._stats.rejected["bad_payload"] += 1
                self._warn("unexpected", f"{c.where}: frame could not be built ({type(e).__name__}: {e})", exc_info=True)
                continue
            if f is not None:
                frames.append(f)
        return frames

    @property
    def stats(self) -> LiveInputStats:
        """A copy of the counters."""
        with self._lock:
            s = self._stats
            return LiveInputStats(
                received=dict(s.received), accepted=dict(s.accepted), emitted=s.emitted, rejected=dict(s.rejected),
                pending=len(self._colours) + len(self._before_info), last_stamp_s=self.last_stamp_s, resets=s.resets,
            )  # fmt: skip

    @property
    def last_stamp_s(self) -> float | None:
        """Colour stamp of the last frame emitted (s), None before the first."""
        return None if self._last_emitted_ns is None else self._last_emitted_ns / _NS

    def silent_topics(self, now: float, after_s: float = 2.0) -> list[str]:
        """Subscribed topics that received nothing for ``after_s`` (counted from the first call
        when they never did). /tf_static is latched: one message ever is enough."""
        with self._lock:
            self._tick(now)
            t0 = self._t0 if self._t0 is not None else now
            out = []
            for topic in self.subscriptions:
                last = self._last_rx.get(topic)
                if self._roles[topic] == "tf_static" and last is not None:
                    continue
                if now - (last if last is not None else t0) >= after_s:
                    out.append(topic)
            return out

    def origin(self, frame_index: int) -> tuple[int, str] | None:
        """Colour stamp (ns) and camera TF frame of an emitted frame (the newest MAX_ORIGINS)."""
        with self._lock:
            return self._origins.get(int(frame_index))

    def newest_stamp(self, child: str) -> int | None:
        """Stamp (ns) of the newest TF sample of ``child``'s dynamic link, None without one."""
        with self._lock:
            return self._tf.latest_stamp(normalize_frame(child))

    def transform(self, target: str, source: str, stamp_ns: int | None) -> np.ndarray | None:
        """``T_target_source`` from the TF buffer at ``stamp_ns`` (None: at the newest stamp
        every dynamic link on the way has), or None when TF cannot give it there."""
        with self._lock:
            try:
                if stamp_ns is None:
                    stamps = [self._tf.latest_stamp(e) for e in self._tf.dynamic_edges(target, source)]
                    if any(s is None for s in stamps):
                        return None
                    stamp_ns = min(stamps, default=0)
                return self._tf.lookup(target, source, stamp_ns, self._tol_ns, self._tol_ns)
            except LookupError:
                return None

    @property
    def error(self) -> str | None:
        """The problem that currently stops frames, as one line; None when there is none."""
        with self._lock:
            for key in ("camera_info", "tf", "size", "input", "sync"):
                if key in self._errors:
                    return self._errors[key]
            return None

    # -- intake -----------------------------------------------------------------------------

    def _dispatch(self, role: str, topic: str, payload: Any, now: float, ros_type: str | None) -> None:
        accepted = self._types[role]
        msg_type = ros_type or accepted[0]
        if msg_type not in accepted:
            self._reject("unsupported_type", topic, f"{topic} carries {msg_type}; expected {' or '.join(accepted)}")
            return
        try:
            msg = decode(payload, msg_type, self.distro, max_bytes=self.max_payload_bytes)
        except RosDecodeError as e:
            self._reject("bad_payload", topic, f"{topic}: {e}")
            return
        try:
            stamp = None if role == "tf" or role == "tf_static" else _stamp_ns(msg.header)
        except ValueError as e:
            self._reject("bad_payload", topic, f"{topic}: {msg_type} with {e}")
            return
        if role == "rgb":
            self._on_colour(topic, msg, stamp, now)
        elif role == "depth":
            self._on_depth(topic, msg, stamp, now)
        elif role == "camera_info":
            self._on_info(topic, msg)
        elif role == "pose":
            self._on_pose(topic, msg, stamp, now)
        else:
            self._on_tf(topic, msg, now, static=role == "tf_static")

    def _on_colour(self, topic: str, msg: Any, stamp: int, now: float) -> None:
        c = _Image(stamp, now, msg, (0, 0), topic, normalize_frame(self.cfg.camera_frame or str(msg.header.frame_id)))
        if not self._peek(c, "colour"):
            return
        if self._info is None:
            since = self._colour_without_info_since
            if since is None:
                since = self._colour_without_info_since = now
            if now - since >= self.cfg.camera_info_timeout_s:
                self._errors["camera_info"] = (
                    f"no sensor_msgs/CameraInfo on {self.cfg.camera_info_topic} after {now - since:.1f} s of colour images"
                )
            self._before_info.append((topic, msg, stamp, now))
            self._expire_before_info(now)
            self._stats.pending = len(self._colours) + len(self._before_info)
            return
        iw, ih = self._info[4], self._info[5]
        if (iw or c.size[0], ih or c.size[1]) != c.size:
            self._size_error(f"{c.where}: image is {c.size[0]}x{c.size[1]}, camera info on "
                             f"{self.cfg.camera_info_topic} says {iw}x{ih}")  # fmt: skip
            return
        if self._last_emitted_ns is not None and stamp <= self._last_emitted_ns:
            if not self._went_back("colour", now, self.cfg.rgb_topic):
                self._reject("out_of_order", topic, f"{c.where}: stamp is not newer than the last frame's "
                             f"({self._last_emitted_ns} ns); expected increasing stamps")  # fmt: skip
                return
        else:
            self._streaks.pop("colour", None)
        if any(p.stamp_ns == stamp for p in self._colours):
            self._reject("out_of_order", topic, f"{c.where}: a colour image with this stamp is already waiting (duplicate)")
            return
        bisect.insort(self._colours, c, key=lambda x: x.stamp_ns)
        while len(self._colours) > self.max_pending:
            self._drop(self._colours[0], "superseded", f"{self._colours[0].where}: more than {self.max_pending} colour "
                       "images waiting; the oldest is dropped")  # fmt: skip
        self._stats.pending = len(self._colours)

    def _on_depth(self, topic: str, msg: Any, stamp: int, now: float) -> None:
        d = _Image(stamp, now, msg, (0, 0), topic)
        if not self._peek(d, "depth"):
            return
        if self._last_emitted_ns is not None and stamp < self._last_emitted_ns - self._slop_ns:
            # No later colour (newer than the last frame) can be within slop of it.
            self._reject("out_of_order", topic, f"{d.where}: older than the last frame ({self._last_emitted_ns} ns) "
                         f"by more than slop_s={self.cfg.slop_s}; expected increasing stamps")  # fmt: skip
            return
        bisect.insort(self._depths, d, key=lambda x: x.stamp_ns)
        if len(self._depths) > self.max_pending:
            del self._depths[0]  # unused depth is no fault (depth often runs faster than colour)
        self._accept(topic)

    def _peek(self, im: _Image, role: str) -> bool:
        """Header checks of a colour or depth image (no pixel decoded); counts a failure."""
        try:
            im.size = peek_size(im.msg, role, im.where)
        except UnsupportedEncodingError as e:
            expected = "rgb8, bgr8, rgba8, bgra8, mono8, JPEG or PNG" if role == "colour" else "16UC1, 32FC1 or compressedDepth png"
            self._reject("unknown_encoding", im.topic, f"{e} (expected {expected})")
            return False
        except DatasetError as e:
            self._reject("bad_payload", im.topic, str(e))
            return False
        return True

    def _on_info(self, topic: str, msg: Any) -> None:
        k = [float(x) for x in msg.k]
        w, h = int(msg.width), int(msg.height)
        fx, fy, cx, cy = k[0], k[4], k[2], k[5]
        if not (all(math.isfinite(v) for v in (fx, fy, cx, cy)) and fx > 0 and fy > 0) or w > 65536 or h > 65536:
            text = (f"sensor_msgs/CameraInfo on {topic} has an invalid camera matrix K (fx={fx}, fy={fy}, cx={cx}, "
                    f"cy={cy}) or size {w}x{h}; is the camera calibrated?")  # fmt: skip
            if self._info is None:
                self._errors["camera_info"] = text
            self._reject("bad_payload", topic, text)
            return
        self._info = (fx, fy, cx, cy, w, h)
        self._colour_without_info_since = None
        self._errors.pop("camera_info", None)
        self._accept(topic)
        held, self._before_info = self._before_info, []
        for c_topic, c_msg, c_stamp, c_arrival in held:  # arrival kept: they wait no longer than max_wait_s in all
            self._on_colour(c_topic, c_msg, c_stamp, c_arrival)
        self._stats.pending = len(self._colours)

    def _expire_before_info(self, now: float) -> None:
        """Refuse held colour images older than max_wait_s, or past max_pending, as no_camera_info."""
        fresh = [now - h[3] <= self.cfg.max_wait_s for h in self._before_info]
        n_keep = min(sum(fresh), self.max_pending)  # arrivals only grow: the fresh ones are the newest
        for c_topic, _, c_stamp, _ in self._before_info[: len(self._before_info) - n_keep]:
            self._reject("no_camera_info", c_topic, f"{c_topic} at stamp {c_stamp} ns: no sensor_msgs/CameraInfo on "
                         f"{self.cfg.camera_info_topic} within max_wait_s={self.cfg.max_wait_s} s; "
                         "colour images are dropped until it comes")  # fmt: skip
        del self._before_info[: len(self._before_info) - n_keep]

    def _on_pose(self, topic: str, msg: Any, stamp: int, now: float) -> None:
        p = msg.pose if msg.__msgtype__ == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
        o, x = p.orientation, p.position
        where = f"{topic} at stamp {stamp} ns"
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                T = checked_pose(pose_from_quat(np.array([x.x, x.y, x.z]), np.array([o.w, o.x, o.y, o.z])), where)
        except (ValueError, DatasetError) as e:
            self._reject("bad_pose", topic, f"{where}: invalid pose ({e}); expected a finite position and unit quaternion")
            return
        frame = normalize_frame(str(msg.header.frame_id))
        if frame != self._world and "pose_frame" not in self._once:
            self._once.add("pose_frame")
            log.warning("ROS input: poses on %s are in frame %r, taken as world_frame %r", topic, frame, self._world)
        if self._pose_stamps and stamp < self._pose_stamps[-1] - self._tol_ns:
            if not self._went_back("pose", now, topic):
                self._reject("out_of_order", topic, f"{where}: older than the newest pose ({self._pose_stamps[-1]} ns) "
                             f"by more than tf_tolerance_s={self.cfg.tf_tolerance_s}; pose jumped back in time")  # fmt: skip
                return
        else:
            self._streaks.pop("pose", None)
        k = bisect.bisect_left(self._pose_stamps, stamp)
        if k < len(self._pose_stamps) and self._pose_stamps[k] == stamp:
            self._pose_T[k] = T  # a repeat of one stamp: the newest message wins
        else:
            self._pose_stamps.insert(k, stamp)
            self._pose_T.insert(k, T)
        self._accept(topic)

    def _on_tf(self, topic: str, msg: Any, now: float, static: bool) -> None:
        problem: tuple[str, str] | None = None
        for t in msg.transforms:
            parent, child = normalize_frame(str(t.header.frame_id)), normalize_frame(str(t.child_frame_id))
            try:
                stamp = _stamp_ns(t.header)
            except ValueError as e:
                problem = problem or ("bad_payload", f"{topic}: transform {parent!r} -> {child!r} has {e}")
                continue
            if not parent or not child or parent == child:
                problem = problem or ("bad_payload", f"{topic}: transform {parent!r} -> {child!r} needs two different "
                                      "non-empty frame ids")  # fmt: skip
                continue
            tr, rq = t.transform.translation, t.transform.rotation
            xyz, q = np.array([tr.x, tr.y, tr.z], np.float64), np.array([rq.w, rq.x, rq.y, rq.z], np.float64)
            with np.errstate(over="ignore", invalid="ignore"):
                n2 = float(q @ q)
            if not (np.isfinite(xyz).all() and math.isfinite(n2)) or abs(n2 - 1.0) > QUATERNION_TOLERANCE:
                problem = problem or ("bad_pose", f"{topic}: transform {parent!r} -> {child!r} at {stamp} ns is not a "
                                      f"finite translation and unit quaternion (|q|^2={n2:.6g})")  # fmt: skip
                continue
            q = q / math.sqrt(n2)
            if static:
                if child not in self._tf.static_frames() and len(self._tf.static_frames()) >= MAX_TF_FRAMES:
                    problem = problem or ("bad_payload", f"{topic}: more than {MAX_TF_FRAMES} static TF frames; "
                                          f"{child!r} refused")  # fmt: skip
                    continue
                self._tf.add(parent, child, stamp, xyz, q, static=True)
                continue
            if (why := self._tf_sample(topic, parent, child, stamp, xyz, q, now)) is not None:
                problem = problem or why
        if problem is not None:
            self._reject(problem[0], topic, problem[1])
        else:
            self._accept(topic)

    def _tf_sample(self, topic: str, parent: str, child: str, stamp: int, xyz: np.ndarray, q: np.ndarray, now: float) -> tuple[str, str] | None:
        """Add one dynamic transform; (reason, text) if it is refused."""
        newest = self._tf.latest_stamp(child)
        if newest is not None and stamp < newest - self._tol_ns:
            back = self._tf_back.setdefault(child, [])
            if not back or back[-1][1] is not None:
                back.append([newest, None])
                del back[:-8]
            if not self._went_back(f"tf:{child}", now, f"TF frame {child!r} on {topic}"):
                # tf2's words for it, so the line is recognised (and searched for) as what it is
                return ("out_of_order", f"TF_OLD_DATA ignoring data from the past for frame {child} at time "
                        f"{stamp / _NS:.6f} according to {topic}: older than the newest transform {parent} -> {child} "
                        f"({newest / _NS:.6f}) by more than tf_tolerance_s={self.cfg.tf_tolerance_s}; TF jumped back "
                        "in time (a bag loop, a simulator reset, or two publishers of one frame?)")  # fmt: skip
            newest = None  # _went_back cleared the buffer: a new timeline starts here
        self._streaks.pop(f"tf:{child}", None)
        back = self._tf_back.get(child)
        if back and back[-1][1] is None:
            back[-1][1] = stamp  # good samples again: the gap is closed
        if child not in self._tf_arrival and len(self._tf_arrival) >= MAX_TF_FRAMES:
            return ("bad_payload", f"{topic}: more than {MAX_TF_FRAMES} dynamic TF frames; {child!r} refused")
        self._tf_arrival[child] = now
        if newest is not None and stamp == newest:
            return None  # tf2's TF_REPEATED_DATA: the same sample again changes nothing
        old_parent = self._tf.dynamic_parent(child)
        if old_parent is not None and old_parent != parent:
            self._warn("tf_reparent", f"TF frame {child!r} re-parented from {old_parent!r} to {parent!r} on {topic}")
            self._tf.remove(child)  # the new parent's history starts now
        self._tf.add(parent, child, stamp, xyz, q, static=False)
        return None

    # -- sync -------------------------------------------------------------------------------

    def _assign_depths(self) -> dict[int, _Image]:
        """Pending colour (by id) -> its depth: nearest pairs first, each depth once."""
        if not self._depths:
            return {}
        cs = np.array([c.stamp_ns for c in self._colours], np.int64)
        ds = np.array([d.stamp_ns for d in self._depths], np.int64)
        dt = np.abs(cs[:, None] - ds[None, :])
        ci, di = np.nonzero(dt <= self._slop_ns)
        order = np.lexsort((cs[ci], dt[ci, di]))
        out: dict[int, _Image] = {}
        used: set[int] = set()
        for k in order:
            c, d = int(ci[k]), int(di[k])
            if id(self._colours[c]) in out or d in used:
                continue
            out[id(self._colours[c])] = self._depths[d]
            used.add(d)
        return out

    def _depth_final(self, c: _Image, d: _Image) -> bool:
        """No nearer depth can still come for ``c`` (depth arrives in stamp order)."""
        return self._depths[-1].stamp_ns >= c.stamp_ns + abs(c.stamp_ns - d.stamp_ns)

    def _pose_for(self, c: _Image, expired: bool) -> tuple[str, Any]:
        """("ok", T_world_cam), ("wait", None) or (reason, log text) for colour ``c``."""
        if self.cfg.pose_topic is not None:
            return self._pose_from_topic(c, expired)
        return self._pose_from_tf(c, expired)

    def _pose_from_topic(self, c: _Image, expired: bool) -> tuple[str, Any]:
        st = self._pose_stamps
        topic = self.cfg.pose_topic
        if not st:
            return ("no_pose", f"{c.where}: no pose on {topic} yet") if expired else ("wait", None)
        k = bisect.bisect_left(st, c.stamp_ns)
        best = min((j for j in (k - 1, k) if 0 <= j < len(st)), key=lambda j: abs(st[j] - c.stamp_ns))
        dt = abs(st[best] - c.stamp_ns)
        if dt <= self._slop_ns and (expired or st[-1] >= c.stamp_ns + dt):
            return ("ok", self._pose_T[best])
        if dt > self._slop_ns and (expired or st[-1] >= c.stamp_ns + self._slop_ns):
            return ("no_pose", f"{c.where}: no pose on {topic} within slop_s={self.cfg.slop_s} of its stamp "
                    f"(nearest {dt / _NS:.3f} s away)")  # fmt: skip
        return ("wait", None)

    def _pose_from_tf(self, c: _Image, expired: bool) -> tuple[str, Any]:
        world, cam = self._world, c.frame_id
        if not cam:
            return ("tf_missing", f"{c.where}: the colour header has no frame_id and camera_frame is not set")
        if cam == world:
            return ("ok", np.eye(4))
        known = self._tf.frames()
        missing = [f for f in (world, cam) if f not in known]
        if missing:
            if not expired:
                return ("wait", None)
            text = f"no frame {' or '.join(repr(f) for f in missing)} (known: {', '.join(sorted(known)) or 'none'})"
            self._errors["tf"] = f"TF: {text}"
            return ("tf_missing", f"{c.where}: TF has {text}")
        try:
            edges = self._tf.dynamic_edges(world, cam)
        except LookupError as e:
            if not expired:
                return ("wait", None)
            why = "are not connected" if "not connected" in str(e) else f"cannot be chained ({e})"
            self._errors["tf"] = f"TF: frames {world!r} and {cam!r} {why} (known: {', '.join(sorted(known))})"
            return ("tf_missing", f"{c.where}: {self._errors['tf']}")
        latest = {e: self._tf.latest_stamp(e) or 0 for e in edges}
        if not expired and any(s < c.stamp_ns for s in latest.values()):
            return ("wait", None)  # TF for this stamp is not there yet (TF often lags images)
        T = self._tf.lookup(world, cam, c.stamp_ns, self._tol_ns, self._tol_ns)
        if T is not None:
            self._errors.pop("tf", None)
            return ("ok", T)
        newest = ", ".join(f"{e} {s / _NS:.3f} s" for e, s in latest.items())
        if self._in_back_gap(edges, c.stamp_ns):
            return ("tf_backwards", f"{c.where}: TF jumped back in time on a link of {world} <- {cam}; "
                    f"no good transform for this stamp (newest per link: {newest})")  # fmt: skip
        return ("tf_missing", f"{c.where}: no TF {world} <- {cam} within tf_tolerance_s={self.cfg.tf_tolerance_s} "
                f"on both sides of the stamp (newest per link: {newest or 'static only'})")  # fmt: skip

    def _in_back_gap(self, edges: list[str], stamp: int) -> bool:
        """True if ``stamp`` falls where a link on the path jumped back in time and lacks
        good samples (the frame would have needed the refused ones)."""
        return any(a < stamp and (b is None or stamp < b) for e in edges for a, b in self._tf_back.get(e, ()))

    def _emit(self, c: _Image, d: _Image, T: Pose) -> Frame | None:
        self._colours.remove(c)
        if c.size != d.size:
            self._size_error(f"{d.where}: depth is {d.size[0]}x{d.size[1]}, colour {c.where} is "
                             f"{c.size[0]}x{c.size[1]} (publish depth aligned to colour)")  # fmt: skip
            return None
        fx, fy, cx, cy, iw, ih = self._info  # type: ignore[misc]  # colour is only taken in with camera info
        w, h = c.size
        if (iw or w, ih or h) != (w, h):
            self._size_error(f"{c.where}: image is {w}x{h}, camera info says {iw}x{ih}")
            return None
        try:
            T = checked_pose(T, f"{c.where}: pose from {self.cfg.pose_topic or f'TF {self._world} <- {c.frame_id}'}")
        except DatasetError as e:
            self._stats.rejected["bad_pose"] += 1
            self._warn("bad_pose", str(e))
            return None
        try:
            rgb = decode_colour(c.msg, c.where)
            depth, scale = decode_depth(d.msg, self.cfg.depth_scale, d.where)
        except UnsupportedEncodingError as e:
            self._stats.rejected["unknown_encoding"] += 1
            self._warn("unknown_encoding", str(e))
            return None
        except DatasetError as e:
            self._stats.rejected["bad_payload"] += 1
            self._warn("bad_payload", str(e))
            return None
        if rgb.shape[:2] != (h, w) or depth.shape != (h, w):
            self._size_error(f"{c.where}: decoded colour {rgb.shape[1]}x{rgb.shape[0]} and depth "
                             f"{depth.shape[1]}x{depth.shape[0]} differ from the header's {w}x{h}")  # fmt: skip
            return None
        try:
            frame = Frame(
                frame_index=self._next_index,
                time_s=c.stamp_ns / _NS,
                rgb=rgb,
                depth=depth,
                depth_scale=scale,
                intrinsics=Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h),
                T_world_cam=T,
            )
        except ValueError as e:  # what the checks above let through (a 70000-pixel-wide image, say)
            self._stats.rejected["bad_payload"] += 1
            self._warn("bad_payload", f"{c.where}: not a valid frame ({e})")
            return None
        self._origins[self._next_index] = (c.stamp_ns, c.frame_id)
        if len(self._origins) > MAX_ORIGINS:
            del self._origins[next(iter(self._origins))]
        self._next_index += 1
        self._last_emitted_ns = c.stamp_ns
        self._stats.emitted += 1
        self._accept(c.topic)
        for key in ("size", "input", "sync", "tf"):
            self._errors.pop(key, None)  # a frame went out: whatever stood in the way is gone
        self._depths.remove(d)
        # depth that no later colour (stamped after this frame) can be within slop of
        self._depths = [x for x in self._depths if x.stamp_ns >= c.stamp_ns - self._slop_ns]
        return frame

    # -- housekeeping -----------------------------------------------------------------------

    def _prune(self, now: float) -> None:
        keep = now - 2 * self.cfg.max_wait_s
        if self._depths and self._depths[0].arrival < keep:
            # a depth nobody claimed for a while goes, unless a waiting colour may still take it
            near = [c.stamp_ns for c in self._colours]
            self._depths = [d for d in self._depths
                            if d.arrival >= keep or any(abs(d.stamp_ns - t) <= self._slop_ns for t in near)]  # fmt: skip
        self._tf.prune(self._horizon_ns)
        for child, t in list(self._tf_arrival.items()):
            if now - t > self._horizon_s:  # the publisher went away: forget the link
                self._tf.remove(child)
                del self._tf_arrival[child]
                self._tf_back.pop(child, None)
                self._streaks.pop(f"tf:{child}", None)
        for child, gaps in list(self._tf_back.items()):
            newest = self._tf.latest_stamp(child)
            gaps[:] = [g for g in gaps if g[1] is None or newest is None or g[1] >= newest - self._horizon_ns]
        if self._pose_stamps:
            k = bisect.bisect_left(self._pose_stamps, self._pose_stamps[-1] - self._horizon_ns)
            k = max(k, len(self._pose_stamps) - MAX_POSE_SAMPLES)
            del self._pose_stamps[:k], self._pose_T[:k]

    def _went_back(self, stream: str, now: float, what: str) -> bool:
        """Count one message of ``stream`` stamped back in time; True (after clearing the
        buffers) when the stream has kept going back long enough to be a new timeline."""
        s = self._streaks.setdefault(stream, _Streak(now))
        s.count += 1
        if now - s.since <= RESET_AFTER_S or s.count < RESET_MIN_MESSAGES:
            return False
        self._reset(what)
        return True

    def _reset(self, what: str) -> None:
        log.warning(
            "ROS input: stamps of %s went back in time for over %.1f s of arrivals (a bag loop or a simulator reset?): "
            "cleared the TF buffer and the sync state; frames continue from the new timeline",
            what, RESET_AFTER_S,
        )  # fmt: skip
        for c in list(self._colours):
            self._drop(c, "out_of_order", f"{c.where}: dropped, the stamps went back in time")
        self._depths.clear()
        self._tf.clear(static=False)
        self._tf_arrival.clear()
        self._tf_back.clear()
        self._pose_stamps.clear()
        self._pose_T.clear()
        self._streaks.clear()
        self._last_emitted_ns = None
        self._stats.resets += 1

    def _tick(self, now: float) -> None:
        if self._t0 is None:
            self._t0 = now
        self._now = max(self._now, now)

    def _accept(self, topic: str) -> None:
        self._stats.accepted[topic] += 1

    def _reject(self, reason: str, topic: str, text: str) -> None:
        """Count a message refused at intake, with a rate-limited warning."""
        self._stats.rejected[reason] += 1
        if reason in ("unknown_encoding", "unsupported_type", "bad_payload") and self._roles[topic] in ("rgb", "depth", "pose"):
            self._errors["input"] = text  # until the next frame: a camera stuck on yuv422 shows here
        self._warn(reason, text)

    def _drop(self, c: _Image, reason: str, text: str) -> None:
        """Give up a pending colour image."""
        self._colours.remove(c)
        self._stats.rejected[reason] += 1
        if reason in ("no_depth", "no_pose", "tf_missing", "tf_backwards"):
            self._errors["sync"] = text  # until the next frame: depth or poses on another clock show here
        self._warn(reason, text)

    def _size_error(self, text: str) -> None:
        self._errors["size"] = text
        self._stats.rejected["size_mismatch"] += 1
        self._warn("size_mismatch", text)

    def _warn(self, key: str, text: str, exc_info: bool = False) -> None:
        """One warning line per ``key`` per WARN_PERIOD_S of ``now``, saying how many were held back."""
        last = self._warned.get(key)
        if last is not None and self._now - last < WARN_PERIOD_S:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        held = self._suppressed.pop(key, 0)
        self._warned[key] = self._now
        more = f" (+{held} more in the last {WARN_PERIOD_S:.0f} s)" if held else ""
        log.warning("ROS input [%s]: %s%s", key, text, more, exc_info=exc_info)
