"""A minimal TF tree for replaying bags: static and time-stamped transforms, chained lookups.

Like tf2, a dynamic transform is interpolated between the samples that bracket the query
time (linear translation, slerp rotation). Unlike tf2, a query up to ``max_gap_ns`` outside
the recorded span takes the nearest sample instead of failing, because drivers often stamp
the first image a few milliseconds before the first odometry transform.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from shared.geometry import Pose, invert, pose_from_quat

log = logging.getLogger(__name__)

Quat = Annotated[np.ndarray, "(4,) w, x, y, z"]


def slerp(q0: Quat, q1: Quat, s: float) -> Quat:
    """Shortest-path spherical interpolation between unit quaternions, s in [0, 1]."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        # Nearly parallel: sin(theta) -> 0 makes the exact formula unstable.
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(d)
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


def normalize_frame(name: str) -> str:
    """ROS 1 era bags write '/map' where ROS 2 writes 'map'."""
    return name.lstrip("/")


@dataclass
class _Samples:
    parent: str
    stamps: list[int] = field(default_factory=list)
    t: list[np.ndarray] = field(default_factory=list)
    q: list[np.ndarray] = field(default_factory=list)


class TfBuffer:
    """Transforms parent <- child; ``lookup`` chains them through the common ancestor."""

    def __init__(self) -> None:
        self._static: dict[str, tuple[str, Pose]] = {}
        self._dynamic: dict[str, _Samples] = {}
        self._sorted = True

    def add(
        self,
        parent: str,
        child: str,
        stamp_ns: int,
        t_xyz: Annotated[np.ndarray, "(3,)"],
        q_wxyz: Quat,
        static: bool,
    ) -> None:
        """Record ``T_parent_child`` (the child's pose in the parent frame)."""
        parent, child = normalize_frame(parent), normalize_frame(child)
        if static:
            self._static[child] = (parent, pose_from_quat(t_xyz, q_wxyz))
            return
        s = self._dynamic.setdefault(child, _Samples(parent))
        if s.parent != parent:
            log.warning("TF frame %r re-parented from %r to %r; using %r", child, s.parent, parent, parent)
            self._dynamic[child] = s = _Samples(parent)
        s.stamps.append(int(stamp_ns))
        s.t.append(np.asarray(t_xyz, dtype=np.float64))
        s.q.append(np.asarray(q_wxyz, dtype=np.float64))
        self._sorted = False

    def frames(self) -> set[str]:
        names = set(self._static) | set(self._dynamic)
        names |= {p for p, _ in self._static.values()} | {s.parent for s in self._dynamic.values()}
        return names

    def _sort(self) -> None:
        for s in self._dynamic.values():
            order = np.argsort(s.stamps, kind="stable")
            s.stamps = [s.stamps[k] for k in order]
            s.t = [s.t[k] for k in order]
            s.q = [s.q[k] for k in order]
        self._sorted = True

    def _parent(self, child: str) -> str | None:
        if child in self._static:
            return self._static[child][0]
        return self._dynamic[child].parent if child in self._dynamic else None

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        while (p := self._parent(chain[-1])) is not None:
            if p in chain:
                raise LookupError(f"TF has a cycle through {p!r}")
            chain.append(p)
        return chain

    def _edge(self, child: str, stamp_ns: int, max_gap_ns: int) -> Pose | None:
        if child in self._static:
            return self._static[child][1]
        s = self._dynamic[child]
        k = int(np.searchsorted(s.stamps, stamp_ns))
        if k < len(s.stamps) and s.stamps[k] == stamp_ns:
            return pose_from_quat(s.t[k], s.q[k])
        if k == 0 or k == len(s.stamps):
            j = 0 if k == 0 else len(s.stamps) - 1
            return pose_from_quat(s.t[j], s.q[j]) if abs(s.stamps[j] - stamp_ns) <= max_gap_ns else None
        a = (stamp_ns - s.stamps[k - 1]) / (s.stamps[k] - s.stamps[k - 1])
        t = (1 - a) * s.t[k - 1] + a * s.t[k]
        return pose_from_quat(t, slerp(s.q[k - 1], s.q[k], a))

    def _to_ancestor(self, chain: list[str], ancestor: str, stamp_ns: int, max_gap_ns: int) -> Pose | None:
        T = np.eye(4)
        for frame in chain[: chain.index(ancestor)]:
            E = self._edge(frame, stamp_ns, max_gap_ns)
            if E is None:
                return None
            T = E @ T
        return T

    def lookup(self, target: str, source: str, stamp_ns: int, max_gap_ns: int) -> Pose | None:
        """``T_target_source`` at ``stamp_ns``; None when a dynamic link has no sample near it.

        Raises LookupError when the two frames are not in one tree.
        """
        if not self._sorted:
            self._sort()
        target, source = normalize_frame(target), normalize_frame(source)
        up_s, up_t = self._chain(source), self._chain(target)
        common = next((f for f in up_s if f in set(up_t)), None)
        if common is None:
            raise LookupError(f"TF frames {target!r} and {source!r} are not connected")
        T_common_source = self._to_ancestor(up_s, common, stamp_ns, max_gap_ns)
        T_common_target = self._to_ancestor(up_t, common, stamp_ns, max_gap_ns)
        if T_common_source is None or T_common_target is None:
            return None
        return invert(T_common_target) @ T_common_source
