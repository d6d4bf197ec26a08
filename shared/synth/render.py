"""Ray-cast rendering: z-depth, per-pixel object ids and Lambert-shaded, textured RGB.

One Open3D ``RaycastingScene`` geometry per object (its parts' meshes concatenated), so a hit's
geometry id is the object and its primitive id gives the part, whose material and local frame
colour the pixel. Rays are built here rather than with ``create_rays_pinhole``, which puts
pixel centres at (u + 0.5, v + 0.5); ours are at integer (u, v), matching cx = (W - 1) / 2.
Each ray's direction has camera z = 1, so the hit distance is the z-depth.

Shading runs as numba kernels (:mod:`shared.synth.kernels`) where numba is installed, giving
:meth:`Renderer.render_numpy`'s frames byte for byte; the numpy path is the reference.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from shared.geometry import Intrinsics
from shared.o3d import import_open3d
from shared.synth import kernels
from shared.synth.config import RenderConfig
from shared.synth.primitives import world_mesh
from shared.synth.textures import _FLAT, MaterialTable, albedo, apply_patterns
from shared.synth.world import World

SUNS = np.array([[0.35, 0.25, 0.9], [-0.55, -0.5, 0.45]])
"""Directions towards two fixed directional lights (normalised below)."""
SUNS = SUNS / np.linalg.norm(SUNS, axis=1, keepdims=True)
SUN_WEIGHTS = np.array([1.0, 0.55])
LAMP_BELOW_CEILING = 0.3
LAMP_FALLOFF = 3.0
"""Distance (m) at which a room lamp's light has halved."""


@dataclass
class RenderedFrame:
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]
    depth: Annotated[np.ndarray, "(H, W) float32 metres, 0 = no reading"]
    instances: Annotated[np.ndarray, "(H, W) int32 object id, -1 = none"]


