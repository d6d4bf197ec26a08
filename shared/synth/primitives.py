"""Textured primitives (boxes, frusta, ellipsoids): materials, closed triangle meshes with
outward normals, and inside tests.

A :class:`Part` lives in its own local frame (box and ellipsoid centred on the origin, a frustum
along z from -h/2 to h/2) and ``pose`` maps it to its parent (object, then world). Textures are
evaluated in the part's local frame so that a pattern moves with the part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import IntEnum
from functools import cache
from typing import Annotated

import numpy as np

Mat4 = Annotated[np.ndarray, "(4, 4) float64"]
Vertices = Annotated[np.ndarray, "(V, 3) float64"]
Faces = Annotated[np.ndarray, "(F, 3) int64"]


class Pattern(IntEnum):
    """Procedural texture of a material (see ``shared.synth.textures``)."""

    SOLID = 0
    STRIPES = 1
    CHECKER = 2
    NOISE = 3
    WOOD = 4
    PLANKS = 5
    TILES = 6
    PICTURE = 7
    SCREEN = 8
    CLOCK = 9


@dataclass(frozen=True)
class Material:
    """Base colour, a second colour mixed in by the pattern, and the pattern's parameters."""

    color: tuple[float, float, float]
    """Base albedo, each channel in [0, 1]."""
    color2: tuple[float, float, float] | None = None
    """Second albedo of the pattern; None: a darker shade of ``color``."""
    pattern: Pattern = Pattern.SOLID
    scale: float = 10.0
    """Pattern frequency (cycles per metre)."""
    axis: int = 0
    """Local axis that stripes, wood grain and planks run across."""
    motif: int = 0
    """Picture subject (index into ``textures.MOTIFS``) or clock time."""

    def second(self) -> tuple[float, float, float]:
        if self.color2 is not None:
            return self.color2
        return tuple(float(c) * 0.6 for c in self.color)  # type: ignore[return-value]


@dataclass(frozen=True)
class Part:
    """One primitive of an object."""

    shape: str
    """"box" (dims = size x, y, z), "frustum" (dims = bottom radius, top radius, height) or
    "ellipsoid" (dims = radii x, y, z)."""
    dims: tuple[float, float, float]
    pose: Mat4 = field(default_factory=lambda: np.eye(4), compare=False)
    material: Material = Material((0.5, 0.5, 0.5))

    def moved(self, T: Mat4) -> Part:
        """This part with ``T`` applied after its own pose."""
        return replace(self, pose=T @ self.pose)


def translation(x: float, y: float, z: float) -> Mat4:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def rot_z(angle: float) -> Mat4:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def rot_x(angle: float) -> Mat4:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[1:3, 1:3] = [[c, -s], [s, c]]
    return T


def rot_y(angle: float) -> Mat4:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[0, 0], T[0, 2], T[2, 0], T[2, 2] = c, s, -s, c
    return T


def box(size: tuple[float, float, float], center: tuple[float, float, float], material: Material) -> Part:
    """An axis-aligned box (in the parent frame) of ``size`` centred at ``center``."""
    return Part("box", tuple(map(float, size)), translation(*center), material)


def frustum(r_bottom: float, r_top: float, height: float, base: tuple[float, float, float],
            material: Material) -> Part:
    """A vertical frustum (cylinder when the radii agree) standing on ``base``."""
    x, y, z = base
    return Part("frustum", (float(r_bottom), float(r_top), float(height)), translation(x, y, z + height / 2), material)


def ellipsoid(radii: tuple[float, float, float], center: tuple[float, float, float], material: Material) -> Part:
    return Part("ellipsoid", tuple(map(float, radii)), translation(*center), material)


@cache
def _unit_box() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    # Indices follow v's (x, y, z) bit order; each face is wound counter-clockwise seen from outside.
    f = np.array([
        [0, 1, 3], [0, 3, 2],  # -x
        [4, 6, 7], [4, 7, 5],  # +x
        [0, 4, 5], [0, 5, 1],  # -y
        [2, 3, 7], [2, 7, 6],  # +y
        [0, 2, 6], [0, 6, 4],  # -z
        [1, 5, 7], [1, 7, 3],  # +z
    ])
    return v, f


