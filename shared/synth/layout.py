"""Floor plans: axis-aligned rooms joined by doorways, and the room shell (walls with door
gaps and lintels, floor and ceiling slabs) as objects.

World frame: z up, the floor at z = 0, metres. Room rectangles are given on the wall centre
lines; each room owns the inner half of its walls, so a shared wall is two half-thickness
slabs (one per room) and each room's walls get their own paint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.synth import palette as pal
from shared.synth.config import LayoutConfig
from shared.synth.primitives import Material, Part, Pattern, box
from shared.synth.templates import Template

Rect = tuple[float, float, float, float]
"""x0, y0, x1, y1."""

FURNISHED_KINDS = ("living", "bedroom", "office", "dining")
ROOM_TYPES: dict[str, str] = {
    "living": "living room",
    "bedroom": "bedroom",
    "office": "office",
    "dining": "dining room",
    "hall": "hall",
    "corridor": "corridor",
}
"""Room kind -> the natural label ground truth gives it (``gt/rooms.json`` ``type``), the
text a room-type query or a room's name is compared with."""
SLAB = 0.05
"""Thickness of floor and ceiling slabs (m)."""


@dataclass(frozen=True)
class Room:
    name: str
    kind: str
    """living, bedroom, office, dining (furnished) or hall, corridor (bare)."""
    rect: Rect
    """On the wall centre lines."""

    @property
    def furnished(self) -> bool:
        return self.kind in FURNISHED_KINDS

    def inner(self, wall_thickness: float) -> Rect:
        h = wall_thickness / 2
        x0, y0, x1, y1 = self.rect
        return (x0 + h, y0 + h, x1 - h, y1 - h)

    def center(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.rect
        return ((x0 + x1) / 2, (y0 + y1) / 2)


@dataclass(frozen=True)
class Doorway:
    axis: str
    """"x": in a wall running along x (at y = line); "y": in a wall running along y."""
    line: float
    center: float
    """Centre of the opening along the wall."""
    width: float
    height: float
    rooms: tuple[str, str]

    def passage(self, wall_thickness: float) -> Rect:
        """The opening's footprint through the wall."""
        h, w = wall_thickness / 2, self.width / 2
        if self.axis == "x":
            return (self.center - w, self.line - h, self.center + w, self.line + h)
        return (self.line - h, self.center - w, self.line + h, self.center + w)

    def point(self) -> tuple[float, float]:
        return (self.center, self.line) if self.axis == "x" else (self.line, self.center)


@dataclass(frozen=True)
class Layout:
    rooms: list[Room]
    doors: list[Doorway]
    wall_height: float
    wall_thickness: float
    return_to_start: bool = False
    """The walk ends back in the first room (the ``revisit`` plan)."""

    def room(self, name: str) -> Room:
        return next(r for r in self.rooms if r.name == name)

    def bounds(self) -> Rect:
        r = np.array([room.rect for room in self.rooms])
        h = self.wall_thickness / 2
        return (float(r[:, 0].min() - h), float(r[:, 1].min() - h), float(r[:, 2].max() + h), float(r[:, 3].max() + h))

    def doors_of(self, room: str) -> list[Doorway]:
        return [d for d in self.doors if room in d.rooms]


def _kinds(cfg: LayoutConfig, n: int, rng: np.random.Generator) -> list[str]:
    if cfg.room_kinds:
        return [cfg.room_kinds[i % len(cfg.room_kinds)] for i in range(n)]
    out: list[str] = []
    while len(out) < n:
        out.extend(str(k) for k in rng.permutation(FURNISHED_KINDS))
    return out[:n]


def _span(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.round(rng.uniform(lo, hi), 2))


def _door_center(rng: np.random.Generator, a: float, b: float, width: float) -> float:
    """A door centre on the shared span [a, b], away from the corners."""
    margin = width / 2 + 0.45
    if b - a < 2 * margin:
        return (a + b) / 2
    return float(np.round(rng.uniform(a + margin, b - margin), 2))


def build_layout(cfg: LayoutConfig, rng: np.random.Generator) -> Layout:
    """Rooms and doorways of the configured kind of floor plan."""
    w_rng, d_rng = cfg.room_width, cfg.room_depth
    rooms: list[Room] = []
    doors: list[Doorway] = []
    if cfg.kind == "single":
        (kind,) = _kinds(cfg, 1, rng)
        W, D = _span(rng, *w_rng), _span(rng, *d_rng)
        rooms.append(Room("room0", kind, (0.0, 0.0, W, D)))
        # A short hall behind a doorway, so the opening shows a space rather than the void.
        hw, hd = 2.2, 1.8
        side = int(rng.integers(4))
        along = W if side in (0, 1) else D
        c = _door_center(rng, hw / 2, along - hw / 2, hw)
        if side == 0:
            rect, door = (c - hw / 2, -hd, c + hw / 2, 0.0), ("x", 0.0)
        elif side == 1:
            rect, door = (c - hw / 2, D, c + hw / 2, D + hd), ("x", D)
        elif side == 2:
            rect, door = (-hd, c - hw / 2, 0.0, c + hw / 2), ("y", 0.0)
        else:
            rect, door = (W, c - hw / 2, W + hd, c + hw / 2), ("y", W)
        rooms.append(Room("hall", "hall", rect))
        doors.append(Doorway(door[0], door[1], c, cfg.door_width, cfg.door_height, ("room0", "hall")))
    elif cfg.kind == "suite":
        kinds = _kinds(cfg, cfg.rooms, rng)
        x = 0.0
        for i, kind in enumerate(kinds):
            W, D = _span(rng, *w_rng), _span(rng, *d_rng)
            rooms.append(Room(f"room{i}", kind, (x, 0.0, x + W, D)))
            if i > 0:
                prev = rooms[i - 1]
                top = min(prev.rect[3], D)
                doors.append(Doorway("y", x, _door_center(rng, 0.0, top, cfg.door_width), cfg.door_width, cfg.door_height, (prev.name, rooms[i].name)))
            x += W
    elif cfg.kind == "revisit":
        ka, kb = _kinds(cfg, 2, rng)
        WA, DA = _span(rng, *w_rng), _span(rng, *d_rng)
        WB, DB = _span(rng, *w_rng), _span(rng, *d_rng)
        cw, L = cfg.corridor_width, cfg.corridor_length
        cy = _door_center(rng, 0.0, DA, cw)
        rooms.append(Room("room0", ka, (0.0, 0.0, WA, DA)))
        rooms.append(Room("corridor", "corridor", (WA, cy - cw / 2, WA + L, cy + cw / 2)))
        yb = float(np.round(cy - DB / 2 + rng.uniform(-0.25, 0.25) * (DB - cw - 1.4), 2))
        rooms.append(Room("room1", kb, (WA + L, yb, WA + L + WB, yb + DB)))
        doors.append(Doorway("y", WA, cy, cfg.door_width, cfg.door_height, ("room0", "corridor")))
        doors.append(Doorway("y", WA + L, cy, cfg.door_width, cfg.door_height, ("corridor", "room1")))
    elif cfg.kind == "building":
        _building(cfg, rng, rooms, doors)
    else:
        raise ValueError(f"unknown layout kind {cfg.kind!r}")
    return Layout(rooms, doors, cfg.wall_height, cfg.wall_thickness, return_to_start=cfg.kind == "revisit")


def _building(cfg: LayoutConfig, rng: np.random.Generator, rooms: list[Room], doors: list[Doorway]) -> None:
    """One floor: a corridor along x over y in [0, corridor_width], rooms side by side along
    its north side (west to east) and its south side, each with a doorway onto the corridor.

    Rooms are listed, and named room0, room1, ..., north row west to east and then south row
    east to west, so floor-plan order is one loop round the corridor; the corridor comes last.
    The corridor runs the length of the longer row."""
    kinds = _kinds(cfg, cfg.rooms, rng)
    cw = cfg.corridor_width
    n_north = (cfg.rooms + 1) // 2
    north = [(_span(rng, *cfg.room_width), _span(rng, *cfg.room_depth)) for _ in range(n_north)]
    south = [(_span(rng, *cfg.room_width), _span(rng, *cfg.room_depth)) for _ in range(cfg.rooms - n_north)]
    south_x = np.concatenate([[0.0], np.cumsum([w for w, _ in south])])
    placed: list[tuple[Rect, float]] = []  # (rect, line of the corridor wall) in walking order
    x = 0.0
    for w, d in north:
        placed.append(((x, cw, x + w, cw + d), cw))
        x += w
    for i in reversed(range(len(south))):
        w, d = south[i]
        x0 = float(south_x[i])
        placed.append(((x0, -d, x0 + w, 0.0), 0.0))
    for i, ((x0, y0, x1, y1), line) in enumerate(placed):
        name = f"room{i}"
        rooms.append(Room(name, kinds[i], (x0, y0, x1, y1)))
        doors.append(Doorway("x", line, _door_center(rng, x0, x1, cfg.door_width), cfg.door_width, cfg.door_height,
                             ("corridor", name)))
    length = max(x, float(south_x[-1]))
    rooms.append(Room("corridor", "corridor", (0.0, 0.0, length, cw)))


def _wall_material(rng: np.random.Generator) -> Material:
    c = pal.pick(rng, ((0.93, 0.92, 0.88), (0.85, 0.88, 0.9), (0.9, 0.85, 0.78), (0.78, 0.84, 0.78), (0.95, 0.95, 0.95)))
    return Material(c, tuple(x * 0.93 for x in c), Pattern.NOISE, 6.0)  # type: ignore[arg-type]


def _floor_material(rng: np.random.Generator, kind: str) -> Material:
    if kind in ("corridor", "hall") or rng.random() < 0.35:
        c = pal.pick(rng, ((0.8, 0.8, 0.78), (0.6, 0.58, 0.55), (0.9, 0.88, 0.82)))
        return Material(c, (0.35, 0.35, 0.35), Pattern.TILES, float(rng.choice([2.5, 3.3, 5.0])))
    c = pal.pick(rng, pal.WOODS)
    return Material(c, tuple(x * 0.75 for x in c), Pattern.PLANKS, float(rng.uniform(5, 8)), int(rng.integers(2)))  # type: ignore[arg-type]


def _intervals_minus(a: float, b: float, cuts: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out = [(a, b)]
    for c0, c1 in sorted(cuts):
        nxt = []
        for s, e in out:
            if c1 <= s or c0 >= e:
                nxt.append((s, e))
                continue
            if c0 > s:
                nxt.append((s, c0))
            if c1 < e:
                nxt.append((c1, e))
        out = nxt
    return [(s, e) for s, e in out if e - s > 1e-6]


def shell(layout: Layout, rng: np.random.Generator) -> list[tuple[str, Template]]:
    """(room name, template in world coordinates) of every wall, floor and ceiling."""
    t, H = layout.wall_thickness, layout.wall_height
    h = t / 2
    out: list[tuple[str, Template]] = []
    for room in layout.rooms:
        x0, y0, x1, y1 = room.rect
        wall_mat = _wall_material(rng)
        out.append((room.name, Template("floor", [box((x1 - x0, y1 - y0, SLAB), ((x0 + x1) / 2, (y0 + y1) / 2, -SLAB / 2), _floor_material(rng, room.kind))])))
        ceil = Material((0.96, 0.96, 0.95), (0.9, 0.9, 0.9), Pattern.NOISE, 4.0)
        out.append((room.name, Template("ceiling", [box((x1 - x0, y1 - y0, SLAB), ((x0 + x1) / 2, (y0 + y1) / 2, H + SLAB / 2), ceil)])))
        # (axis, line, start, end, inward sign): each side of the room, walls on its inner half.
        sides = (("x", y0, x0, x1, 1), ("x", y1, x0, x1, -1), ("y", x0, y0, y1, 1), ("y", x1, y0, y1, -1))
        for axis, line, a, b, sign in sides:
            cuts = [(d.center - d.width / 2, d.center + d.width / 2, d.height) for d in layout.doors_of(room.name)
                    if d.axis == axis and abs(d.line - line) < 1e-6]
            mid = line + sign * h / 2
            parts: list[Part] = []
            pieces = [(s, e, 0.0, H) for s, e in _intervals_minus(a, b, [(c0, c1) for c0, c1, _ in cuts])]
            pieces += [(c0, c1, dh, H) for c0, c1, dh in cuts]
            for s, e, z0, z1 in pieces:
                if axis == "x":
                    parts.append(box((e - s, h, z1 - z0), ((s + e) / 2, mid, (z0 + z1) / 2), wall_mat))
                else:
                    parts.append(box((h, e - s, z1 - z0), (mid, (s + e) / 2, (z0 + z1) / 2), wall_mat))
            out.append((room.name, Template("wall", parts)))
    return out
