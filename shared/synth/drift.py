"""Drifting odometry for a synthetic sequence, and the loop-closure corrections a SLAM back end
would send (``trackgraph synth --drift RATE``).

A mapper fed ground-truth poses never meets the problem a real robot has: its odometry drifts,
so a place seen again lands beside itself in the map until a loop closure corrects the past
poses. :func:`add_drift` turns a written sequence into that situation. The images stay those
of the true poses; ``traj.txt`` becomes the drifted odometry, the true poses move to
``traj_gt.txt``, and ``corrections.jsonl`` holds one :class:`PoseCorrection` per loop closure
(the true poses of every frame up to it: a perfect back end)::

    traj.txt            drifted odometry, one row-major 4x4 camera-to-world per line
    traj_gt.txt         the true poses the images were rendered from (same format)
    corrections.jsonl   one PoseCorrection per line (shared.messages.poses.read_corrections)
    drift.png           top-down: true path, drifted path, loop closures
    gt/scene.json       gains a "drift" entry (rate, seed, closures, errors)

Numpy only (matplotlib for the picture, imported when it is drawn).
"""

from __future__ import annotations

import io
import json
import math
import os
from pathlib import Path
from typing import Annotated

import numpy as np

from shared.messages.poses import PoseCorrection
from shared.synth import writer

Poses = Annotated[np.ndarray, "(N, 4, 4) float64 camera-to-world"]

MAX_RATE = 0.5
"""Largest accepted drift rate (m per m travelled). Beyond half a metre per metre the
odometry no longer resembles any odometry, and the corrections dwarf the map."""

ROT_DRIFT_PER_RATE = 0.1
"""Yaw drift in rad per metre travelled, per unit of ``rate`` (0.002 rad/m at rate 0.02).
Only yaw drifts: gravity keeps roll and pitch observable to a real robot's IMU, so its
odometry drifts in position and heading only (the 4 unobservable degrees of freedom of VIO)."""

WALK_PER_SQRT_M = 0.5
"""Size of the random walk around the bias, per unit of ``rate``: after L metres its spread is
``rate * WALK_PER_SQRT_M * sqrt(L)`` metres per axis (and ``ROT_DRIFT_PER_RATE`` times that in
yaw radians). Small next to the bias ``rate * L`` over a room-sized walk, so the error grows
about linearly, yet the drifted path wanders instead of being a straight shear of the true one."""

LOOP_RADIUS = 1.0
"""A frame closes a loop when its true position is within this many metres of an earlier one."""

LOOP_MIN_GAP = 150
"""... of one at least this many frames earlier: consecutive frames are always close, and a
back end only searches for loop closures among keyframes well in the past."""

LOOP_MIN_SPACING = 30
"""Frames between two loop closures at least: walking along a place seen before matches it at
every frame, and a back end re-localises against it about once a second (30 frames at 30 Hz),
sending the optimised trajectory each time."""

DRIFT_PICTURE = "drift.png"
TRAJ_GT = "traj_gt.txt"
CORRECTIONS = "corrections.jsonl"
_STREAM = 29
"""Mixed into the seed so the drift's random numbers differ from the world's and the
renderer's streams of the same seed."""


def validate_rate(rate: float) -> float:
    """``rate`` as a float, or a ValueError saying what a drift rate must be."""
    try:
        value = float(rate)
    except (TypeError, ValueError):
        raise ValueError(f"drift rate must be a number (metres per metre travelled), got {rate!r}") from None
    if not math.isfinite(value) or not 0.0 < value <= MAX_RATE:
        raise ValueError(f"drift rate must be a finite number in (0, {MAX_RATE}] metres per metre travelled, got {rate!r}")
    return value


