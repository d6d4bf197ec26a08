"""Pose corrections from a ROS 2 robot's SLAM: what ``trackgraph source --ros2`` sends on
``poses/correction`` (``ros2.input.corrections``).

A live SLAM states its loop closures in one of two ways, and :class:`CorrectionBuilder` turns
either into the absolute :class:`~shared.messages.poses.PoseCorrection` fusion applies:

- ``path``: a ``nav_msgs/Path`` of optimised poses (rtabmap's ``mapPath``, a pose-graph
  optimiser's output), republished after each optimisation. Each pose of the Path states the
  camera pose of the published frame nearest its stamp (within ``slop_s``), through the
  camera's offset from ``corrections_body_frame`` at that frame; fusion moves the frames
  between two listed ones with the nearer one by their own odometry, as it does for any
  correction.
- ``map_odom``: the ``world_frame -> odom_frame`` transform (slam_toolbox, AMCL) jumps when
  the SLAM corrects the robot. The camera's odometry pose is drift that accumulated since the
  previous change, so the change is spread over the frames placed since then: none of it at
  the first of them, all of it at the newest, in proportion to the distance travelled (the
  classic linear distribution of a loop's error). Earlier frames keep what earlier
  corrections gave them.

Both keep the poses each frame was published with, and send a correction only when it moves
some camera by more than ``corrections_min_m`` / ``corrections_min_rad``, at most once per
``corrections_min_period_s``: each one costs fusion a pass over the map. Ids are the SLAM's
stamps in nanoseconds (forced to grow), so a restarted source still sends ids above the ones
fusion applied. No Zenoh here: :mod:`services.ros2.session` wires it.
"""

from __future__ import annotations

import bisect
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from shared.config.ros2 import Ros2InputConfig
from shared.datasets.tf import normalize_frame, slerp
from shared.geometry import Pose, invert, matrix_to_quat, pose_from_quat
from shared.messages.poses import PoseCorrection

log = logging.getLogger(__name__)

_NS = 1_000_000_000
Lookup = Callable[[str, str, int | None], "np.ndarray | None"]
"""``T_target_source`` at a stamp (ns; None: the newest), or None: :meth:`FrameAssembler.transform`."""
MAX_LISTED = 4096
"""Most frames one correction lists (a long run's would otherwise grow without bound); beyond
it every k-th frame is listed, the ends always, and fusion moves the rest with the nearer
listed frame by their odometry."""


@dataclass
class CorrectionStats:
    """What the builder did with the SLAM's messages."""

    sent: int = 0
    unchanged: int = 0
    """SLAM updates that moved no camera beyond the thresholds (nothing sent)."""
    unmatched: int = 0
    """Paths none of whose poses fell within ``slop_s`` of a published frame."""
    rejected: int = 0
    """Paths refused: wrong frame id, invalid poses, undecodable."""
    unplaced: int = 0
    """Frames TF could not place in ``odom_frame`` / ``corrections_body_frame`` (sent as they came)."""
    last_id: int | None = None

    def as_dict(self) -> dict:
        return {"sent": self.sent, "unchanged": self.unchanged, "unmatched": self.unmatched, "rejected": self.rejected,
                "unplaced": self.unplaced, "last_id": self.last_id}  # fmt: skip


@dataclass
class _Frames:
    index: list[int] = field(default_factory=list)
    stamp: list[int] = field(default_factory=list)
    raw: list[np.ndarray] = field(default_factory=list)  # T_world_cam as published
    ref: list[np.ndarray] = field(
        default_factory=list
    )  # T_body_cam (path) or T_odom_cam (map_odom)
    est: list[np.ndarray] = field(
        default_factory=list
    )  # T_world_cam as the last correction sent put it


