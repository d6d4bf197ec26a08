"""The poses fusion fused each frame with, and how a pose correction changes them.

Every fused frame keeps two poses: the one that came with it (``raw``, the robot's odometry)
and fusion's current estimate (``est``), which placed the frame in the map. A
:class:`~shared.messages.poses.PoseCorrection` states corrected poses of some past frames.
The estimates after it are a function of the raw poses and that one correction alone:

- a listed frame takes its corrected pose;
- any other fused frame follows the nearest listed frame that is in the map (by frame index)
  by its own odometry: ``est_f = P_g @ inv(raw_g) @ raw_f``;
- frames fused later are placed by the fix of the last listed frame, ``P_last @ inv(raw_last)``
  (what a ``map -> odom`` transform does for a ROS robot).

So corrections are absolute: the same correction again changes no estimate, and nothing
compounds. What moved is reported per frame as ``delta_f = est_new_f @ inv(est_old_f)``; map
content anchored to frame ``f`` moves by it (:mod:`services.fusion.core`).

Estimates are kept per *epoch*, one per applied correction, for the TSDF's archived blocks,
which are moved lazily, when they are read again (:mod:`services.fusion.volume.tsdf`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from shared.messages.poses import PoseCorrection

Pose = Annotated[np.ndarray, "(4, 4) float64 camera-to-world"]


SAME_POSE = 1e-9
"""Estimates closer than this (max abs difference of the 4x4 entries; a nanometre) are the
same pose: rounding in a product of poses is no correction."""


class CorrectionError(ValueError):
    """A correction that fusion refuses; the map is unchanged. The message says why."""


@dataclass
class Motion:
    """What a correction moved: per anchor frame, the rigid motion of the map content anchored there."""

    frames: Annotated[np.ndarray, "(M,) int64 frame indices, ascending"]
    deltas: Annotated[np.ndarray, "(M, 4, 4) float64 est_new @ inv(est_old)"]
    max_shift_m: float = 0.0
    """Largest translation among the deltas (how far the map moved at most, near its anchor)."""
    fused: Annotated[np.ndarray, "(F,) int64 every fused frame, ascending"] | None = None
    """When given, an anchor that is no fused frame (a weighted mean of frame indices, see
    ``HypothesisTSDF.integrate``) takes the fused frame at or before it."""

    def __len__(self) -> int:
        return len(self.frames)

    def rows(self, lo: int, hi: int) -> Annotated[np.ndarray, "(hi - lo + 1,) int64 row of deltas, -1 = stays"]:
        """The delta row of every anchor value in ``lo..hi`` (a table for per-voxel lookups)."""
        moves, row = self.lookup(np.arange(lo, hi + 1))
        return np.where(moves, row, -1)

    def rotates(self) -> bool:
        """Whether any delta turns (rounding onto the voxel grid then leaves gaps)."""
        return bool(len(self.deltas)) and not np.allclose(self.deltas[:, :3, :3], np.eye(3), atol=1e-9)

    def lookup(
        self, anchors: Annotated[np.ndarray, "(N,) int frame index per item, -1 = none"]
    ) -> tuple[Annotated[np.ndarray, "(N,) bool moves"], Annotated[np.ndarray, "(N,) int64 row of deltas"]]:
        """Which items move, and the row of :attr:`deltas` each one takes."""
        a = np.asarray(anchors, np.int64).reshape(-1)
        if len(self.frames) == 0 or len(a) == 0:
            return np.zeros(len(a), bool), np.zeros(len(a), np.int64)
        if self.fused is not None and len(self.fused):
            at = np.searchsorted(self.fused, a, side="right") - 1
            a = np.where(at >= 0, self.fused[at.clip(min=0)], -1)
        pos = np.searchsorted(self.frames, a).clip(max=len(self.frames) - 1)
        return self.frames[pos] == a, pos

    def apply(
        self,
        points: Annotated[np.ndarray, "(N, 3) float"],
        anchors: Annotated[np.ndarray, "(N,) int frame index per point"],
    ) -> tuple[Annotated[np.ndarray, "(N, 3) same dtype"], Annotated[np.ndarray, "(N,) bool moved"]]:
        """Each point moved by the delta of its anchor (unmoved where its anchor did not move)."""
        moves, row = self.lookup(anchors)
        out = np.array(points, copy=True)
        if moves.any():
            # grouped by delta: one small matrix product per frame, no (N, 4, 4) gather
            idx = np.flatnonzero(moves)
            idx = idx[np.argsort(row[idx], kind="stable")]
            starts = np.flatnonzero(np.diff(row[idx], prepend=-1))
            for a, b in zip(starts, [*starts[1:], len(idx)], strict=True):
                part = idx[a:b]
                D = self.deltas[row[part[0]]]
                out[part] = (np.asarray(points[part], np.float64) @ D[:3, :3].T + D[:3, 3]).astype(out.dtype)
        return out, moves


@dataclass
class PoseBook:
    """Raw and estimated pose of every fused frame, the fix for new ones, and the corrections."""

    frames: list[int] = field(default_factory=list)
    """Fused frame indices, ascending (fusion fuses each frame index once, in order)."""
    raw: list[np.ndarray] = field(default_factory=list)
    est: list[np.ndarray] = field(default_factory=list)
    fix: np.ndarray = field(default_factory=lambda: np.eye(4))
    """World-from-odometry of the newest correction: a new frame's estimate is ``fix @ raw``."""
    last_id: int = -1
    """Id of the newest correction applied (-1: none)."""
    last_digest: str = ""
    """Digest of that correction's content, to tell the same correction sent again."""
    epochs: list[np.ndarray] = field(default_factory=list)
    """Estimates of the frames fused by then, as each correction left them (epoch e = after the
    e-th applied correction; epoch 0, before any, is the raw poses and is not stored)."""

    @property
    def epoch(self) -> int:
        return len(self.epochs)

    def add(self, frame_index: int, raw: Pose) -> Pose:
        """A new frame with its pose as it came; returns the estimate it is fused with."""
        if self.frames and frame_index <= self.frames[-1]:
            raise ValueError(f"frame {frame_index} is not after the last fused frame {self.frames[-1]}")
        raw = np.asarray(raw, np.float64).reshape(4, 4)
        est = raw if self.last_id < 0 else _rigid(self.fix @ raw)
        self.frames.append(int(frame_index))
        self.raw.append(raw.copy())
        self.est.append(est.copy())
        return est

    def estimate(self, frame_index: int) -> Pose | None:
        k = self._index(frame_index)
        return None if k is None else self.est[k]

    def _index(self, frame_index: int) -> int | None:
        k = int(np.searchsorted(np.asarray(self.frames, np.int64), frame_index))
        return k if k < len(self.frames) and self.frames[k] == frame_index else None

    # ------------------------------------------------------------------ corrections

    def check(self, c: PoseCorrection) -> str | None:
        """Why ``c`` is refused, or None. "duplicate" for the newest correction sent again."""
        digest = _digest(c)
        if c.correction_id == self.last_id and digest == self.last_digest:
            return "duplicate"
        if c.correction_id <= self.last_id:
            return (f"PoseCorrection.correction_id {c.correction_id} is not after the newest applied correction "
                    f"{self.last_id} (an older correction after a newer one)")  # fmt: skip
        if not self.frames:
            return "PoseCorrection: the map has no frame yet"
        newest = self.frames[-1]
        if int(c.frames[-1]) > newest:
            return (f"PoseCorrection.frames: frame {int(c.frames[-1])} is unknown (the map has fused frames "
                    f"{self.frames[0]}..{newest})")  # fmt: skip
        if not np.isin(c.frames, np.asarray(self.frames, np.int64)).any():
            return f"PoseCorrection.frames: none of its {len(c.frames)} frames is in the map"
        return None

    def correct(self, c: PoseCorrection) -> Motion:
        """Apply ``c`` (checked first: :class:`CorrectionError` and nothing changed when it is
        refused); returns what moved."""
        why = self.check(c)
        if why == "duplicate":
            return Motion(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        if why is not None:
            raise CorrectionError(why)
        frames = np.asarray(self.frames, np.int64)
        raw = np.stack(self.raw)
        old = np.stack(self.est)
        listed = np.asarray(c.frames, np.int64)
        inmap = np.isin(listed, frames)
        listed, poses = listed[inmap], np.asarray(c.poses, np.float64)[inmap]
        at = np.searchsorted(frames, listed)
        # each listed frame's world-from-odometry; other frames take the nearest listed one's
        fixes = np.stack([_rigid(P @ _inverse(raw[k])) for P, k in zip(poses, at, strict=True)])
        nearest = _nearest(listed, frames)
        new = np.einsum("nij,njk->nik", fixes[nearest], raw)
        new[at] = poses
        new = np.stack([_rigid(T) for T in new])
        # bits of difference are not a motion: those frames keep their estimate exactly
        same = np.abs(new - old).max(axis=(1, 2)) <= SAME_POSE
        new[same] = old[same]
        changed = np.flatnonzero(~same)
        deltas = np.stack([_rigid(new[k] @ _inverse(old[k])) for k in changed]) if len(changed) else np.zeros((0, 4, 4))
        self.est = list(new)
        self.fix = fixes[-1]
        self.last_id, self.last_digest = c.correction_id, _digest(c)
        self.epochs.append(new.copy())
        shift = float(np.linalg.norm(deltas[:, :3, 3], axis=1).max()) if len(deltas) else 0.0
        return Motion(frames[changed], deltas, shift, fused=frames)

    def epoch_motion(self, epoch: int) -> Motion:
        """From the estimates of ``epoch`` to the current ones, for content saved then."""
        if epoch >= self.epoch:
            return Motion(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        # epoch 0 (before any correction) placed the frames fused before the first one by their raw poses
        then = self.epochs[epoch - 1] if epoch > 0 else np.stack(self.raw)[: len(self.epochs[0])]
        m = len(then)
        now = np.stack(self.est)[:m]
        changed = np.flatnonzero(np.abs(now - then).max(axis=(1, 2)) > SAME_POSE)
        deltas = np.stack([_rigid(now[k] @ _inverse(then[k])) for k in changed]) if len(changed) else np.zeros((0, 4, 4))
        return Motion(np.asarray(self.frames, np.int64)[changed], deltas, fused=np.asarray(self.frames, np.int64))

    # ------------------------------------------------------------------ persistence

    def state_dict(self) -> dict[str, Any]:
        n = len(self.frames)
        return {
            "frames": np.asarray(self.frames, np.int64),
            "raw": np.stack(self.raw) if n else np.zeros((0, 4, 4)),
            "est": np.stack(self.est) if n else np.zeros((0, 4, 4)),
            "fix": self.fix.copy(),
            "last": np.asarray([self.last_id], np.int64),
            "digest": np.frombuffer(bytes.fromhex(self.last_digest or "00" * 16), np.uint8).copy(),
            "epoch_sizes": np.asarray([len(e) for e in self.epochs], np.int64),
            "epochs": np.concatenate(self.epochs) if self.epochs else np.zeros((0, 4, 4)),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.frames = np.asarray(state["frames"], np.int64).reshape(-1).tolist()
        self.raw = list(np.asarray(state["raw"], np.float64).reshape(-1, 4, 4))
        self.est = list(np.asarray(state["est"], np.float64).reshape(-1, 4, 4))
        self.fix = np.asarray(state["fix"], np.float64).reshape(4, 4)
        self.last_id = int(np.asarray(state["last"]).reshape(-1)[0])
        self.last_digest = "" if self.last_id < 0 else bytes(np.asarray(state["digest"], np.uint8)).hex()
        sizes = np.asarray(state["epoch_sizes"], np.int64).reshape(-1)
        flat = np.asarray(state["epochs"], np.float64).reshape(-1, 4, 4)
        self.epochs = list(np.split(flat, np.cumsum(sizes)[:-1])) if len(sizes) else []

    @classmethod
    def from_raw(cls, frames: list[int], poses: list[np.ndarray]) -> PoseBook:
        """A book for a map saved before corrections existed: estimates equal the raw poses."""
        book = cls()
        for f, T in zip(frames, poses, strict=True):
            book.add(int(f), T)
        return book


def _digest(c: PoseCorrection) -> str:
    h = hashlib.blake2b(digest_size=16)
    h.update(np.int64(c.frame_index).tobytes())
    h.update(np.ascontiguousarray(c.frames, np.int64).tobytes())
    h.update(np.ascontiguousarray(c.poses, np.float64).tobytes())
    return h.hexdigest()


def _nearest(
    listed: Annotated[np.ndarray, "(L,) int64 ascending"], frames: Annotated[np.ndarray, "(N,) int64"]
) -> Annotated[np.ndarray, "(N,) int64 row of listed"]:
    """The listed frame nearest to each frame by index (the earlier one on a tie)."""
    hi = np.searchsorted(listed, frames).clip(max=len(listed) - 1)
    lo = (hi - 1).clip(min=0)
    take_lo = np.abs(frames - listed[lo]) <= np.abs(listed[hi] - frames)
    return np.where(take_lo, lo, hi)


def _inverse(T: Pose) -> Pose:
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def _rigid(T: Pose) -> Pose:
    """``T`` with its rotation re-orthonormalised (products of many poses drift off SO(3))."""
    out = np.array(T, np.float64, copy=True)
    u, _, vt = np.linalg.svd(out[:3, :3])
    R = u @ vt
    if np.linalg.det(R) < 0:
        u[:, -1] *= -1
        R = u @ vt
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out
