"""An object template: parts in the object's own frame, and the surfaces other objects can
stand on.

Object frame: z up with the object's lowest point at z = 0, its footprint centred on the
origin, its front facing -y and its back at +y (a wall-mounted object's back touches the wall).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shared.synth.primitives import Part, rot_y, translation, world_mesh


@dataclass(frozen=True)
class Surface:
    """A horizontal rectangle objects can be put on, in the object frame."""

    rect: tuple[float, float, float, float]
    """x0, y0, x1, y1."""
    z: float
    """Height of the surface."""
    max_height: float
    """Free height above it (a shelf board's spacing; inf for open tops)."""
    kind: str
    """top, shelf, seat or mattress: which small objects it takes."""


@dataclass
class Template:
    """One object before placement."""

    category: str
    parts: list[Part]
    surfaces: list[Surface] = field(default_factory=list)
    depictions: tuple[str, ...] = ()
    """Instance-specific depictions (the pattern of its fabric, the subject of a picture)."""

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (min, max) of all parts, in the object frame."""
        pts = np.vstack([world_mesh(p)[0] for p in self.parts])
        return pts.min(axis=0), pts.max(axis=0)

    def size(self) -> np.ndarray:
        lo, hi = self.bounds()
        return hi - lo

    def normalized(self) -> Template:
        """The same object shifted so its footprint is centred on the origin and its lowest
        point is at z = 0 (builders need not get this exactly right)."""
        lo, hi = self.bounds()
        dx, dy, dz = -(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]
        shift = translation(dx, dy, dz)
        surfaces = [
            Surface((s.rect[0] + dx, s.rect[1] + dy, s.rect[2] + dx, s.rect[3] + dy), s.z + dz, s.max_height, s.kind)
            for s in self.surfaces
        ]
        return Template(self.category, [p.moved(shift) for p in self.parts], surfaces, self.depictions)


def lay_down(t: Template) -> Template:
    """The template rotated a quarter turn about y (a standing book put flat), back on z = 0."""
    return Template(t.category, [p.moved(rot_y(np.pi / 2)) for p in t.parts], [], t.depictions).normalized()