class CorrectionBuilder:
    """Published frames in (:meth:`record`), SLAM updates in (:meth:`from_path`,
    :meth:`from_map_odom`), :class:`PoseCorrection` out (see the module docstring)."""

    def __init__(self, cfg: Ros2InputConfig) -> None:
        if cfg.corrections == "none":
            raise ValueError(
                "ros2.input.corrections is 'none': there is nothing to build corrections from"
            )
        self.cfg = cfg
        self.stats = CorrectionStats()
        self._f = _Frames()
        self._segment_start = 0  # map_odom: first frame placed since the last correction
        self._last_sent_at: float | None = None
        self._waiting: PoseCorrection | None = None  # built within the min period; sent after it
        self._pending_pos: tuple[list[int], np.ndarray] = ([], np.zeros((0, 4, 4)))
        self._M0: np.ndarray | None = None  # world -> odom at the first frame
        self._fix = np.eye(
            4
        )  # fusion's fix for new frames: the last listed frame's, as PoseBook keeps it
        self._slop_ns = int(round(cfg.slop_s * _NS))

    # -- frames ------------------------------------------------------------------------------

    def record(self, frame_index: int, stamp_ns: int, T_world_cam: Pose, T_ref_cam: Pose) -> None:
        """A frame went out with ``T_world_cam``, its odometry pose (:func:`odometry_pose`);
        ``T_ref_cam`` is the camera in ``corrections_body_frame`` (``path``; identity for camera
        poses) or in ``odom_frame`` (``map_odom``) at its stamp."""
        f = self._f
        if f.index and (frame_index <= f.index[-1] or stamp_ns <= f.stamp[-1]):
            raise ValueError(
                f"frame {frame_index} at {stamp_ns} ns is not after frame {f.index[-1]} at {f.stamp[-1]} ns"
            )
        f.index.append(int(frame_index))
        f.stamp.append(int(stamp_ns))
        f.raw.append(np.asarray(T_world_cam, np.float64).copy())
        f.ref.append(np.asarray(T_ref_cam, np.float64).copy())
        f.est.append(_rigid(self._fix @ f.raw[-1]))  # where fusion puts it (PoseBook: fix @ raw)

    def place(
        self, frame_index: int, stamp_ns: int, camera_frame: str, T_world_cam: Pose, lookup: Lookup
    ) -> Pose | None:
        """Record a frame about to go out and return the pose it goes out with (None: as it came).

        With an ``odom_frame``, frames go out at their odometry pose, ``M0 @ T_odom_cam``
        (``M0``: ``world -> odom`` at the first frame): a SLAM's map -> odom jumps reach the map
        as corrections only, and fusion's fix for later frames would otherwise count them twice.
        ``lookup(target, source, stamp_ns)`` is the TF buffer's (:meth:`FrameAssembler.transform`).
        A frame TF cannot place so is sent as it came and not recorded (counted, logged)."""
        cfg = self.cfg
        T = np.asarray(T_world_cam, np.float64)
        pose = T
        if cfg.odom_frame is not None:
            T_odom_cam = lookup(cfg.odom_frame, camera_frame, stamp_ns)
            if T_odom_cam is None:
                return self._unplaced(frame_index, f"no TF {cfg.odom_frame} <- {camera_frame}")
            if self._M0 is None:
                self._M0 = T @ invert(T_odom_cam)
            pose = _rigid(self._M0 @ T_odom_cam)
        if cfg.corrections == "map_odom":
            ref = invert(self._M0) @ pose  # T_odom_cam
        elif cfg.corrections_body_frame is not None:
            ref = lookup(cfg.corrections_body_frame, camera_frame, stamp_ns)
            if ref is None:
                return self._unplaced(
                    frame_index, f"no TF {cfg.corrections_body_frame} <- {camera_frame}"
                )
        else:
            ref = np.eye(4)
        self.record(frame_index, stamp_ns, pose, ref)
        return pose

    def _unplaced(self, frame_index: int, why: str) -> Pose | None:
        self.stats.unplaced += 1
        if self.stats.unplaced == 1 or self.stats.unplaced % 100 == 0:
            log.warning("pose corrections: frame %d cannot be tracked (%s; %d so far); it goes out as it came and "
                        "corrections will not move it", frame_index, why, self.stats.unplaced)  # fmt: skip
        return None

    @property
    def frames(self) -> int:
        return len(self._f.index)

    # -- path ----------------------------------------------------------------------------------

    def from_path(
        self,
        stamps_ns: Annotated[np.ndarray, "(N,) int64 ns"],
        T_world_body: Annotated[np.ndarray, "(N, 4, 4) poses of corrections_body_frame"],
        now: float,
        path_stamp_ns: int = 0,
    ) -> PoseCorrection | None:
        """The correction an optimised Path states, or None (nothing to send now)."""
        f = self._f
        stamps_ns = np.asarray(stamps_ns, np.int64)
        if len(stamps_ns) == 0 or not f.index:
            self.stats.unmatched += 1
            return self._flush(now)
        order = np.argsort(stamps_ns, kind="stable")
        chosen: dict[int, tuple[int, int]] = {}  # frame position -> (|dt|, path pose)
        fs = f.stamp
        for j in order:
            st = int(stamps_ns[j])
            k = bisect.bisect_left(fs, st)
            near = [i for i in (k - 1, k) if 0 <= i < len(fs)]
            i = min(near, key=lambda i: abs(fs[i] - st))
            dt = abs(fs[i] - st)
            if dt <= self._slop_ns and (i not in chosen or dt < chosen[i][0]):
                chosen[i] = (dt, int(j))
        if not chosen:
            self.stats.unmatched += 1
            return self._flush(now)
        pos = sorted(chosen)
        poses = np.stack([_rigid(T_world_body[chosen[i][1]] @ f.ref[i]) for i in pos])
        newest = max(int(stamps_ns.max()), int(path_stamp_ns))
        return self._offer(pos, poses, newest, now)

    # -- map -> odom ---------------------------------------------------------------------------

    def from_map_odom(self, T_world_odom: Pose, stamp_ns: int, now: float) -> PoseCorrection | None:
        """The correction a ``world -> odom`` transform of ``stamp_ns`` states, or None."""
        f = self._f
        n = len(f.index)
        if n == 0 or self._segment_start >= n:
            return self._flush(now)
        seg = range(self._segment_start, n)
        start_fix = f.est[seg[0]] @ invert(f.raw[seg[0]])  # what the segment's first frame had
        new_end = _rigid(T_world_odom @ f.ref[n - 1])
        end_fix = new_end @ invert(f.raw[n - 1])
        # Distance travelled along the segment, the weight of each frame's share of the change.
        xyz = np.stack([f.raw[i][:3, 3] for i in seg])
        run = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
        share = (
            run / run[-1]
            if run[-1] > 1e-9
            else np.linspace(0.0, 1.0, len(seg))
            if len(seg) > 1
            else np.ones(1)
        )
        new = [
            _rigid(_blend(start_fix, end_fix, float(a)) @ f.raw[i])
            for i, a in zip(seg, share, strict=True)
        ]
        pos = list(range(n))
        poses = np.stack([f.est[i] for i in range(seg[0])] + new)
        out = self._offer(pos, poses, int(stamp_ns), now)
        return out

    # -- sending -------------------------------------------------------------------------------

    def _offer(
        self, pos: list[int], poses: np.ndarray, stamp_ns: int, now: float
    ) -> PoseCorrection | None:
        f = self._f
        moved_m, moved_rad = 0.0, 0.0
        for i, P in zip(pos, poses, strict=True):
            d = invert(f.est[i]) @ P
            moved_m = max(moved_m, float(np.linalg.norm(P[:3, 3] - f.est[i][:3, 3])))
            moved_rad = max(
                moved_rad, float(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1.0, 1.0)))
            )
        if moved_m <= self.cfg.corrections_min_m and moved_rad <= self.cfg.corrections_min_rad:
            self.stats.unchanged += 1
            self._waiting = None  # the SLAM went back to what the map has
            return None
        keep = _thin(len(pos))
        pos_k = [pos[k] for k in keep]
        last_id = self.stats.last_id if self._waiting is None else self._waiting.correction_id
        cid = max(int(stamp_ns), -1 if last_id is None else last_id + 1)
        frames = np.asarray([f.index[i] for i in pos_k], np.int64)
        c = PoseCorrection(correction_id=cid, frame_index=f.index[-1], frames=frames, poses=poses[keep],
                           apply_after_frame=f.index[-1])  # fmt: skip
        self._waiting = c
        self._pending_pos = (pos, poses)
        return self._flush(now)

    def _flush(self, now: float) -> PoseCorrection | None:
        """The waiting correction, if the minimum period since the last one has passed."""
        c = self._waiting
        if c is None:
            return None
        if (
            self._last_sent_at is not None
            and now - self._last_sent_at < self.cfg.corrections_min_period_s
        ):
            return None
        self._waiting = None
        self._last_sent_at = now
        pos, poses = self._pending_pos
        for i, P in zip(pos, poses, strict=True):
            self._f.est[i] = P
        self._fix = poses[-1] @ invert(self._f.raw[pos[-1]])
        self._segment_start = len(self._f.index)
        self.stats.sent += 1
        self.stats.last_id = c.correction_id
        log.info(
            "pose correction %d: %d frames up to frame %d",
            c.correction_id,
            len(c.frames),
            c.frame_index,
        )
        return c

    def due(self, now: float) -> PoseCorrection | None:
        """A correction held back by ``corrections_min_period_s`` that may go now, else None."""
        return self._flush(now)


