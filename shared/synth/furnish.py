"""Furnishing one room: pieces against walls, groups in the middle, pictures on the walls,
and small objects on every supporting surface.

Every placement is checked against the room's inner rectangle, the approach zones of its
doorways and the boxes of what is already there; after each floor-standing piece the room's
free floor (at the camera's clearance) must stay one connected region reaching every doorway,
so the camera can always tour the room.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from shared.synth.config import FurnishConfig
from shared.synth.furniture import FURNITURE, WALL_HUNG
from shared.synth.items import ITEMS, SURFACE_ITEMS
from shared.synth.layout import Layout, Room
from shared.synth.primitives import Mat4, rot_z, translation
from shared.synth.templates import Template

log = logging.getLogger(__name__)

GAP = 0.03
"""Least horizontal gap between two pieces (m)."""
LIFT = 0.001
"""Small objects float this far above their support, so no two faces are coplanar."""
DOOR_ZONE = 1.1
"""Depth of the floor kept free in front of a doorway (m)."""

PLANS: dict[str, tuple[str, tuple[str, ...], tuple[str, ...]]] = {
    "living": ("sofa group", (), ("armchair", "bookshelf", "floor lamp", "potted plant", "cabinet",
                                             "picture frame", "picture frame", "clock", "radiator", "trash bin")),
    "bedroom": ("bed group", ("wardrobe", "cabinet"), ("rug", "picture frame", "potted plant", "desk", "clock", "trash bin",
                                                       "big box", "chair", "floor lamp", "radiator", "bookshelf")),
    "office": ("desk group", ("bookshelf",), ("cabinet", "trash bin", "whiteboard", "potted plant", "clock", "floor lamp",
                                              "stool", "picture frame", "bookshelf", "big box", "radiator")),
    "dining": ("dining group", ("cabinet",), ("picture frame", "potted plant", "clock", "stool", "floor lamp",
                                              "radiator", "bookshelf", "picture frame", "trash bin", "armchair")),
}
"""Per room style: the anchor group, pieces always tried, and the pool of optional pieces."""



def _ahead(pose: Mat4, dist: float) -> Mat4:
    """``pose`` moved ``dist`` (m) along its front, its local -y (away from the wall it backs on)."""
    front = pose[:3, :3] @ np.array([0, -1.0, 0])
    return translation(*(front * dist)) @ pose

@dataclass
class Placed:
    """An object placed in the world (its template in its own frame, and its pose)."""

    template: Template
    pose: Mat4
    room: str
    mount: str
    """floor, flat (rugs: not an obstacle), wall (hung) or item (stands on ``support``)."""
    support: int | None = None
    """Index, in the room's list, of the object it stands on."""
    lo: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hi: np.ndarray = field(default_factory=lambda: np.zeros(3))


def world_box(template: Template, pose: Mat4) -> tuple[np.ndarray, np.ndarray]:
    """World AABB of a template under ``pose`` (from its local box's corners)."""
    lo, hi = template.bounds()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    w = corners @ pose[:3, :3].T + pose[:3, 3]
    return w.min(axis=0), w.max(axis=0)


def _yaw_facing(normal: tuple[float, float]) -> float:
    """Yaw that turns an object's front (-y) to face along ``normal``."""
    return math.atan2(normal[0], -normal[1])


