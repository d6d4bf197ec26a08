"""A minimal TF tree for replaying bags: static and time-stamped transforms, chained lookups.

Like tf2, a dynamic transform is interpolated between the samples that bracket the query
time (linear translation, slerp rotation). Unlike tf2, a query up to ``max_gap_ns`` outside
the recorded span takes the nearest sample instead of failing, because drivers often stamp
the first image a few milliseconds before the first odometry transform.

For a live stream (the ROS 2 source's frame assembler) the buffer also answers which dynamic edges a
lookup needs and how new each one is, refuses to interpolate across a gap wider than a
tolerance (``max_bracket_ns``), and forgets old samples (:meth:`TfBuffer.prune`), so its
memory stays bounded however long the robot runs.
"""

from __future__ import annotations

import bisect
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
        stamp_ns = int(stamp_ns)
        if s.stamps and stamp_ns < s.stamps[-1]:
            self._sorted = False  # sorted lazily, once, before the next lookup (bags interleave topics)
        s.stamps.append(stamp_ns)
        s.t.append(np.asarray(t_xyz, dtype=np.float64))
        s.q.append(np.asarray(q_wxyz, dtype=np.float64))

    def frames(self) -> set[str]:
        """Every frame name the buffer knows, as parent or child."""
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

    def _edge(self, child: str, stamp_ns: int, max_gap_ns: int, max_bracket_ns: int | None = None) -> Pose | None:
        if child in self._static:
            return self._static[child][1]
        s = self._dynamic[child]
        k = bisect.bisect_left(s.stamps, stamp_ns)
        if k < len(s.stamps) and s.stamps[k] == stamp_ns:
            return pose_from_quat(s.t[k], s.q[k])
        if k == 0 or k == len(s.stamps):
            j = 0 if k == 0 else len(s.stamps) - 1
            return pose_from_quat(s.t[j], s.q[j]) if abs(s.stamps[j] - stamp_ns) <= max_gap_ns else None
        if max_bracket_ns is not None and max(stamp_ns - s.stamps[k - 1], s.stamps[k] - stamp_ns) > max_bracket_ns:
            return None  # a gap in the stream: interpolating across it would invent motion
        a = (stamp_ns - s.stamps[k - 1]) / (s.stamps[k] - s.stamps[k - 1])
        t = (1 - a) * s.t[k - 1] + a * s.t[k]
        return pose_from_quat(t, slerp(s.q[k - 1], s.q[k], a))

    def _to_ancestor(
        self, chain: list[str], ancestor: str, stamp_ns: int, max_gap_ns: int, max_bracket_ns: int | None = None
    ) -> Pose | None:
        T = np.eye(4)
        for frame in chain[: chain.index(ancestor)]:
            E = self._edge(frame, stamp_ns, max_gap_ns, max_bracket_ns)
            if E is None:
                return None
            T = E @ T
        return T

    def _path(self, target: str, source: str) -> tuple[list[str], list[str], str]:
        """Chains up from ``source`` and ``target`` and their first common frame."""
        up_s, up_t = self._chain(source), self._chain(target)
        common = next((f for f in up_s if f in set(up_t)), None)
        if common is None:
            raise LookupError(f"TF frames {target!r} and {source!r} are not connected")
        return up_s, up_t, common

    def lookup(
        self, target: str, source: str, stamp_ns: int, max_gap_ns: int, max_bracket_ns: int | None = None
    ) -> Pose | None:
        """``T_target_source`` at ``stamp_ns``; None when a dynamic link has no sample near it.

        ``max_gap_ns``: how far before the first or after the last sample of a dynamic link
        its nearest sample still answers. ``max_bracket_ns`` (None: no limit): interpolate
        only between samples that are each at most this far from ``stamp_ns``.
        Raises LookupError when the two frames are not in one tree.
        """
        if not self._sorted:
            self._sort()
        target, source = normalize_frame(target), normalize_frame(source)
        up_s, up_t, common = self._path(target, source)
        T_common_source = self._to_ancestor(up_s, common, stamp_ns, max_gap_ns, max_bracket_ns)
        T_common_target = self._to_ancestor(up_t, common, stamp_ns, max_gap_ns, max_bracket_ns)
        if T_common_source is None or T_common_target is None:
            return None
        return invert(T_common_target) @ T_common_source

    # -- live streams: what a lookup needs, how new it is, and forgetting -------------------

    def dynamic_edges(self, target: str, source: str) -> list[str]:
        """Child frames of the dynamic links a ``target <- source`` lookup goes through
        (static links never lack a sample). Raises LookupError when not in one tree."""
        target, source = normalize_frame(target), normalize_frame(source)
        up_s, up_t, common = self._path(target, source)
        links = up_s[: up_s.index(common)] + up_t[: up_t.index(common)]
        return [f for f in links if f not in self._static and f in self._dynamic]

    def is_static(self, child: str) -> bool:
        """True if ``child``'s link to its parent came from /tf_static."""
        return normalize_frame(child) in self._static

    def static_frames(self) -> list[str]:
        """Child frames linked to their parent by /tf_static."""
        return list(self._static)

    def dynamic_parent(self, child: str) -> str | None:
        """The parent of ``child``'s dynamic link, or None if it has none."""
        s = self._dynamic.get(normalize_frame(child))
        return None if s is None else s.parent

    def dynamic_frames(self) -> list[str]:
        """Child frames that have time-stamped samples."""
        return list(self._dynamic)

    def latest_stamp(self, child: str) -> int | None:
        """Newest sample stamp (ns) of ``child``'s dynamic link; None if it has none."""
        stamps = self._sorted_stamps(child)
        return stamps[-1] if stamps else None

    def oldest_stamp(self, child: str) -> int | None:
        """Oldest sample stamp (ns) still held for ``child``'s dynamic link."""
        stamps = self._sorted_stamps(child)
        return stamps[0] if stamps else None

    def _sorted_stamps(self, child: str) -> list[int]:
        """The sample stamps (ns) of ``child``'s dynamic link in time order; empty if it has none."""
        s = self._dynamic.get(normalize_frame(child))
        if s is None or not s.stamps:
            return []
        if not self._sorted:
            self._sort()
        return s.stamps

    def latest_stamps(self) -> dict[str, int]:
        """Newest sample stamp (ns) of every dynamic link, by child frame."""
        if not self._sorted:
            self._sort()
        return {child: s.stamps[-1] for child, s in self._dynamic.items() if s.stamps}

    def prune(self, max_age_ns: int) -> int:
        """Forget dynamic samples older than their link's newest by more than ``max_age_ns``
        (tf2's cache time); returns how many were dropped. The newest sample always stays."""
        if not self._sorted:
            self._sort()
        dropped = 0
        for s in self._dynamic.values():
            if not s.stamps or s.stamps[0] >= s.stamps[-1] - max_age_ns:
                continue
            k = bisect.bisect_left(s.stamps, s.stamps[-1] - max_age_ns)
            del s.stamps[:k], s.t[:k], s.q[:k]
            dropped += k
        return dropped

    def remove(self, child: str) -> None:
        """Forget ``child``'s dynamic link (a publisher that went away)."""
        self._dynamic.pop(normalize_frame(child), None)

    def clear(self, static: bool = False) -> None:
        """Forget every dynamic link (after a clock jump), and the static ones if ``static``."""
        self._dynamic.clear()
        self._sorted = True
        if static:
            self._static.clear()

    def sample_count(self) -> int:
        """Dynamic samples held, all links together (for memory bounds)."""
        return sum(len(s.stamps) for s in self._dynamic.values())
