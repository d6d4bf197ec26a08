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
one reason of :data:`~services.ros2.live.stats.REASONS` (:attr:`LiveInputStats.rejected`),
or, for colour images, still pending. Each reason is logged at most once per
:data:`~services.ros2.live.stats.WARN_PERIOD_S` (naming the topic and what was expected);
:attr:`FrameAssembler.error` holds the problem that currently stops frames, if any, and
:meth:`FrameAssembler.silent_topics` the topics that went quiet.

Stamps that go back in time (a bag played in a loop, a simulator reset) are refused as
``out_of_order`` (for TF, like tf2's TF_OLD_DATA); when a stream keeps going back for more
than :data:`~services.ros2.live.clock.RESET_AFTER_S` of arrivals, the TF buffer and the
sync state are cleared and the new timeline is taken from there.

Memory is bounded: a few pending colour and depth messages (decoded CDR, pixels decoded only
when a frame is complete), TF pruned to ``tf_buffer_s + max_wait_s`` per link, links silent
for that long forgotten, and at most :data:`~services.ros2.live.poses.MAX_TF_FRAMES` frame
names.

The parts, each holding its own state: :mod:`.sync` (colour/depth pairing),
:mod:`.camera_info`, :mod:`.poses` (the pose topic, TF), :mod:`.clock` (stamps, timeline
resets), :mod:`.stats` (counters, current problems, warning lines) and :mod:`.frames` (a
complete pair decoded into a frame). :class:`FrameAssembler` routes messages to them.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from services.ros2.live.camera_info import CAMERA_INFO_TYPE, CameraInfoGate
from services.ros2.live.clock import NS, RESET_AFTER_S, Timeline, header_stamp_ns
from services.ros2.live.frames import build_frame
from services.ros2.live.poses import TF_TYPE, Poses
from services.ros2.live.stats import REASONS, Ledger, LiveInputStats, log
from services.ros2.live.sync import Pairing, PendingImage
from shared.config.ros2 import COLOUR_TYPES, DEPTH_TYPES, POSE_TYPES, Ros2InputConfig
from shared.datasets.tf import normalize_frame
from shared.geometry import Pose
from shared.messages.frames import Frame
from shared.ros2.types import RosDecodeError, decode

__all__ = ["REASONS", "FrameAssembler", "LiveInputStats"]

MAX_ORIGINS = 4096
"""Emitted frames whose stamp and camera frame :meth:`FrameAssembler.origin` still answers."""


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
        self.max_pending = max(4, 2 * math.ceil(cfg.max_wait_s * 60))
        """Most colour (and depth) images held waiting; a newer one pushes out the oldest."""
        self._ledger = Ledger(self._roles)
        self._timeline = Timeline(self._reset)
        self._camera = CameraInfoGate(cfg, self._ledger, self.max_pending)
        self._sync = Pairing(cfg, self._ledger, self._timeline, self.max_pending)
        self._poses = Poses(cfg, self._ledger, self._timeline)
        self._origins: dict[int, tuple[int, str]] = {}  # frame index -> (colour stamp ns, camera frame), the newest
        self._next_index = 0
        self._last_rx: dict[str, float] = {}

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
            self._ledger.tick(now)
            role = self._roles.get(topic)
            if role is None:
                self._ledger.warn("unknown_topic", f"message on {topic!r}, which is none of the configured topics "
                                  f"({', '.join(self._roles)}); ignored")  # fmt: skip
                return
            self._ledger.stats.received[topic] += 1
            self._last_rx[topic] = now
            try:
                self._dispatch(role, topic, payload, now, ros_type)
            except Exception as e:  # a bug must not take the source down with one message: count, log, go on
                self._ledger.count("bad_payload", f"{topic}: message could not be handled ({type(e).__name__}: {e})",
                                   key="unexpected", exc_info=True)  # fmt: skip

    def poll(self, now: float) -> list[Frame]:
        """Frames that became complete by ``now``, in stamp order (usually none or one)."""
        with self._lock:
            self._ledger.tick(now)
            frames = self._poll(now) if self._sync.colours else []
            # after: how often poll is called must not change what it returns
            self._sync.prune(now)
            self._poses.prune(now)
            self._camera.expire(now)
            return frames

    @property
    def stats(self) -> LiveInputStats:
        """A copy of the counters."""
        with self._lock:
            s = self._ledger.stats
            return LiveInputStats(
                received=dict(s.received), accepted=dict(s.accepted), emitted=s.emitted, rejected=dict(s.rejected),
                pending=len(self._sync.colours) + len(self._camera.held), last_stamp_s=self.last_stamp_s,
                resets=s.resets,
            )  # fmt: skip

    @property
    def last_stamp_s(self) -> float | None:
        """Colour stamp of the last frame emitted (s), None before the first."""
        last = self._sync.last_emitted_ns
        return None if last is None else last / NS

    def silent_topics(self, now: float, after_s: float = 2.0) -> list[str]:
        """Subscribed topics that received nothing for ``after_s`` (counted from the first call
        when they never did). /tf_static is latched: one message ever is enough."""
        with self._lock:
            self._ledger.tick(now)
            t0 = self._ledger.t0 if self._ledger.t0 is not None else now
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
            return self._poses.tf.latest_stamp(normalize_frame(child))

    def transform(self, target: str, source: str, stamp_ns: int | None) -> np.ndarray | None:
        """``T_target_source`` (4, 4) from the TF buffer at ``stamp_ns`` (None: at the newest
        stamp every dynamic link on the way has), or None when TF cannot give it there."""
        with self._lock:
            return self._poses.transform(target, source, stamp_ns)

    @property
    def error(self) -> str | None:
        """The problem that currently stops frames, as one line; None when there is none."""
        with self._lock:
            return self._ledger.error

    # -- intake -----------------------------------------------------------------------------

    def _dispatch(self, role: str, topic: str, payload: Any, now: float, ros_type: str | None) -> None:
        accepted = self._types[role]
        msg_type = ros_type or accepted[0]
        if msg_type not in accepted:
            self._ledger.reject("unsupported_type", topic, f"{topic} carries {msg_type}; expected {' or '.join(accepted)}")
            return
        try:
            msg = decode(payload, msg_type, self.distro, max_bytes=self.max_payload_bytes)
        except RosDecodeError as e:
            self._ledger.reject("bad_payload", topic, f"{topic}: {e}")
            return
        try:
            stamp = None if role == "tf" or role == "tf_static" else header_stamp_ns(msg.header)
        except ValueError as e:
            self._ledger.reject("bad_payload", topic, f"{topic}: {msg_type} with {e}")
            return
        if role == "rgb":
            self._on_colour(topic, msg, stamp, now)
        elif role == "depth":
            self._sync.on_depth(topic, msg, stamp, now)
        elif role == "camera_info":
            for held in self._camera.on_info(topic, msg):
                self._on_colour(*held)
        elif role == "pose":
            self._poses.on_pose(topic, msg, stamp, now)
        else:
            self._poses.on_tf(topic, msg, now, static=role == "tf_static")

    def _on_colour(self, topic: str, msg: Any, stamp: int, now: float) -> None:
        c = PendingImage(stamp, now, msg, (0, 0), topic, normalize_frame(self.cfg.camera_frame or str(msg.header.frame_id)))
        if not self._sync.peek(c, "colour"):
            return
        if self._camera.info is None:
            self._camera.hold(topic, msg, stamp, now)
            return
        if self._camera.size_differs(c.size):
            iw, ih = self._camera.info[4], self._camera.info[5]
            self._ledger.size_error(f"{c.where}: image is {c.size[0]}x{c.size[1]}, camera info on "
                                    f"{self.cfg.camera_info_topic} says {iw}x{ih}")  # fmt: skip
            return
        self._sync.add_colour(c, now)

    # -- output -----------------------------------------------------------------------------

    def _poll(self, now: float) -> list[Frame]:
        """Pair, resolve poses, drop what waited too long or was overtaken, emit."""
        sync = self._sync
        depth_of = sync.assign_depths()
        ready: list[tuple[PendingImage, PendingImage, Pose]] = []
        waiting: list[PendingImage] = []
        for c in list(sync.colours):
            expired = now - c.arrival > self.cfg.max_wait_s
            d = depth_of.get(id(c))
            if d is None or not (expired or sync.depth_final(c, d)):
                if expired:
                    sync.drop(c, "no_depth", f"{c.where}: no depth on {self.cfg.depth_topic} within "
                              f"{self.cfg.slop_s} s of its stamp after waiting {self.cfg.max_wait_s} s")  # fmt: skip
                else:
                    waiting.append(c)
                continue
            state, value = self._poses.pose_for(c, expired)
            if state == "ok":
                ready.append((c, d, value))
            elif state == "wait":
                waiting.append(c)
            else:
                sync.drop(c, state, value)
        if ready:
            newest = ready[-1][0].stamp_ns
            for c in waiting:
                if c.stamp_ns < newest:
                    sync.drop(c, "superseded", f"{c.where}: a newer colour image completed first; dropped (latest wins)")
        frames = []
        for c, d, T in ready:
            try:
                f = self._emit(c, d, T)
            except Exception as e:  # a decoder's surprise on hostile pixels must not end the source
                if c in sync.colours:
                    sync.colours.remove(c)
                self._ledger.count("bad_payload", f"{c.where}: frame could not be built ({type(e).__name__}: {e})",
                                   key="unexpected", exc_info=True)  # fmt: skip
                continue
            if f is not None:
                frames.append(f)
        return frames

    def _emit(self, c: PendingImage, d: PendingImage, T: Pose) -> Frame | None:
        self._sync.colours.remove(c)
        frame = build_frame(self._next_index, c, d, T, self._camera, self.cfg.depth_scale, self._poses.source(c), self._ledger)
        if frame is None:
            return None
        self._origins[self._next_index] = (c.stamp_ns, c.frame_id)
        if len(self._origins) > MAX_ORIGINS:
            del self._origins[next(iter(self._origins))]
        self._next_index += 1
        self._ledger.emitted(c.topic)
        self._sync.emitted(c, d)
        return frame

    def _reset(self, what: str) -> None:
        """The stamps of ``what`` went back for good: clear TF and the sync state."""
        log.warning(
            "ROS input: stamps of %s went back in time for over %.1f s of arrivals (a bag loop or a simulator reset?): "
            "cleared the TF buffer and the sync state; frames continue from the new timeline",
            what, RESET_AFTER_S,
        )  # fmt: skip
        self._sync.reset()
        self._poses.reset()
        self._timeline.clear()
        self._ledger.stats.resets += 1
