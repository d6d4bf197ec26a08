"""Camera poses of the live input: the ``pose_topic`` samples, or TF.

A colour image's pose is TF ``world_frame <- camera frame`` interpolated between samples each
within ``tf_tolerance_s`` of its stamp, or the nearest ``pose_topic`` sample within ``slop_s``.
TF usually lags images, so a lookup says "wait" until the samples after the stamp are in or the
image has waited ``max_wait_s``. Memory is bounded: TF pruned to ``tf_buffer_s + max_wait_s``
per link, links silent for that long forgotten, at most :data:`MAX_TF_FRAMES` frame names and
:data:`MAX_POSE_SAMPLES` pose samples.
"""

from __future__ import annotations

import bisect
import math
from typing import Any

import numpy as np

from services.ros2.live.clock import NS, Timeline, header_stamp_ns
from services.ros2.live.stats import Ledger, log
from services.ros2.live.sync import PendingImage
from shared.config.ros2 import Ros2InputConfig
from shared.datasets.base import DatasetError
from shared.datasets.files import checked_pose
from shared.datasets.tf import TfBuffer, normalize_frame
from shared.geometry import Pose, pose_from_quat

TF_TYPE = "tf2_msgs/msg/TFMessage"
MAX_TF_FRAMES = 1024
"""Most TF child frames held (static and dynamic each); a TF message adding more is refused."""
MAX_POSE_SAMPLES = 4096
"""Most ``pose_topic`` samples held (pruned by time before that)."""
QUATERNION_TOLERANCE = 1e-2
"""|q|^2 may differ from 1 by this much (then q is normalised), as tf2 accepts."""