class RoomFurnisher:
    def __init__(self, room: Room, layout: Layout, cfg: FurnishConfig, clearance: float, rng: np.random.Generator):
        self.room, self.cfg, self.rng, self.clearance = room, cfg, rng, clearance
        self.inner = room.inner(layout.wall_thickness)
        self.door_zones: list[tuple[float, float, float, float]] = []
        self.door_cells: list[tuple[float, float]] = []
        x0, y0, x1, y1 = self.inner
        for d in layout.doors_of(room.name):
            px, py = d.point()
            pad = d.width / 2 + 0.3
            if d.axis == "x":
                self.door_zones.append((px - pad, py - DOOR_ZONE, px + pad, py + DOOR_ZONE))
                inward = 1.0 if abs(py - room.rect[1]) < 1e-6 else -1.0
                self.door_cells.append((px, py + inward * (layout.wall_thickness / 2 + clearance + 0.1)))
            else:
                self.door_zones.append((px - DOOR_ZONE, py - pad, px + DOOR_ZONE, py + pad))
                inward = 1.0 if abs(px - room.rect[0]) < 1e-6 else -1.0
                self.door_cells.append((px + inward * (layout.wall_thickness / 2 + clearance + 0.1), py))
        self.placed: list[Placed] = []

    # ------------------------------------------------------------------ checks

    def _fits(self, lo: np.ndarray, hi: np.ndarray, mount: str, ignore: tuple[int, ...] = ()) -> bool:
        x0, y0, x1, y1 = self.inner
        if lo[0] < x0 - 1e-6 or lo[1] < y0 - 1e-6 or hi[0] > x1 + 1e-6 or hi[1] > y1 + 1e-6:
            return False
        for zx0, zy0, zx1, zy1 in self.door_zones:
            if lo[0] < zx1 and hi[0] > zx0 and lo[1] < zy1 and hi[1] > zy0:
                return False
        for i, p in enumerate(self.placed):
            if i in ignore or p.mount == "item":
                continue
            if (mount == "flat") != (p.mount == "flat"):
                continue
            if (lo[0] < p.hi[0] + GAP and hi[0] > p.lo[0] - GAP and lo[1] < p.hi[1] + GAP and hi[1] > p.lo[1] - GAP
                    and lo[2] < p.hi[2] + GAP and hi[2] > p.lo[2] - GAP):
                return False
        return True

    def free_grid(self, res: float = 0.05) -> tuple[np.ndarray, int]:
        """Free floor cells at the camera's clearance, and the label of the region that holds
        the doorways (0 when they are not all in one region)."""
        x0, y0, x1, y1 = self.inner
        nx, ny = max(1, int((x1 - x0) / res)), max(1, int((y1 - y0) / res))
        cx = x0 + (np.arange(nx) + 0.5) * res
        cy = y0 + (np.arange(ny) + 0.5) * res
        c = self.clearance
        free = (cx[:, None] > x0 + c) & (cx[:, None] < x1 - c) & (cy[None, :] > y0 + c) & (cy[None, :] < y1 - c)
        for p in self.placed:
            if p.mount in ("floor",):
                free &= ~((cx[:, None] > p.lo[0] - c) & (cx[:, None] < p.hi[0] + c) & (cy[None, :] > p.lo[1] - c) & (cy[None, :] < p.hi[1] + c))
        labels, _ = ndimage.label(free, structure=np.ones((3, 3)))
        ids = set()
        for px, py in self.door_cells:
            i = int(np.clip((px - x0) / res, 0, nx - 1))
            j = int(np.clip((py - y0) / res, 0, ny - 1))
            ids.add(int(labels[i, j]))
        if not self.door_cells:
            counts = np.bincount(labels.ravel())
            counts[0] = 0
            ids = {int(np.argmax(counts))} if counts.max() > 0 else {0}
        label = ids.pop() if len(ids) == 1 else 0
        return labels == label if label else np.zeros_like(free), label

    def _tourable(self) -> bool:
        region, label = self.free_grid()
        x0, y0, x1, y1 = self.inner
        area = (x1 - x0 - 2 * self.clearance) * (y1 - y0 - 2 * self.clearance)
        return label > 0 and region.sum() * 0.05**2 >= 0.3 * area

    # -------------------------------------------------------------- placement

    def _commit(self, template: Template, pose: Mat4, mount: str, support: int | None = None) -> int:
        lo, hi = world_box(template, pose)
        self.placed.append(Placed(template, pose, self.room.name, mount, support, lo, hi))
        return len(self.placed) - 1

    def _try(self, template: Template, pose: Mat4, mount: str, ignore: tuple[int, ...] = ()) -> int | None:
        lo, hi = world_box(template, pose)
        if not self._fits(lo, hi, mount, ignore):
            return None
        idx = self._commit(template, pose, mount)
        if mount == "floor" and not self._tourable():
            self.placed.pop()
            return None
        return idx

    def _group(self, members: list[tuple[Template, Mat4, str]]) -> list[int] | None:
        """Place several pieces together, or none of them."""
        start = len(self.placed)
        for t, pose, mount in members:
            lo, hi = world_box(t, pose)
            if not self._fits(lo, hi, mount):
                del self.placed[start:]
                return None
            self._commit(t, pose, mount)
        if not self._tourable():
            del self.placed[start:]
            return None
        return list(range(start, len(self.placed)))

    def wall_pose(self, template: Template, side: int, along: float, z: float = 0.0, gap: float = 0.01) -> Mat4:
        """Pose of a piece with its back against wall ``side`` (0: y min, 1: y max, 2: x min,
        3: x max), its centre at ``along`` on the wall."""
        x0, y0, x1, y1 = self.inner
        d = template.size()[1]
        normal = ((0.0, 1.0), (0.0, -1.0), (1.0, 0.0), (-1.0, 0.0))[side]
        line = (y0, y1, x0, x1)[side]
        off = line + (normal[0] + normal[1]) * (gap + d / 2)
        x, y = (along, off) if side < 2 else (off, along)
        return translation(x, y, z) @ rot_z(_yaw_facing(normal))

    def _wall_range(self, template: Template, side: int) -> tuple[float, float]:
        x0, y0, x1, y1 = self.inner
        w = template.size()[0]
        a, b = (x0, x1) if side < 2 else (y0, y1)
        return a + w / 2 + 0.02, b - w / 2 - 0.02

    def _wall_spots(self, template: Template, tries: int, corner: bool = False) -> Iterator[tuple[int, float]]:
        """Up to ``tries`` random (wall side, position along it) where ``template`` fits, drawn
        lazily so the caller's own draws interleave with them; ``corner``: at either end."""
        for _ in range(tries):
            side = int(self.rng.integers(4))
            a, b = self._wall_range(template, side)
            if b < a:
                continue
            yield side, (a if self.rng.random() < 0.5 else b) if corner else float(self.rng.uniform(a, b))

    def place_on_wall(self, template: Template, mount: str = "floor", z: float = 0.0, tries: int = 30,
                      corner: bool = False) -> int | None:
        for side, along in self._wall_spots(template, tries, corner):
            idx = self._try(template, self.wall_pose(template, side, along, z, 0.002 if mount == "wall" else 0.01), mount)
            if idx is not None:
                return idx
        return None

    def place_center(self, build, tries: int = 25) -> list[int] | None:
        """A group built around a pose near the room centre; ``build(pose)`` lists its members."""
        x0, y0, x1, y1 = self.inner
        for _ in range(tries):
            x = (x0 + x1) / 2 + self.rng.uniform(-0.15, 0.15) * (x1 - x0)
            y = (y0 + y1) / 2 + self.rng.uniform(-0.15, 0.15) * (y1 - y0)
            yaw = float(self.rng.choice([0.0, math.pi / 2]))
            got = self._group(build(translation(x, y, 0) @ rot_z(yaw)))
            if got is not None:
                return got
        return None

    # --------------------------------------------------------------- groups

    def sofa_group(self) -> None:
        sofa = FURNITURE["sofa"](self.rng).normalized()
        table = FURNITURE["coffee table"](self.rng).normalized()
        rug = FURNITURE["rug"](self.rng).normalized()
        for side, along in self._wall_spots(sofa, 25):
            pose = self.wall_pose(sofa, side, along)
            dist = sofa.size()[1] / 2 + 0.45 + table.size()[1] / 2
            tpose, rpose = _ahead(pose, dist), _ahead(pose, dist - 0.15)
            if self._group([(sofa, pose, "floor"), (table, tpose, "floor"), (rug, rpose, "flat")]) is not None:
                # The TV goes on the opposite wall, facing the sofa.
                stand = FURNITURE["tv stand"](self.rng).normalized()
                opposite = (1, 0, 3, 2)[side]
                a, b = self._wall_range(stand, opposite)
                facing = None
                if a <= b:
                    facing = self._try(stand, self.wall_pose(stand, opposite, float(np.clip(pose[0 if side < 2 else 1, 3], a, b))), "floor")
                if facing is None:
                    self.place_on_wall(stand)
                return
        self.place_on_wall(FURNITURE["armchair"](self.rng).normalized())
        self.place_on_wall(FURNITURE["tv stand"](self.rng).normalized())

    def bed_group(self) -> None:
        bed = FURNITURE["bed"](self.rng).normalized()
        stands = [FURNITURE["nightstand"](self.rng).normalized() for _ in range(2)]
        for side, along in self._wall_spots(bed, 25):
            pose = self.wall_pose(bed, side, along)
            members = [(bed, pose, "floor")]
            for sgn, ns in zip((-1, 1), stands, strict=True):
                members.append((ns, self.wall_pose(ns, side, along + sgn * (bed.size()[0] / 2 + 0.06 + ns.size()[0] / 2)), "floor"))
            if self._group(members) is not None or self._group(members[:2]) is not None or self._group(members[:1]) is not None:
                return

    def desk_group(self) -> None:
        desk = FURNITURE["desk"](self.rng).normalized()
        chair = FURNITURE["office chair"](self.rng).normalized()
        for side, along in self._wall_spots(desk, 25):
            pose = self.wall_pose(desk, side, along)
            dist = desk.size()[1] / 2 + 0.12 + chair.size()[1] / 2
            cpose = _ahead(pose, dist) @ rot_z(math.pi + self.rng.uniform(-0.4, 0.4))
            if self._group([(desk, pose, "floor"), (chair, cpose, "floor")]) is not None or self._group([(desk, pose, "floor")]) is not None:
                return

    def dining_group(self) -> None:
        table = FURNITURE["table"](self.rng).normalized()
        w, d = table.size()[:2]
        chairs = []
        n_side = max(1, int((w - 0.1) / 0.62))
        for sgn in (-1, 1):
            for k in range(n_side):
                x = (k + 0.5) * w / n_side - w / 2
                chairs.append(((x, sgn * (d / 2 + 0.06)), (0.0, float(sgn))))
        if self.rng.random() < 0.6:
            for sgn in (-1, 1):
                chairs.append(((sgn * (w / 2 + 0.06), 0.0), (float(sgn), 0.0)))
        templates = [FURNITURE["chair"](self.rng).normalized() for _ in chairs]
        with_rug = self.rng.random() < 0.5
        rug = FURNITURE["rug"](self.rng).normalized()

        def build(pose: Mat4) -> list[tuple[Template, Mat4, str]]:
            members = [(table, pose, "floor")]
            for t, ((x, y), n) in zip(templates, chairs, strict=True):
                # Offset by half the chair's depth along the outward normal, then face the table.
                off = t.size()[1] / 2
                local = translation(x + n[0] * off, y + n[1] * off, 0) @ rot_z(_yaw_facing((-n[0], -n[1])))
                members.append((t, pose @ local, "floor"))
            if with_rug:
                members.append((rug, pose, "flat"))
            return members

        if self.place_center(build) is None:
            # Fewer chairs when the full set does not fit.
            templates, chairs = templates[:2], chairs[:2]
            if self.place_center(build) is None:
                self.place_on_wall(FURNITURE["cabinet"](self.rng).normalized())

    def single(self, category: str) -> None:
        if category in WALL_HUNG:
            t = FURNITURE[category](self.rng).normalized()
            self.place_on_wall(t, "wall", z=WALL_HUNG[category] - t.size()[2] / 2)
        elif category == "rug":
            t = FURNITURE["rug"](self.rng).normalized()
            x0, y0, x1, y1 = self.inner
            for _ in range(15):
                pose = translation(self.rng.uniform(x0 + 1, x1 - 1), self.rng.uniform(y0 + 1, y1 - 1), 0) @ rot_z(float(self.rng.choice([0, math.pi / 2])))
                if self._try(t, pose, "flat") is not None:
                    return
        elif category == "big box":
            self.place_on_wall(ITEMS["big box"](self.rng).normalized())
        else:
            corner = category in ("floor lamp", "potted plant", "trash bin")
            self.place_on_wall(FURNITURE[category](self.rng).normalized(), corner=corner and self.rng.random() < 0.7)

    # ---------------------------------------------------------- small objects

    def _put(self, support: int, surface_idx: int, template: Template, x: float, y: float, yaw: float) -> int | None:
        """Put ``template`` on a surface of ``support`` at local (x, y) if it fits there."""
        sup = self.placed[support]
        s = sup.template.surfaces[surface_idx]
        local = translation(x, y, s.z + LIFT) @ rot_z(yaw)
        lo, hi = world_box(template, local)
        x0, y0, x1, y1 = s.rect
        if lo[0] < x0 or lo[1] < y0 or hi[0] > x1 or hi[1] > y1 or hi[2] - lo[2] > s.max_height:
            return None
        pose = sup.pose @ local
        wlo, whi = world_box(template, pose)
        for i, p in enumerate(self.placed):
            if i == support:
                continue
            if p.mount == "item":
                # Only neighbours on the same surface can collide (supports do not overlap).
                if p.support != support or abs(p.lo[2] - wlo[2]) > 0.05:
                    continue
                m = 0.01
            elif p.mount == "flat":
                continue
            else:
                m = 0.0
            if (wlo[0] < p.hi[0] + m and whi[0] > p.lo[0] - m and wlo[1] < p.hi[1] + m and whi[1] > p.lo[1] - m
                    and wlo[2] < p.hi[2] and whi[2] > p.lo[2]):
                return None
        idx = self._commit(template, pose, "item", support)
        return idx

    def _scatter(self, support: int, k: int, names: tuple[str, ...], n: int) -> None:
        s = self.placed[support].template.surfaces[k]
        x0, y0, x1, y1 = s.rect
        for _ in range(n):
            if self.rng.random() > self.cfg.small_object_fill:
                continue
            name = names[int(self.rng.integers(len(names)))]
            t = ITEMS[name](self.rng).normalized()
            for _ in range(12):
                yaw = float(self.rng.uniform(-0.5, 0.5)) if name in ("laptop", "book", "keyboard") else float(self.rng.uniform(0, 2 * math.pi))
                if self._put(support, k, t, float(self.rng.uniform(x0, x1)), float(self.rng.uniform(y0, y1)), yaw) is not None:
                    break

    def _shelf_row(self, support: int, k: int) -> None:
        s = self.placed[support].template.surfaces[k]
        x0, y0, x1, y1 = s.rect
        cursor = x0 + float(self.rng.uniform(0.0, 0.15))
        while cursor < x1 - 0.05:
            name = SURFACE_ITEMS["shelf"][int(self.rng.integers(len(SURFACE_ITEMS["shelf"])))]
            run = int(self.rng.integers(2, 7)) if name == "standing book" else 1
            for _ in range(run):
                t = ITEMS[name](self.rng).normalized()
                w, d, _h = t.size()
                x = cursor + w / 2
                y = y1 - d / 2 - 0.01 if name == "standing book" else (y0 + y1) / 2
                if x + w / 2 > x1:
                    return
                if self.rng.random() < self.cfg.small_object_fill and self._put(support, k, t, x, y, 0.0) is not None:
                    cursor += w + 0.003
                else:
                    cursor += w + 0.02
            cursor += float(self.rng.uniform(0.02, 0.2))

    def clutter_surfaces(self) -> None:
        """Small objects on every surface of the pieces placed so far."""
        cap = self.cfg.max_items_per_surface
        for i in range(len(self.placed)):
            p = self.placed[i]
            if p.mount == "item" or cap == 0:
                continue
            for k, s in enumerate(p.template.surfaces):
                cat = p.template.category
                x0, y0, x1, y1 = s.rect
                if s.kind == "shelf":
                    self._shelf_row(i, k)
                    continue
                if s.kind in ("seat", "mattress"):
                    name = "cushion" if s.kind == "seat" else "pillow"
                    n = int(self.rng.integers(1, 4 if s.kind == "seat" else 3))
                    for j in range(n):
                        t = ITEMS[name](self.rng).normalized()
                        x = x0 + (j + 0.5) * (x1 - x0) / n
                        yaw = float(self.rng.uniform(-0.15, 0.15))
                        sx, sy, _ = t.size()
                        # Against the back of the seat (or the headboard), turned a little.
                        half_y = abs(math.sin(yaw)) * sx / 2 + abs(math.cos(yaw)) * sy / 2
                        self._put(i, k, t, x, y1 - half_y - 0.005, yaw)
                    continue
                if cat == "tv stand":
                    self._put(i, k, ITEMS["tv"](self.rng).normalized(), (x0 + x1) / 2, (y0 + y1) / 2, 0.0)
                elif cat == "desk":
                    mon = ITEMS["monitor"](self.rng).normalized()
                    mx = (x0 + x1) / 2 + float(self.rng.uniform(-0.15, 0.15))
                    self._put(i, k, mon, mx, y1 - mon.size()[1] / 2 - 0.03, 0.0)
                    kb = ITEMS["keyboard"](self.rng).normalized()
                    self._put(i, k, kb, mx, y0 + kb.size()[1] / 2 + 0.06, float(self.rng.uniform(-0.1, 0.1)))
                elif cat == "nightstand" and self.rng.random() < 0.7:
                    self._put(i, k, ITEMS["table lamp"](self.rng).normalized(), (x0 + x1) / 2, (y0 + y1) / 2, 0.0)
                area = (x1 - x0) * (y1 - y0)
                n = min(cap, max(1, int(area / 0.12)))
                if cat == "bookshelf":
                    n = min(n, 2)
                self._scatter(i, k, SURFACE_ITEMS["top"], n)


def furnish(room: Room, layout: Layout, cfg: FurnishConfig, clearance: float, rng: np.random.Generator) -> list[Placed]:
    """Everything in one furnished room (its shell excluded)."""
    f = RoomFurnisher(room, layout, cfg, clearance, rng)
    anchor, required, optional = PLANS[room.kind]
    getattr(f, anchor.replace(" ", "_"))()
    for cat in required:
        f.single(cat)
    lo, hi = cfg.large_objects
    n_opt = max(0, int(rng.integers(lo, hi + 1)) - 1 - len(required))
    for j in rng.permutation(len(optional))[:n_opt]:
        f.single(optional[int(j)])
    # Pieces that found no room are replaced by others from the pool, up to the maximum.
    for j in rng.permutation(len(optional)):
        if sum(p.mount != "item" for p in f.placed) >= hi:
            break
        f.single(optional[int(j)])
    f.clutter_surfaces()
    log.debug("room %s (%s): %d objects", room.name, room.kind, len(f.placed))
    return f.placed