def read_path(
    msg: Any, world_frame: str
) -> tuple[Annotated[np.ndarray, "(N,) int64 ns"], Annotated[np.ndarray, "(N, 4, 4)"], int]:
    """Stamps, poses and header stamp (ns) of a decoded ``nav_msgs/Path``. Raises ValueError
    naming the field when its frame is not ``world_frame`` or a pose is not finite and unit."""
    world = normalize_frame(world_frame)
    frame = normalize_frame(str(msg.header.frame_id))
    if frame and frame != world:
        raise ValueError(
            f"nav_msgs/Path header.frame_id is {frame!r}; expected the world frame {world!r}"
        )
    stamps, poses = [], []
    for k, ps in enumerate(msg.poses):
        pf = normalize_frame(str(ps.header.frame_id))
        if pf and pf != world:
            raise ValueError(
                f"nav_msgs/Path poses[{k}].header.frame_id is {pf!r}; expected {world!r}"
            )
        p, o = ps.pose.position, ps.pose.orientation
        t = np.array([p.x, p.y, p.z], np.float64)
        q = np.array([o.w, o.x, o.y, o.z], np.float64)
        n = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else float("nan")
        if not (np.all(np.isfinite(t)) and abs(n - 1.0) < 1e-3):
            raise ValueError(
                f"nav_msgs/Path poses[{k}].pose is not a finite position and unit quaternion"
            )
        stamps.append(int(ps.header.stamp.sec) * _NS + int(ps.header.stamp.nanosec))
        poses.append(pose_from_quat(t, q / n))
    head = int(msg.header.stamp.sec) * _NS + int(msg.header.stamp.nanosec)
    return np.asarray(stamps, np.int64), np.stack(poses) if poses else np.zeros((0, 4, 4)), head


def _thin(n: int) -> list[int]:
    """Positions of ``n`` listed frames to keep: all up to MAX_LISTED, else evenly spaced with both ends."""
    if n <= MAX_LISTED:
        return list(range(n))
    return sorted(set(np.linspace(0, n - 1, MAX_LISTED).round().astype(int).tolist()))


def _blend(A: Pose, B: Pose, a: float) -> Pose:
    """The rigid transform a of the way from A to B (linear translation, slerp rotation)."""
    q = slerp(matrix_to_quat(A[:3, :3]), matrix_to_quat(B[:3, :3]), a)
    return pose_from_quat((1 - a) * A[:3, 3] + a * B[:3, 3], q)


def _rigid(T: np.ndarray) -> Pose:
    """``T`` with its rotation re-orthonormalised (products of many poses drift off rigid)."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    R = u @ vt
    if np.linalg.det(R) < 0:
        u[:, -1] *= -1
        R = u @ vt
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, T[:3, 3]
    return out