class Poses:
    """The TF buffer and the pose samples, and the pose of a colour image from them."""

    def __init__(self, cfg: Ros2InputConfig, ledger: Ledger, timeline: Timeline) -> None:
        self.cfg = cfg
        self.ledger = ledger
        self.timeline = timeline
        self.world = normalize_frame(cfg.world_frame)
        self.tf = TfBuffer()
        self._slop_ns = int(round(cfg.slop_s * NS))
        self._tol_ns = int(round(cfg.tf_tolerance_s * NS))
        self._horizon_s = cfg.tf_buffer_s + cfg.max_wait_s
        self._horizon_ns = int(round(self._horizon_s * NS))
        self._tf_arrival: dict[str, float] = {}  # dynamic child -> last arrival
        # dynamic child -> stamp ranges [from, to] (to None: still open) where the link's
        # stamps jumped back and good samples are missing: frames there are tf_backwards.
        self._tf_back: dict[str, list[list[int | None]]] = {}
        self._stamps: list[int] = []  # pose_topic samples, sorted
        self._T: list[Pose] = []
        self._pose_frame_told = False

    # -- intake -----------------------------------------------------------------------------

    def on_pose(self, topic: str, msg: Any, stamp: int, now: float) -> None:
        p = msg.pose if msg.__msgtype__ == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
        o, x = p.orientation, p.position
        where = f"{topic} at stamp {stamp} ns"
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                T = checked_pose(pose_from_quat(np.array([x.x, x.y, x.z]), np.array([o.w, o.x, o.y, o.z])), where)
        except (ValueError, DatasetError) as e:
            self.ledger.reject("bad_pose", topic, f"{where}: invalid pose ({e}); expected a finite position and unit quaternion")
            return
        frame = normalize_frame(str(msg.header.frame_id))
        if frame != self.world and not self._pose_frame_told:
            self._pose_frame_told = True
            log.warning("ROS input: poses on %s are in frame %r, taken as world_frame %r", topic, frame, self.world)
        if self._stamps and stamp < self._stamps[-1] - self._tol_ns:
            if not self.timeline.went_back("pose", now, topic):
                self.ledger.reject("out_of_order", topic, f"{where}: older than the newest pose ({self._stamps[-1]} ns) "
                                   f"by more than tf_tolerance_s={self.cfg.tf_tolerance_s}; pose jumped back in time")  # fmt: skip
                return
        else:
            self.timeline.forward("pose")
        k = bisect.bisect_left(self._stamps, stamp)
        if k < len(self._stamps) and self._stamps[k] == stamp:
            self._T[k] = T  # a repeat of one stamp: the newest message wins
        else:
            self._stamps.insert(k, stamp)
            self._T.insert(k, T)
        self.ledger.accept(topic)

    def on_tf(self, topic: str, msg: Any, now: float, static: bool) -> None:
        problem: tuple[str, str] | None = None
        for t in msg.transforms:
            parent, child = normalize_frame(str(t.header.frame_id)), normalize_frame(str(t.child_frame_id))
            try:
                stamp = header_stamp_ns(t.header)
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
                if child not in self.tf.static_frames() and len(self.tf.static_frames()) >= MAX_TF_FRAMES:
                    problem = problem or ("bad_payload", f"{topic}: more than {MAX_TF_FRAMES} static TF frames; "
                                          f"{child!r} refused")  # fmt: skip
                    continue
                self.tf.add(parent, child, stamp, xyz, q, static=True)
                continue
            if (why := self._tf_sample(topic, parent, child, stamp, xyz, q, now)) is not None:
                problem = problem or why
        if problem is not None:
            self.ledger.reject(problem[0], topic, problem[1])
        else:
            self.ledger.accept(topic)

    def _tf_sample(self, topic: str, parent: str, child: str, stamp: int, xyz: np.ndarray, q: np.ndarray, now: float) -> tuple[str, str] | None:
        """Add one dynamic transform (``xyz`` (3,), unit ``q`` (4,) wxyz); (reason, text) if it is refused."""
        newest = self.tf.latest_stamp(child)
        if newest is not None and stamp < newest - self._tol_ns:
            back = self._tf_back.setdefault(child, [])
            if not back or back[-1][1] is not None:
                back.append([newest, None])
                del back[:-8]
            if not self.timeline.went_back(f"tf:{child}", now, f"TF frame {child!r} on {topic}"):
                # tf2's words for it, so the line is recognised (and searched for) as what it is
                return ("out_of_order", f"TF_OLD_DATA ignoring data from the past for frame {child} at time "
                        f"{stamp / NS:.6f} according to {topic}: older than the newest transform {parent} -> {child} "
                        f"({newest / NS:.6f}) by more than tf_tolerance_s={self.cfg.tf_tolerance_s}; TF jumped back "
                        "in time (a bag loop, a simulator reset, or two publishers of one frame?)")  # fmt: skip
            newest = None  # the reset cleared the buffer: a new timeline starts here
        self.timeline.forward(f"tf:{child}")
        back = self._tf_back.get(child)
        if back and back[-1][1] is None:
            back[-1][1] = stamp  # good samples again: the gap is closed
        if child not in self._tf_arrival and len(self._tf_arrival) >= MAX_TF_FRAMES:
            return ("bad_payload", f"{topic}: more than {MAX_TF_FRAMES} dynamic TF frames; {child!r} refused")
        self._tf_arrival[child] = now
        if newest is not None and stamp == newest:
            return None  # tf2's TF_REPEATED_DATA: the same sample again changes nothing
        old_parent = self.tf.dynamic_parent(child)
        if old_parent is not None and old_parent != parent:
            self.ledger.warn("tf_reparent", f"TF frame {child!r} re-parented from {old_parent!r} to {parent!r} on {topic}")
            self.tf.remove(child)  # the new parent's history starts now
        self.tf.add(parent, child, stamp, xyz, q, static=False)
        return None

    # -- lookup -----------------------------------------------------------------------------

    def pose_for(self, c: PendingImage, expired: bool) -> tuple[str, Any]:
        """("ok", T_world_cam (4, 4)), ("wait", None) or (reason, log text) for colour ``c``."""
        if self.cfg.pose_topic is not None:
            return self._from_topic(c, expired)
        return self._from_tf(c, expired)

    def source(self, c: PendingImage) -> str:
        """Where the pose of colour ``c`` comes from, for a log line."""
        return self.cfg.pose_topic or f"TF {self.world} <- {c.frame_id}"

    def _from_topic(self, c: PendingImage, expired: bool) -> tuple[str, Any]:
        st = self._stamps
        topic = self.cfg.pose_topic
        if not st:
            return ("no_pose", f"{c.where}: no pose on {topic} yet") if expired else ("wait", None)
        k = bisect.bisect_left(st, c.stamp_ns)
        best = min((j for j in (k - 1, k) if 0 <= j < len(st)), key=lambda j: abs(st[j] - c.stamp_ns))
        dt = abs(st[best] - c.stamp_ns)
        if dt <= self._slop_ns and (expired or st[-1] >= c.stamp_ns + dt):
            return ("ok", self._T[best])
        if dt > self._slop_ns and (expired or st[-1] >= c.stamp_ns + self._slop_ns):
            return ("no_pose", f"{c.where}: no pose on {topic} within slop_s={self.cfg.slop_s} of its stamp "
                    f"(nearest {dt / NS:.3f} s away)")  # fmt: skip
        return ("wait", None)

    def _from_tf(self, c: PendingImage, expired: bool) -> tuple[str, Any]:
        world, cam, errors = self.world, c.frame_id, self.ledger.errors
        if not cam:
            return ("tf_missing", f"{c.where}: the colour header has no frame_id and camera_frame is not set")
        if cam == world:
            return ("ok", np.eye(4))
        known = self.tf.frames()
        missing = [f for f in (world, cam) if f not in known]
        if missing:
            if not expired:
                return ("wait", None)
            text = f"no frame {' or '.join(repr(f) for f in missing)} (known: {', '.join(sorted(known)) or 'none'})"
            errors["tf"] = f"TF: {text}"
            return ("tf_missing", f"{c.where}: TF has {text}")
        try:
            edges = self.tf.dynamic_edges(world, cam)
        except LookupError as e:
            if not expired:
                return ("wait", None)
            why = "are not connected" if "not connected" in str(e) else f"cannot be chained ({e})"
            errors["tf"] = f"TF: frames {world!r} and {cam!r} {why} (known: {', '.join(sorted(known))})"
            return ("tf_missing", f"{c.where}: {errors['tf']}")
        latest = {e: self.tf.latest_stamp(e) or 0 for e in edges}
        if not expired and any(s < c.stamp_ns for s in latest.values()):
            return ("wait", None)  # TF for this stamp is not there yet (TF often lags images)
        T = self.tf.lookup(world, cam, c.stamp_ns, self._tol_ns, self._tol_ns)
        if T is not None:
            errors.pop("tf", None)
            return ("ok", T)
        newest = ", ".join(f"{e} {s / NS:.3f} s" for e, s in latest.items())
        if self._in_back_gap(edges, c.stamp_ns):
            return ("tf_backwards", f"{c.where}: TF jumped back in time on a link of {world} <- {cam}; "
                    f"no good transform for this stamp (newest per link: {newest})")  # fmt: skip
        return ("tf_missing", f"{c.where}: no TF {world} <- {cam} within tf_tolerance_s={self.cfg.tf_tolerance_s} "
                f"on both sides of the stamp (newest per link: {newest or 'static only'})")  # fmt: skip

    def _in_back_gap(self, edges: list[str], stamp: int) -> bool:
        """True if ``stamp`` falls where a link on the path jumped back in time and lacks
        good samples (the frame would have needed the refused ones)."""
        return any(a < stamp and (b is None or stamp < b) for e in edges for a, b in self._tf_back.get(e, ()))

    def transform(self, target: str, source: str, stamp_ns: int | None) -> np.ndarray | None:
        """``T_target_source`` (4, 4) from the TF buffer at ``stamp_ns`` (None: at the newest
        stamp every dynamic link on the way has), or None when TF cannot give it there."""
        try:
            if stamp_ns is None:
                stamps = [self.tf.latest_stamp(e) for e in self.tf.dynamic_edges(target, source)]
                if any(s is None for s in stamps):
                    return None
                stamp_ns = min(stamps, default=0)
            return self.tf.lookup(target, source, stamp_ns, self._tol_ns, self._tol_ns)
        except LookupError:
            return None

    # -- housekeeping -----------------------------------------------------------------------

    def prune(self, now: float) -> None:
        """Forget TF and pose samples older than the horizon, and TF links silent that long."""
        self.tf.prune(self._horizon_ns)
        for child, t in list(self._tf_arrival.items()):
            if now - t > self._horizon_s:  # the publisher went away: forget the link
                self.tf.remove(child)
                del self._tf_arrival[child]
                self._tf_back.pop(child, None)
                self.timeline.forward(f"tf:{child}")
        for child, gaps in list(self._tf_back.items()):
            newest = self.tf.latest_stamp(child)
            gaps[:] = [g for g in gaps if g[1] is None or newest is None or g[1] >= newest - self._horizon_ns]
        if self._stamps:
            k = bisect.bisect_left(self._stamps, self._stamps[-1] - self._horizon_ns)
            k = max(k, len(self._stamps) - MAX_POSE_SAMPLES)
            del self._stamps[:k], self._T[:k]

    def reset(self) -> None:
        """A new timeline: the dynamic TF and the pose samples are forgotten (static TF stays)."""
        self.tf.clear(static=False)
        self._tf_arrival.clear()
        self._tf_back.clear()
        self._stamps.clear()
        self._T.clear()