def _yaw(angle: Annotated[np.ndarray, "(N,) rad"]) -> Annotated[np.ndarray, "(N, 3, 3) float64"]:
    """Rotations about world z."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def drift_poses(true_poses: Poses, rate: float, seed: int) -> Poses:
    """Odometry that drifts from ``true_poses`` by about ``rate`` metres per metre travelled.

    The odometry integrates the true motion of each step with its own (wrong) heading, plus a
    translation error; both errors are random walks with a seeded constant bias, in steps
    proportional to the distance of the step (a standing camera does not drift). So the error
    compounds along the path the way dead reckoning does: a heading error turns every later
    step, and a loop closure that resets the past leaves the future drifting from there only.
    Frame 0 is exact (odometry starts where the map starts); the same poses, rate and seed
    give the same output. ``rate`` 0 returns the true poses.
    """
    true = np.asarray(true_poses, np.float64)
    if true.ndim != 3 or true.shape[1:] != (4, 4):
        raise ValueError(f"expected (N, 4, 4) poses, got shape {true.shape}")
    if rate == 0 or len(true) < 2:
        return true.copy()
    rate = float(rate)
    if not math.isfinite(rate) or rate < 0:
        raise ValueError(f"drift rate must be finite and non-negative, got {rate}")
    rng = np.random.default_rng([int(seed), _STREAM])
    n = len(true)
    steps = np.diff(true[:, :3, 3], axis=0)  # (N-1, 3) true motion of each step, world frame
    dist = np.linalg.norm(steps, axis=1)

    # Translation bias in the floor plane: a robot's height is held by the floor it moves on,
    # and a bias along z would hide the drift from the top-down picture. The random walk
    # around the bias is 3-D, so height is not exact either.
    angle = rng.uniform(0.0, 2.0 * math.pi)
    bias = np.array([math.cos(angle), math.sin(angle), 0.0])
    walk = rng.standard_normal((n - 1, 3))
    err_steps = rate * (dist[:, None] * bias + WALK_PER_SQRT_M * np.sqrt(dist)[:, None] * walk)

    # Yaw: a bias of either sign, and its own random walk, both per metre travelled.
    rot_rate = ROT_DRIFT_PER_RATE * rate
    sign = 1.0 if rng.random() < 0.5 else -1.0
    yaw_walk = rng.standard_normal(n - 1)
    yaw_steps = rot_rate * (sign * dist + WALK_PER_SQRT_M * np.sqrt(dist) * yaw_walk)
    yaw = np.concatenate([[0.0], np.cumsum(yaw_steps)])  # (N,) heading error of each frame

    # Dead reckoning: each step is walked with the heading the odometry had when it began.
    Rz = _yaw(yaw)
    turned = np.einsum("nij,nj->ni", Rz[:-1], steps)
    pos = true[0, :3, 3] + np.concatenate([np.zeros((1, 3)), np.cumsum(turned + err_steps, axis=0)])

    odom = np.zeros_like(true)
    # A yaw times a rotation is a rotation to machine precision: the drifted poses are as rigid
    # as the true ones (to 1e-15 for synth's poses), with no re-orthonormalisation to skew them.
    odom[:, :3, :3] = Rz @ true[:, :3, :3]
    odom[:, :3, 3] = pos
    odom[:, 3, 3] = 1.0
    odom[0] = true[0]
    return odom


def loop_closures(true_poses: Poses, radius: float = LOOP_RADIUS, min_gap: int = LOOP_MIN_GAP,
                  min_spacing: int = LOOP_MIN_SPACING) -> list[int]:
    """Frames where the camera is back at a place it was before: its true position within
    ``radius`` m of the true position of a frame at least ``min_gap`` frames earlier, and at
    least ``min_spacing`` frames after the previous closure. In frame order."""
    pos = np.asarray(true_poses, np.float64)[:, :3, 3]
    out: list[int] = []
    r2 = float(radius) ** 2
    for t in range(int(min_gap), len(pos)):
        if out and t - out[-1] < min_spacing:
            continue
        # One row at a time keeps memory linear in the sequence length.
        d2 = np.sum((pos[: t - min_gap + 1] - pos[t]) ** 2, axis=1)
        if float(d2.min()) <= r2:
            out.append(t)
    return out


def corrections(true_poses: Poses, closures: list[int]) -> list[PoseCorrection]:
    """One correction per loop closure, ids 1, 2, ... in order: the true poses of every frame up
    to the closure, as a perfect pose-graph back end would send them."""
    true = np.asarray(true_poses, np.float64)
    return [
        PoseCorrection(correction_id=k, frame_index=int(t), frames=np.arange(t + 1, dtype=np.int64),
                       poses=true[: t + 1].copy())
        for k, t in enumerate(closures, 1)
    ]


def position_errors(true_poses: Poses, odom_poses: Poses) -> Annotated[np.ndarray, "(N,) float64 m"]:
    """Distance between each frame's odometry position and its true position."""
    return np.linalg.norm(np.asarray(odom_poses)[:, :3, 3] - np.asarray(true_poses)[:, :3, 3], axis=1)


