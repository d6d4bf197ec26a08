"""A smooth walk through the rooms: a loop around each furnished room, doorway to doorway,
with a look direction that follows the path and sweeps left and right over the furniture.

The route is planned on the free-space grid (so it never passes closer than the configured
clearance to walls or furniture), smoothed with a Gaussian along its length (less where the
smoothing would cut a corner), and sampled at evenly spaced distances. Poses are
camera-to-world in OpenCV axes (x right, y down, z forward); the world is z up.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.ndimage import gaussian_filter1d

from shared.synth.config import CameraConfig
from shared.synth.freespace import PathPlanner, free_space
from shared.synth.layout import Layout, Room
from shared.synth.world import World

log = logging.getLogger(__name__)

STEP = 0.05
"""Resampling step of the dense path (m)."""


class TrajectoryError(RuntimeError):
    """No collision-free walk could be planned through the world."""


@dataclass
class Trajectory:
    poses: Annotated[np.ndarray, "(N, 4, 4) float64 camera-to-world, OpenCV axes"]
    path: Annotated[np.ndarray, "(M, 2) float64 dense walked path"]
    waypoints: Annotated[np.ndarray, "(K, 2) float64 planned stops"]
    yaw: Annotated[np.ndarray, "(N,) float64 look direction about z (rad)"]
    length: float
    """Walked distance (m)."""

    @property
    def positions(self) -> Annotated[np.ndarray, "(N, 3) float64"]:
        return self.poses[:, :3, 3]


def look_pose(position: Annotated[np.ndarray, "(3,)"], yaw: float, pitch: float) -> Annotated[np.ndarray, "(4, 4)"]:
    """Camera-to-world pose (OpenCV axes) at ``position`` looking along ``yaw`` (about world z,
    0 = +x) tilted by ``pitch`` (positive looks up)."""
    f = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, f, position
    return T


def _loop_targets(room: Room, wall_thickness: float, scale: float) -> list[tuple[float, float]]:
    """Corners of the touring rectangle, counter-clockwise seen from above."""
    x0, y0, x1, y1 = room.inner(wall_thickness)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    hx, hy = scale * (x1 - x0), scale * (y1 - y0)
    return [(cx - hx, cy - hy), (cx + hx, cy - hy), (cx + hx, cy + hy), (cx - hx, cy + hy)]


def _room_loop(planner: PathPlanner, layout: Layout, room: Room, scale: float) -> list[tuple[float, float]]:
    inner = room.inner(layout.wall_thickness)
    pts = [planner.snap(t, inner) for t in _loop_targets(room, layout.wall_thickness, scale)]
    return list(dict.fromkeys(p for p in pts if p is not None))


def _dist(a: tuple[float, float], b: tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _tour(loop: list[tuple[float, float]], entry: tuple[float, float] | None,
          exit_: tuple[float, float] | None) -> list[tuple[float, float]]:
    """All touring points of a room, in loop order (either way round), starting near where
    the camera comes in and ending near where it leaves."""
    best: tuple[float, list[tuple[float, float]]] | None = None
    n = len(loop)
    for start in range(n):
        for direction in (1, -1):
            order = [loop[(start + direction * i) % n] for i in range(n)]
            cost = (_dist(entry, order[0]) if entry else 0.0) + (_dist(order[-1], exit_) if exit_ else 0.0)
            if best is None or cost < best[0] - 1e-9:
                best = (cost, order)
    assert best is not None
    return best[1]


def plan_route(world: World, planner: PathPlanner, scale: float) -> list[tuple[float, float]]:
    """Waypoints: each furnished room toured once around, in floor-plan order. A single room's
    tour closes on its start; in a revisit layout the camera then walks back to the first room
    and along the start of its tour again."""
    layout = world.layout
    furnished = [r for r in layout.rooms if r.furnished]
    loops = [(r, _room_loop(planner, layout, r, scale)) for r in furnished]
    for r, loop in loops:
        if not loop:
            log.warning("room %s has no walkable touring point", r.name)
    loops = [(r, loop) for r, loop in loops if loop]
    revisit = layout.return_to_start
    route: list[tuple[float, float]] = []
    tours = []
    for k, (room, loop) in enumerate(loops):
        entry = route[-1] if route else None
        if k + 1 < len(loops):
            nxt = loops[k + 1][0].name
            door = next((d for d in layout.doors if nxt in d.rooms and room.name in d.rooms), None)
            exit_ = door.point() if door else loops[k + 1][1][0]
        elif revisit and k > 0:
            exit_ = entry
        else:
            exit_ = None
        tour = _tour(loop, entry, exit_)
        tours.append(tour)
        route.extend(tour)
        if len(loops) == 1:
            route.append(tour[0])
    if revisit and len(tours) > 1:
        # Back in the first room, follow its tour in the same direction as at the start, up
        # to its second point, so the last frames retrace the first ones.
        first = tours[0]
        n = len(first)
        k = int(np.argmin([_dist(route[-1], p) for p in first]))
        passed_start = False
        for _ in range(2 * n + 2):
            route.append(first[k])
            if k == 0:
                passed_start = True
            elif passed_start and k == 1:
                break
            k = (k + 1) % n
    return route


def _smooth(planner: PathPlanner, dense: np.ndarray, sigma_m: float, min_clear: float) -> np.ndarray:
    sigma = sigma_m / STEP
    for _ in range(6):
        if sigma < 0.5:
            return dense
        sm = np.stack([gaussian_filter1d(dense[:, k], sigma, mode="nearest") for k in range(2)], axis=1)
        if planner.fs.clearance_at(sm).min() >= min_clear:
            return sm
        sigma /= 2
    return dense


def _resample(poly: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    seg = np.hypot(*np.diff(poly, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])
    poly, s = poly[keep], s[keep]
    n = max(2, int(np.ceil(s[-1] / step)) + 1)
    t = np.linspace(0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1), t


def _inward_offset(layout: Layout, xy: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Angle from the heading to the centre of the room each point is in, faded out when the
    centre is close (its direction is unstable) or behind (the sign would flip)."""
    out = np.zeros(len(xy))
    for room in layout.rooms:
        x0, y0, x1, y1 = room.inner(layout.wall_thickness)
        inside = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
        if not inside.any():
            continue
        cx, cy = room.center()
        to = np.stack([cx - xy[inside, 0], cy - xy[inside, 1]], axis=1)
        diff = np.angle(np.exp(1j * (np.arctan2(to[:, 1], to[:, 0]) - heading[inside])))
        near = np.clip(np.hypot(to[:, 0], to[:, 1]) / 1.0, 0, 1)
        behind = np.clip((math.radians(170) - np.abs(diff)) / math.radians(30), 0, 1)
        out[inside] = diff * near * behind
    return out