@cache
def _unit_frustum(segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Ring vertices at z = -0.5 (unit radius, scaled later) and z = +0.5, plus two cap centres."""
    a = np.arange(segments) * (2 * math.pi / segments)
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    bottom = np.column_stack([ring, np.full(segments, -0.5)])
    top = np.column_stack([ring, np.full(segments, 0.5)])
    v = np.vstack([bottom, top, [[0, 0, -0.5]], [[0, 0, 0.5]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    cb, ct = 2 * segments, 2 * segments + 1
    side = np.vstack([np.column_stack([i, j, j + segments]), np.column_stack([i, j + segments, i + segments])])
    caps_b = np.column_stack([np.full(segments, cb), j, i])
    caps_t = np.column_stack([np.full(segments, ct), i + segments, j + segments])
    return v, np.vstack([side, caps_b, caps_t])


@cache
def _unit_sphere(n_lat: int, n_lon: int) -> tuple[np.ndarray, np.ndarray]:
    lat = np.linspace(-math.pi / 2, math.pi / 2, n_lat + 1)[1:-1]
    lon = np.arange(n_lon) * (2 * math.pi / n_lon)
    cl, sl = np.cos(lat)[:, None], np.sin(lat)[:, None]
    ring = np.stack([cl * np.cos(lon), cl * np.sin(lon), np.broadcast_to(sl, (len(lat), n_lon))], axis=-1)
    v = np.vstack([[[0, 0, -1]], ring.reshape(-1, 3), [[0, 0, 1]]])
    south, north = 0, len(v) - 1
    idx = 1 + np.arange(len(lat) * n_lon).reshape(len(lat), n_lon)
    faces = []
    nxt = np.roll(idx, -1, axis=1)
    faces.append(np.column_stack([np.full(n_lon, south), nxt[0], idx[0]]))
    for r in range(len(lat) - 1):
        a, b, c, d = idx[r], nxt[r], nxt[r + 1], idx[r + 1]
        faces.append(np.column_stack([a, b, c]))
        faces.append(np.column_stack([a, c, d]))
    faces.append(np.column_stack([np.full(n_lon, north), idx[-1], nxt[-1]]))
    return v, np.vstack(faces)


def local_mesh(part: Part) -> tuple[Vertices, Faces]:
    """The part's closed triangle mesh in its local frame, faces wound outward."""
    if part.shape == "box":
        v, f = _unit_box()
        return v * np.asarray(part.dims), f
    if part.shape == "frustum":
        r0, r1, h = part.dims
        segments = 24 if max(r0, r1) > 0.12 else 14
        v, f = _unit_frustum(segments)
        v = v.copy()
        n = segments
        v[:n, :2] *= r0
        v[n:2 * n, :2] *= r1
        v[:, 2] *= h
        return v, f
    if part.shape == "ellipsoid":
        v, f = _unit_sphere(8, 14)
        return v * np.asarray(part.dims), f
    raise ValueError(f"unknown primitive shape {part.shape!r}")


def world_mesh(part: Part) -> tuple[Vertices, Faces]:
    """The part's mesh with its pose applied."""
    v, f = local_mesh(part)
    return v @ part.pose[:3, :3].T + part.pose[:3, 3], f


def contains(part: Part, local: Annotated[np.ndarray, "(N, 3) part-local points"],
             eps: float = 1e-4) -> Annotated[np.ndarray, "(N,) bool"]:
    """Which points lie strictly inside the part (by more than ``eps``)."""
    if part.shape == "box":
        half = np.asarray(part.dims) / 2 - eps
        return np.all(np.abs(local) < half, axis=1)
    if part.shape == "frustum":
        r0, r1, h = part.dims
        t = np.clip(local[:, 2] / h + 0.5, 0, 1)
        # The mesh is a polygon, whose flat sides are cos(pi/segments) inside the circle.
        segments = 24 if max(r0, r1) > 0.12 else 14
        radius = (r0 + (r1 - r0) * t) * math.cos(math.pi / segments) - eps
        return (np.abs(local[:, 2]) < h / 2 - eps) & (np.hypot(local[:, 0], local[:, 1]) < radius)
    if part.shape == "ellipsoid":
        # Shrunk a little because the polygonal mesh lies inside the true surface.
        q = local / (np.asarray(part.dims) * 0.9)
        return np.einsum("ij,ij->i", q, q) < 1.0
    raise ValueError(f"unknown primitive shape {part.shape!r}")
