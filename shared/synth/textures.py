"""Procedural textures evaluated at 3D points in each part's local frame (vectorised numpy;
value noise, tiles and checker run as numba kernels where numba is installed, to the same bits:
:mod:`shared.synth.kernels`).

The same functions colour rendered pixels and ground-truth points, so a point's colour in
``gt/colors.npy`` is the unlit albedo the renderer shades.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from shared.synth import kernels
from shared.synth.primitives import Part, Pattern

Points = Annotated[np.ndarray, "(N, 3) float"]
Colors = Annotated[np.ndarray, "(N, 3) float32 in [0, 1]"]

MOTIFS = ("mountains", "sea", "flowers", "abstract")
"""Picture subjects, indexed by ``Material.motif`` of a PICTURE material."""


@dataclass(frozen=True)
class MaterialTable:
    """Per-part material parameters and world-to-local transforms, as arrays for gathering."""

    color: Annotated[np.ndarray, "(P, 3) float32"]
    color2: Annotated[np.ndarray, "(P, 3) float32"]
    pattern: Annotated[np.ndarray, "(P,) int16"]
    scale: Annotated[np.ndarray, "(P,) float32"]
    axis: Annotated[np.ndarray, "(P,) int8"]
    motif: Annotated[np.ndarray, "(P,) int32"]
    dims: Annotated[np.ndarray, "(P, 3) float32"]
    world_to_local: Annotated[np.ndarray, "(P, 4, 4) float64"]

    @classmethod
    def from_parts(cls, parts: list[Part]) -> MaterialTable:
        inv = np.stack([np.linalg.inv(p.pose) for p in parts]) if parts else np.zeros((0, 4, 4))
        return cls(
            color=np.array([p.material.color for p in parts], np.float32).reshape(-1, 3),
            color2=np.array([p.material.second() for p in parts], np.float32).reshape(-1, 3),
            pattern=np.array([int(p.material.pattern) for p in parts], np.int16),
            scale=np.array([p.material.scale for p in parts], np.float32),
            axis=np.array([p.material.axis for p in parts], np.int8),
            motif=np.array([p.material.motif for p in parts], np.int32),
            dims=np.array([p.dims for p in parts], np.float32).reshape(-1, 3),
            world_to_local=inv,
        )

    def to_local(self, part_idx: Annotated[np.ndarray, "(N,) int"], world: Points) -> Points:
        """Points in their part's frame (float32: textures need millimetres, not more)."""
        R = self.rot32.take(part_idx, axis=0)
        t = self.trans32.take(part_idx, axis=0)
        w = np.asarray(world, np.float32)
        return np.einsum("nij,nj->ni", R, w) + t

    def to_local_soa(self, part_idx: Annotated[np.ndarray, "(N,) int"],
                     world: list[np.ndarray]) -> Points:
        """Like :meth:`to_local` for world points given as three (N,) float32 arrays."""
        R = self.rot32
        t = self.trans32
        out = np.empty((len(part_idx), 3), np.float32)
        for k in range(3):
            acc = t[:, k].take(part_idx)
            for j in range(3):
                acc += R[:, k, j].take(part_idx) * world[j]
            out[:, k] = acc
        return out

    @property
    def rot32(self) -> np.ndarray:
        return self._cache("_rot32", lambda: self.world_to_local[:, :3, :3].astype(np.float32))

    @property
    def trans32(self) -> np.ndarray:
        return self._cache("_trans32", lambda: self.world_to_local[:, :3, 3].astype(np.float32))

    def _cache(self, name: str, make):
        if name not in self.__dict__:
            object.__setattr__(self, name, make())
        return self.__dict__[name]


_LATTICE_BITS = 6
_LATTICE = np.random.default_rng(0x5EED).random((1 << _LATTICE_BITS,) * 3, dtype=np.float32)
"""Random values on a periodic 64^3 lattice: a table lookup is much cheaper than hashing."""
_MASK = (1 << _LATTICE_BITS) - 1
_FLAT = _LATTICE.ravel()