def _slew(values: np.ndarray, max_step: float) -> np.ndarray:
    out = values.copy()
    for i in range(1, len(out)):
        out[i] = min(max(out[i], out[i - 1] - max_step), out[i - 1] + max_step)
    return out


def _limit_turn(yaw: np.ndarray, max_step: float) -> np.ndarray:
    """The per-frame yaw with no step above ``max_step`` (frames far apart along a long walk
    would turn too fast for trackers otherwise). Slew limiting run forwards and backwards and
    averaged keeps the turn centred where it was meant; a final light smoothing keeps the bound
    (a convolution with a positive kernel cannot steepen a slope)."""
    if len(yaw) < 3 or np.abs(np.diff(yaw)).max() <= max_step:
        return yaw
    limited = 0.5 * (_slew(yaw, max_step) + _slew(yaw[::-1], max_step)[::-1])
    return gaussian_filter1d(limited, 1.5, mode="nearest")


def build_trajectory(world: World, cfg: CameraConfig) -> Trajectory:
    """Poses of all frames; raises :class:`TrajectoryError` if the rooms cannot be toured."""
    fs = free_space(world)
    planner = PathPlanner(fs, cfg.clearance)
    route = plan_route(world, planner, cfg.loop_scale)
    pieces = []
    for a, b in zip(route[:-1], route[1:], strict=True):
        leg = planner.path(a, b)
        if leg is None:
            raise TrajectoryError(f"no walkable path from {a} to {b} with clearance {cfg.clearance} m")
        pieces.append(leg if not pieces else leg[1:])
    if not pieces:
        raise TrajectoryError("no room to walk in: the furnished rooms have no walkable touring points")
    dense, _ = _resample(np.vstack(pieces), STEP)
    dense = _smooth(planner, dense, cfg.smoothing, cfg.clearance - 0.02)
    dense, s = _resample(dense, STEP)
    length = float(s[-1])

    # Heading along the path, unwrapped and smoothed so the camera turns gradually.
    d = np.gradient(dense, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    if cfg.yaw_smoothing > 0:
        heading = gaussian_filter1d(heading, cfg.yaw_smoothing / STEP, mode="nearest")
    # In open space the camera looks part way towards the middle of the room (so it sees the
    # furniture across the room rather than the nearest wall) and sweeps left and right;
    # where walls are close (doorways, corridors) both fade out and it looks ahead.
    open_ = np.clip((fs.wall_clearance_at(dense) - 0.5) / 0.3, 0, 1)
    inward = _inward_offset(world.layout, dense, heading) * cfg.look_inward
    sweep = math.radians(cfg.sweep_deg) * np.sin(2 * math.pi * s / cfg.sweep_period_m)
    offset = gaussian_filter1d(open_ * (inward + sweep), 0.6 / STEP, mode="nearest")
    yaw_dense = heading + offset

    t = np.linspace(0.0, length, cfg.frames)
    x, y = np.interp(t, s, dense[:, 0]), np.interp(t, s, dense[:, 1])
    yaw = _limit_turn(np.interp(t, s, yaw_dense), math.radians(cfg.max_yaw_step_deg))
    pitch = np.radians(cfg.pitch_deg + cfg.pitch_wobble_deg * np.sin(2 * math.pi * t / (1.7 * cfg.sweep_period_m) + 1.0))
    z = cfg.eye_height + cfg.bob * np.sin(2 * math.pi * t / 0.7)
    poses = np.stack([look_pose(np.array([x[i], y[i], z[i]]), float(yaw[i]), float(pitch[i])) for i in range(cfg.frames)])
    log.info("trajectory: %d frames over %.1f m (%.1f cm per frame)", cfg.frames, length, 100 * length / max(cfg.frames - 1, 1))
    return Trajectory(poses, dense, np.array(route, float), yaw, length)