def picture(true_poses: Poses, odom_poses: Poses, closures: list[int], title: str) -> bytes:
    """PNG, top-down (world x, y): the true path, the drifted path, and each loop closure with
    a line from its drifted to its true position (what the correction moves)."""
    from matplotlib.figure import Figure

    from shared.synth.pictures import PNG_META

    p, q = true_poses[:, :3, 3], odom_poses[:, :3, 3]
    fig = Figure(figsize=(9.0, 7.0), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(p[:, 0], p[:, 1], color="#1f77b4", lw=1.5, label="true path (traj_gt.txt)")
    ax.plot(q[:, 0], q[:, 1], color="#d62728", lw=1.2, label="drifted odometry (traj.txt)")
    ax.plot(p[0, 0], p[0, 1], "o", color="black", ms=6, label="start")
    for k, t in enumerate(closures, 1):
        ax.plot([q[t, 0], p[t, 0]], [q[t, 1], p[t, 1]], color="#2ca02c", lw=1.0, ls="--")
        ax.plot(p[t, 0], p[t, 1], "*", color="#2ca02c", ms=13, mec="black", mew=0.5,
                label="loop closure (true / drifted)" if k == 1 else None)
        ax.plot(q[t, 0], q[t, 1], "x", color="#2ca02c", ms=8)
        ax.annotate(f"#{k}: frame {t}", (p[t, 0], p[t, 1]), textcoords="offset points", xytext=(6, 6), fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata=PNG_META)
    return buf.getvalue()


def _replace(path: Path, data: bytes) -> None:
    """Write through a temporary file beside ``path``, so a reader never sees half a file.
    (A plain open, not mkstemp: the file gets the same permissions as the sequence's others.)"""
    tmp = path.with_name(f".{path.name}.partial")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def add_drift(seq_dir: str | Path, rate: float, seed: int) -> dict:
    """Give the sequence in ``seq_dir`` (whose ``traj.txt`` holds the true poses) drifting
    odometry and loop-closure corrections: see the module docstring for the files.

    Refuses (ValueError) a folder that already has drift (``traj_gt.txt``) and a bad rate.
    Returns ``{"rate", "seed", "closures", "corrections", "final_error_m", "max_error_m"}``.
    """
    from shared.datasets.base import DatasetError
    from shared.datasets.replica import read_traj

    seq = Path(seq_dir)
    rate = validate_rate(rate)
    if (seq / TRAJ_GT).exists():
        raise ValueError(f"{seq}: already has drift ({TRAJ_GT} exists); drift the original sequence instead")
    read = read_traj(seq / "traj.txt")
    bad = [p for p in read if isinstance(p, DatasetError)]
    if bad:
        raise ValueError(f"{seq}: traj.txt has a pose that cannot be drifted: {bad[0]}")
    true = np.stack(read).astype(np.float64)
    odom = drift_poses(true, rate, seed)
    closures = loop_closures(true)
    fixes = corrections(true, closures)
    err = position_errors(true, odom)
    summary = {
        "rate": rate,
        "seed": int(seed),
        "closures": closures,
        "corrections": len(fixes),
        "final_error_m": round(float(err[-1]), 4),
        "max_error_m": round(float(err.max()), 4),
    }

    # Everything is computed before the first write, so a failure leaves the folder as it was.
    scene_path = seq / writer.MARKER
    scene = json.loads(scene_path.read_text(encoding="utf-8")) if scene_path.is_file() else None
    label = scene["name"] if isinstance(scene, dict) and isinstance(scene.get("name"), str) else seq.name
    files = {
        TRAJ_GT: writer.traj_text(true).encode("ascii"),
        CORRECTIONS: "".join(c.to_json() + "\n" for c in fixes).encode("utf-8"),
        # Named after the scene, not the folder: in generate() the folder is a randomly named
        # staging folder, and the same scene must give the same picture.
        DRIFT_PICTURE: picture(true, odom, closures, f"{label}: odometry drift {rate:g} m/m (seed {seed}), "
                               f"{len(closures)} loop closures, final error {err[-1]:.2f} m"),
    }
    if isinstance(scene, dict):
        # scene.json is read by key (rooms, config, seed), never checked for unknown keys, so a
        # new key is safe there; intrinsics.json, by contrast, is compared key for key.
        scene["drift"] = {
            **summary,
            "rot_drift_rad_per_m": ROT_DRIFT_PER_RATE * rate,
            "files": {"traj.txt": "drifted odometry", TRAJ_GT: "true poses (the images')",
                      CORRECTIONS: "one PoseCorrection per loop closure"},
        }
        files[str(writer.MARKER)] = writer.json_bytes(scene)
    # traj_gt.txt first: once it exists the folder counts as drifted and is refused again, and
    # until traj.txt is replaced (last) both files hold the true poses, so nothing is lost.
    for name, data in files.items():
        _replace(seq / name, data)
    _replace(seq / "traj.txt", writer.traj_text(odom).encode("ascii"))
    return summary


__all__ = [
    "LOOP_MIN_GAP", "LOOP_MIN_SPACING", "LOOP_RADIUS", "MAX_RATE", "ROT_DRIFT_PER_RATE",
    "add_drift", "corrections", "drift_poses", "loop_closures", "position_errors", "validate_rate",
]