class Renderer:
    """Renders a world from camera-to-world poses (OpenCV axes)."""

    def __init__(self, world: World, K: Intrinsics, cfg: RenderConfig):
        o3d = import_open3d()
        self._o3c = o3d.core
        self.cfg, self.K = cfg, K
        self.scene = o3d.t.geometry.RaycastingScene()
        parts, _ = world.parts()
        self.table = MaterialTable.from_parts(parts)
        geom_obj, tri_offset, tri_part = [], [], []
        part_base, tri_total = 0, 0
        for obj in world.objects:
            verts, faces, owners = [], [], []
            n_v = 0
            for k, part in enumerate(obj.parts):
                v, f = world_mesh(part)
                verts.append(v)
                faces.append(f + n_v)
                owners.append(np.full(len(f), part_base + k, np.int32))
                n_v += len(v)
            gid = self.scene.add_triangles(
                o3d.core.Tensor(np.vstack(verts).astype(np.float32)),
                o3d.core.Tensor(np.vstack(faces).astype(np.uint32)),
            )
            if gid != len(geom_obj):
                raise RuntimeError(f"unexpected geometry id {gid} for object {obj.id}")
            geom_obj.append(obj.id)
            tri_offset.append(tri_total)
            tri_part.append(np.concatenate(owners))
            tri_total += sum(len(f) for f in faces)
            part_base += len(obj.parts)
        self.geom_obj = np.array(geom_obj, np.int32)
        self.tri_offset = np.array(tri_offset, np.int64)
        self.tri_part = np.concatenate(tri_part)
        self.triangles = tri_total
        layout = world.layout
        self.lamps = np.array([[*r.center(), layout.wall_height - LAMP_BELOW_CEILING] for r in layout.rooms])
        u = np.arange(K.width, dtype=np.float64)
        v = np.arange(K.height, dtype=np.float64)
        self._noise = np.random.default_rng(0xC0FFEE).standard_normal((2 * K.height, 2 * K.width, 3), dtype=np.float32)
        self._xc = np.broadcast_to(((u - K.cx) / K.fx)[None, :], (K.height, K.width)).astype(np.float32)
        self._yc = np.broadcast_to(((v - K.cy) / K.fy)[:, None], (K.height, K.width)).astype(np.float32)
        # The kernels' per-sequence constants, in the types and roundings render_numpy uses.
        self._xc_row = np.ascontiguousarray(self._xc[0])
        self._yc_col = np.ascontiguousarray(self._yc[:, 0])
        self._suns = SUNS.astype(np.float32)
        self._sun_weights = np.array([np.float32(cfg.sun_strength * w) for w in SUN_WEIGHTS], np.float32)
        self._lamps32 = np.ascontiguousarray(self.lamps.astype(np.float32)).reshape(-1, 3)

    def cast(self, pose: Annotated[np.ndarray, "(4, 4) camera-to-world"]) -> dict[str, np.ndarray]:
        """Raw hits: t_hit (z-depth, inf on a miss), geometry and primitive ids, normals, and
        the (H, W, 6) float32 rays (origin, direction with camera z = 1)."""
        R = pose[:3, :3].astype(np.float32)
        rays = np.empty((self.K.height, self.K.width, 6), np.float32)
        if kernels.ENABLED:
            kernels.pinhole_rays(R, pose[:3, 3].astype(np.float32), self._xc_row, self._yc_col, rays)
        else:
            rays[..., :3] = pose[:3, 3].astype(np.float32)
            for k in range(3):
                rays[..., 3 + k] = R[k, 0] * self._xc + R[k, 1] * self._yc + R[k, 2]
        ans = self.scene.cast_rays(self._o3c.Tensor.from_numpy(rays))
        out = {k: ans[k].numpy() for k in ("t_hit", "geometry_ids", "primitive_ids", "primitive_normals")}
        out["rays"] = rays
        return out

    def render(self, pose: Annotated[np.ndarray, "(4, 4) camera-to-world"],
               rng: np.random.Generator | None = None) -> RenderedFrame:
        """One frame; ``rng`` draws the sensor noise (none without it)."""
        if kernels.ENABLED:
            return self._render_kernels(pose, rng)
        return self.render_numpy(pose, rng)

    def _render_kernels(self, pose: np.ndarray, rng: np.random.Generator | None) -> RenderedFrame:
        """:meth:`render_numpy`'s frame, byte for byte, from the kernels of
        :mod:`shared.synth.kernels` (patterned materials still in numpy)."""
        cfg = self.cfg
        hits = self.cast(pose)
        t_hit = hits["t_hit"]
        H, W = t_hit.shape
        obj, light, base, shade = self.shade_kernels(hits)
        rgb_noise = rng is not None and cfg.rgb_noise_std > 0
        depth_noise = rng is not None and cfg.depth_noise_std > 0
        dy = dx = 0
        if rgb_noise:
            dy, dx = int(rng.integers(H)), int(rng.integers(W))
        rgb = np.empty((H, W, 3), np.uint8)
        inst = np.empty((H, W), np.int32)
        depth = np.empty((H, W), np.float32)
        kernels.compose(
            t_hit, base, shade, light, obj, cfg.textures, self._noise, dy, dx,
            np.float32(cfg.rgb_noise_std if rgb_noise else 0.0), np.float32(cfg.depth_max), not depth_noise,
            rgb, inst, depth,
        )
        if depth_noise:
            hit = np.isfinite(t_hit)
            noise = rng.standard_normal(depth.shape, dtype=np.float32) * np.float32(cfg.depth_noise_std)
            depth = np.where(hit, depth + noise * depth**2, np.float32(0))
            depth = np.where((depth > 0) & (depth <= cfg.depth_max), depth, np.float32(0)).astype(np.float32)
        return RenderedFrame(rgb, depth, inst)

    def shade_numpy(self, hits: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The hit mask (H, W), and for the hits in raster order the object ids (N,) int32 and
        the lit colour (N, 3) float32 in 0-255 units, before noise and rounding."""
        cfg = self.cfg
        t_hit = hits["t_hit"]
        H, W = t_hit.shape
        hit = np.isfinite(t_hit)
        everywhere = bool(hit.all())

        def pick(a: np.ndarray) -> np.ndarray:
            # Inside closed rooms every ray hits: plain reshapes then replace masked gathers.
            return a.reshape(H * W, *a.shape[2:]) if everywhere else a[hit]

        g = pick(hits["geometry_ids"]).astype(np.int64)
        obj = self.geom_obj.take(g)
        part = self.tri_part.take(self.tri_offset.take(g) + pick(hits["primitive_ids"]).astype(np.int64))
        # Shading works on one (N,) float32 array per coordinate: much faster in numpy than
        # (N, 3) arrays with tiny matrix products. float32 keeps micrometres at 20 m.
        z = pick(t_hit)
        rays = hits["rays"]
        d = [pick(rays[..., 3 + k]) for k in range(3)]
        p = [rays[0, 0, k] + d[k] * z for k in range(3)]
        nrm = pick(hits["primitive_normals"])
        n = [np.ascontiguousarray(nrm[:, k]) for k in range(3)]
        # Light the face the camera sees, whichever way the triangle is wound.
        flip = np.where(n[0] * d[0] + n[1] * d[1] + n[2] * d[2] > 0, np.float32(-1), np.float32(1))
        n = [c * flip for c in n]
        light = np.full(len(z), cfg.ambient, np.float32)
        for sun, weight in zip(SUNS.astype(np.float32), SUN_WEIGHTS, strict=True):
            light += np.float32(cfg.sun_strength * weight) * np.maximum(n[0] * sun[0] + n[1] * sun[1] + n[2] * sun[2], 0)
        light += np.float32(cfg.bounce) * np.maximum(-n[2], 0)
        for lamp in self.lamps.astype(np.float32):
            to = [lamp[k] - p[k] for k in range(3)]
            dist2 = np.maximum(to[0] * to[0] + to[1] * to[1] + to[2] * to[2], np.float32(1e-12))
            lam = np.maximum(n[0] * to[0] + n[1] * to[1] + n[2] * to[2], 0) / np.sqrt(dist2)
            light += np.float32(cfg.lamp_strength) * lam / (1 + dist2 / np.float32(LAMP_FALLOFF**2))
        local = self.table.to_local_soa(part, p)
        color = albedo(self.table, part, local, cfg.textures)
        color *= (light * np.float32(255.0))[:, None]
        return hit, obj, color

    def shade_kernels(self, hits: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """For the hits in raster order: object ids (N,) int32, light (N,) float32, and the
        albedo (N, 3) float32 before the grime shade (N,) float32 that textures multiply it by
        (see :func:`shared.synth.kernels.compose`)."""
        cfg, table = self.cfg, self.table
        t_hit = hits["t_hit"]
        size = t_hit.size
        obj = np.empty(size, np.int32)
        part = np.empty(size, np.int32)
        local = np.empty((size, 3), np.float32)
        light = np.empty(size, np.float32)
        base = np.empty((size, 3), np.float32)
        shade = np.empty(size, np.float32)
        pat = np.empty(size, np.int16)
        n = kernels.shade_hits(
            t_hit.reshape(size), hits["geometry_ids"].reshape(size), hits["primitive_ids"].reshape(size),
            hits["primitive_normals"].reshape(size, 3), hits["rays"].reshape(size, 6),
            self.geom_obj, self.tri_offset, self.tri_part,
            self._suns, self._sun_weights, np.float32(cfg.ambient), np.float32(cfg.bounce),
            self._lamps32, np.float32(cfg.lamp_strength), np.float32(LAMP_FALLOFF**2),
            table.rot32, table.trans32, table.color, table.color2, table.pattern, table.scale, _FLAT,
            cfg.textures, obj, part, local, light, base, shade, pat,
        )
        if cfg.textures and n:
            kinds = np.flatnonzero(np.bincount(pat[:n]))
            apply_patterns(table, part[:n], local[:n], pat[:n], kinds, base[:n])
        return obj[:n], light[:n], base[:n], shade[:n]

    def render_numpy(self, pose: Annotated[np.ndarray, "(4, 4) camera-to-world"],
                     rng: np.random.Generator | None = None) -> RenderedFrame:
        """:meth:`render` in numpy: the reference of the kernels (used without numba)."""
        cfg = self.cfg
        hits = self.cast(pose)
        t_hit = hits["t_hit"]
        H, W = t_hit.shape
        hit, obj, color = self.shade_numpy(hits)
        everywhere = bool(hit.all())
        if everywhere:
            rgb = color.reshape(H, W, 3)
            inst = obj.reshape(H, W).astype(np.int32)
        else:
            rgb = np.zeros((H, W, 3), np.float32)
            rgb[hit] = color
            inst = np.full((H, W), -1, np.int32)
            inst[hit] = obj
        depth = np.where(hit, t_hit, np.float32(0)).astype(np.float32)
        if rng is not None and cfg.rgb_noise_std > 0:
            # A random window of a fixed noise field: per-frame draws cost more than the shading.
            dy, dx = int(rng.integers(H)), int(rng.integers(W))
            rgb += self._noise[dy:dy + H, dx:dx + W] * np.float32(cfg.rgb_noise_std)
        if rng is not None and cfg.depth_noise_std > 0:
            noise = rng.standard_normal(depth.shape, dtype=np.float32) * np.float32(cfg.depth_noise_std)
            depth = np.where(hit, depth + noise * depth**2, np.float32(0))
        depth = np.where((depth > 0) & (depth <= cfg.depth_max), depth, np.float32(0)).astype(np.float32)
        return RenderedFrame(np.clip(np.rint(rgb), 0, 255).astype(np.uint8), depth, inst)