def _hash(*ints: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) of up to three lattice coordinates."""
    idx = [np.asarray(v).astype(np.int64) & _MASK for v in ints]
    while len(idx) < 3:
        idx.append(np.zeros_like(idx[0]))
    return _LATTICE[idx[0], idx[1], idx[2]]


def value_noise(p: Points) -> Annotated[np.ndarray, "(N,) float32 in [0, 1)"]:
    """Smooth 3D value noise with unit lattice spacing (period 64)."""
    p = np.asarray(p, np.float32)
    if kernels.ENABLED:
        out = np.empty(len(p), np.float32)
        kernels.value_noise_kernel(np.ascontiguousarray(p), _FLAT, out)
        return out
    return value_noise_numpy(p)


def value_noise_numpy(p: Annotated[np.ndarray, "(N, 3) float32"]) -> Annotated[np.ndarray, "(N,) float32 in [0, 1)"]:
    """:func:`value_noise` in numpy (the reference of its kernel)."""
    fl = np.floor(p)
    f = p - fl
    u = f * f * (3 - 2 * f)
    i = fl.astype(np.int32) & _MASK
    b = _LATTICE_BITS
    # Flat indices into the lattice: x, y and z of the cell's corner and of its +1 neighbours.
    x0, y0, z0 = i[:, 0] << (2 * b), i[:, 1] << b, i[:, 2]
    x1 = ((i[:, 0] + 1) & _MASK) << (2 * b)
    y1 = ((i[:, 1] + 1) & _MASK) << b
    z1 = (i[:, 2] + 1) & _MASK
    L = _FLAT
    ux, uy, uz = u[:, 0], u[:, 1], u[:, 2]
    xy00, xy10, xy01, xy11 = x0 + y0, x1 + y0, x0 + y1, x1 + y1
    a = L.take(xy00 + z0)
    c00 = a + (L.take(xy10 + z0) - a) * ux
    a = L.take(xy01 + z0)
    c10 = a + (L.take(xy11 + z0) - a) * ux
    a = L.take(xy00 + z1)
    c01 = a + (L.take(xy10 + z1) - a) * ux
    a = L.take(xy01 + z1)
    c11 = a + (L.take(xy11 + z1) - a) * ux
    c0 = c00 + (c10 - c00) * uy
    c1 = c01 + (c11 - c01) * uy
    return c0 + (c1 - c0) * uz


def fbm(p: Points, octaves: int = 3) -> Annotated[np.ndarray, "(N,) float32 in [0, 1)"]:
    total = np.zeros(len(p), np.float32)
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += np.float32(amp) * value_noise(p * (2.0**o) + 17.0 * o)
        norm += amp
        amp *= 0.5
    return total / np.float32(norm)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + (b - a) * t[:, None]


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)


def _picture(q: Points, dims: np.ndarray, motif: np.ndarray, c1: np.ndarray) -> Colors:
    """Simple paintings on a canvas whose face is the local x-z plane."""
    u = np.clip(q[:, 0] / dims[:, 0] + 0.5, 0, 1)
    v = np.clip(q[:, 2] / dims[:, 2] + 0.5, 0, 1)
    out = np.empty((len(q), 3), np.float32)
    sky = _mix(np.array([[0.95, 0.95, 0.9]], np.float32), np.array([[0.45, 0.65, 0.92]], np.float32), v)
    for m in np.unique(motif):
        s = motif == m
        uu, vv, col = u[s], v[s], sky[s].copy()
        name = MOTIFS[int(m) % len(MOTIFS)]
        if name == "mountains":
            ridge = 0.62 - 0.9 * np.abs(((uu * 2.2 + 0.15) % 1.0) - 0.5) * (0.6 + 0.4 * np.sin(uu * 7))
            rock = vv < ridge
            snow = rock & (vv > ridge - 0.08)
            col[rock] = (0.35, 0.38, 0.45)
            col[snow] = (0.97, 0.97, 0.97)
            col[vv < 0.22] = (0.25, 0.5, 0.2)
        elif name == "sea":
            col = _mix(np.array([[0.98, 0.85, 0.45]], np.float32), np.array([[0.95, 0.45, 0.3]], np.float32), vv)
            sun = (uu - 0.5) ** 2 + (vv - 0.6) ** 2 < 0.012
            col[sun] = (1.0, 0.95, 0.7)
            sea = vv < 0.45
            waves = 0.5 + 0.5 * np.sin(vv * 90 + np.sin(uu * 20))
            col[sea] = _mix(np.array([[0.05, 0.2, 0.45]], np.float32), np.array([[0.15, 0.35, 0.6]], np.float32), waves[sea])
        elif name == "flowers":
            col[:] = (0.3, 0.55, 0.25)
            gu, gv = uu * 7, vv * 6
            cu, cv = np.floor(gu), np.floor(gv)
            jx = _hash(cu, cv, np.full_like(cu, 3)) * 0.5 + 0.25
            jy = _hash(cu, cv, np.full_like(cu, 5)) * 0.5 + 0.25
            d = (gu - cu - jx) ** 2 + (gv - cv - jy) ** 2
            petal = d < 0.06
            hue = _hash(cu, cv, np.full_like(cu, 7))
            palette = np.array([[0.9, 0.2, 0.3], [0.95, 0.85, 0.2], [0.8, 0.4, 0.9], [1.0, 1.0, 1.0]], np.float32)
            col[petal] = palette[(hue[petal] * 4).astype(int) % 4]
            col[d < 0.012] = (0.95, 0.75, 0.1)
        else:
            cu, cv = np.floor(uu * 3.3 + 0.2), np.floor(vv * 2.7 + 0.4)
            h = _hash(cu, cv, np.full_like(cu, 11))
            palette = np.array([[0.85, 0.1, 0.1], [0.1, 0.2, 0.7], [0.95, 0.85, 0.1], [0.95, 0.95, 0.93]], np.float32)
            col = palette[(h * 4).astype(int) % 4]
            fu, fv = (uu * 3.3 + 0.2) % 1.0, (vv * 2.7 + 0.4) % 1.0
            line = (np.minimum(fu, 1 - fu) < 0.04) | (np.minimum(fv, 1 - fv) < 0.05)
            col[line] = (0.05, 0.05, 0.05)
        out[s] = col
    return out * (0.85 + 0.15 * c1)


def _clock(q: Points, dims: np.ndarray, motif: np.ndarray, c1: np.ndarray, c2: np.ndarray) -> Colors:
    """A clock face on the +z cap of a frustum: ticks and two hands; the rim takes ``c2``."""
    R = dims[:, 0]
    x, y = q[:, 0] / R, q[:, 1] / R
    r = np.hypot(x, y)
    theta = np.arctan2(x, y)  # clockwise from 12 o'clock when seen from +z
    step = math.pi / 6
    ang_off = np.abs(((theta / step) + 0.5) % 1.0 - 0.5) * step * r
    tick = (r > 0.78) & (r < 0.9) & (ang_off < 0.035)
    minutes = (motif % 720).astype(np.float32)
    a_min = minutes % 60 / 60 * 2 * math.pi
    a_hour = minutes / 720 * 2 * math.pi

    def hand(angle: np.ndarray, length: float, width: float) -> np.ndarray:
        dx, dy = np.sin(angle), np.cos(angle)
        along = x * dx + y * dy
        across = np.abs(x * dy - y * dx)
        return (along > -0.08) & (along < length) & (across < width)

    ink = tick | hand(a_min, 0.75, 0.03) | hand(a_hour, 0.5, 0.05) | (r < 0.06)
    col = np.where(ink[:, None], np.float32(0.05), c1)
    rim = (r > 0.93) | (np.abs(q[:, 2]) < dims[:, 2] / 2 - 1e-4)
    return np.where(rim[:, None], c2, col).astype(np.float32)


def apply_patterns(table: MaterialTable, part_idx: Annotated[np.ndarray, "(N,) int"], local: Points,
                   pat: Annotated[np.ndarray, "(N,) int16"], kinds: Iterable[int], out: Colors) -> None:
    """Overwrite ``out``'s rows of the patterned materials (all but SOLID and NOISE) among
    ``kinds`` with their pattern's albedo; ``pat`` is each point's pattern."""
    for kind in kinds:
        if kind in (Pattern.SOLID, Pattern.NOISE):
            continue
        s = np.flatnonzero(pat == kind)
        sub = part_idx.take(s)
        q, sc = local.take(s, axis=0), table.scale.take(sub)
        a1, a2 = table.color.take(sub, axis=0), table.color2.take(sub, axis=0)
        if kind in (Pattern.STRIPES, Pattern.WOOD, Pattern.PLANKS):
            ax = table.axis.take(sub).astype(np.int64)
            rows = np.arange(len(s))
            along = q[rows, ax]
            across = q[rows, (ax + 1) % 3]
        if kind == Pattern.STRIPES:
            res = _mix(a1, a2, _smoothstep(0.4, 0.6, 0.5 + 0.5 * np.sin(2 * math.pi * along * sc)))
        elif kind == Pattern.CHECKER and kernels.ENABLED:
            res = np.empty_like(a1)
            kernels.checker(q, sc, a1, a2, res)
        elif kind == Pattern.CHECKER:
            cells = np.floor(q * sc[:, None] + 1e-3).astype(np.int64).sum(axis=1)
            res = _mix(a1, a2, (cells % 2).astype(np.float32))
        elif kind == Pattern.WOOD:
            other = q[rows, (ax + 2) % 3]
            ring = (across + 0.3 * other) * sc + 2.5 * fbm(q * np.float32(4.0))
            res = _mix(a1, a2, ((0.5 + 0.5 * np.sin(2 * math.pi * ring)) ** 3).astype(np.float32))
        elif kind == Pattern.PLANKS:
            width = 1.0 / sc
            k = np.floor(across / width)
            length = 1.3
            shift = _hash(k, np.zeros_like(k), np.ones_like(k)) * length
            j = np.floor((along + shift) / length)
            tint = 0.82 + 0.3 * _hash(k, j, np.full_like(k, 2))
            grain = fbm(np.stack([along * 1.5, across * 40, k], axis=1))
            res = _mix(a1, a2, grain * 0.6) * tint[:, None]
            fa, fb = (across / width) % 1.0, ((along + shift) / length) % 1.0
            seam = (np.minimum(fa, 1 - fa) < 0.03) | (np.minimum(fb, 1 - fb) < 0.004)
            res[seam] *= 0.55
        elif kind == Pattern.TILES and kernels.ENABLED:
            res = np.empty_like(a1)
            kernels.tiles(q, sc, a1, a2, _FLAT, res)
        elif kind == Pattern.TILES:
            gq = q * sc[:, None]
            cells = np.floor(gq).astype(np.int64)
            frac = gq - cells
            grout = (np.minimum(frac, 1 - frac)[:, :2] < 0.035).any(axis=1)
            res = a1 * (0.92 + 0.16 * _hash(cells[:, 0], cells[:, 1], cells[:, 2]))[:, None]
            res[grout] = a2[grout]
        elif kind == Pattern.PICTURE:
            res = _picture(q, table.dims[sub], table.motif[sub], a1)
        elif kind == Pattern.SCREEN:
            v = q[:, 2] / table.dims[sub, 2] + 0.5
            u = q[:, 0] / table.dims[sub, 0] + 0.5
            glare = np.exp(-((u - v * 0.8 - 0.1) ** 2) / 0.01) * 0.25
            res = _mix(a1, a2, np.clip(v * 0.6 + glare, 0, 1).astype(np.float32))
        elif kind == Pattern.CLOCK:
            res = _clock(q, table.dims[sub], table.motif[sub], a1, a2)
        else:
            res = a1
        out[s] = res


def albedo(table: MaterialTable, part_idx: Annotated[np.ndarray, "(N,) int"], local: Points,
           textures: bool = True) -> Colors:
    """Albedo at points given in their part's local frame."""
    c1 = table.color.take(part_idx, axis=0)
    if not textures or len(part_idx) == 0:
        return c1
    c2 = table.color2.take(part_idx, axis=0)
    pat = table.pattern.take(part_idx)
    scale = table.scale.take(part_idx)
    # One noise lookup serves every point: a NOISE material's own pattern (most of the pixels:
    # walls and fabrics), and a faint grime on everything else so that no surface is
    # perfectly uniform (which also helps feature trackers). Doing both in one pass over whole
    # arrays avoids gathering and scattering the bulk of the points.
    is_noise = pat == Pattern.NOISE
    nscale = np.where(is_noise, scale, np.float32(9.0))
    offset = np.where(is_noise, np.float32(0.0), part_idx.astype(np.float32) * np.float32(3.7))
    g = local * nscale[:, None] + offset[:, None]
    t = value_noise(g)
    fine = np.flatnonzero(is_noise & (scale >= 20))
    if len(fine):
        t[fine] = (t[fine] + 0.5 * value_noise(g[fine] * 2.0 + 17.0)) / 1.5
    out = c1 + (c2 - c1) * np.where(is_noise, t, np.float32(0.0))[:, None]
    shade = np.where(is_noise, np.float32(1.0), np.float32(0.93) + np.float32(0.14) * t)
    apply_patterns(table, part_idx, local, pat, np.unique(pat), out)
    out *= shade[:, None]
    return np.clip(out, 0, 1).astype(np.float32, copy=False)
