"""Builders of floor-standing and wall-mounted furniture from primitives.

Each builder draws sizes and materials from ``rng`` and returns a :class:`Template` in the
object frame (see ``shared.synth.templates``). Parts that meet overlap by a few millimetres
so that no two faces are coplanar (a coplanar tie would make the nearest hit ambiguous).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from shared.synth import palette as pal
from shared.synth.primitives import (
    Material,
    Part,
    Pattern,
    box,
    ellipsoid,
    frustum,
    rot_x,
    rot_z,
    translation,
)
from shared.synth.templates import Surface, Template
from shared.synth.textures import MOTIFS
from shared.synth.vocabulary import MOTIF_DEPICTIONS

U = np.random.Generator
SINK = 0.005
"""How far a leg or post reaches into the part it carries."""


def _legs(w: float, d: float, h: float, size: float, inset: float, mat: Material, round_: bool = False) -> list[Part]:
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x = sx * (w / 2 - inset - size / 2)
            y = sy * (d / 2 - inset - size / 2)
            if round_:
                out.append(frustum(size / 2, size / 2, h + SINK, (x, y, 0), mat))
            else:
                out.append(box((size, size, h + SINK), (x, y, (h + SINK) / 2), mat))
    return out


def chair(rng: U) -> Template:
    w, d = rng.uniform(0.42, 0.5), rng.uniform(0.42, 0.5)
    seat_h, t, back_h = rng.uniform(0.43, 0.48), 0.04, rng.uniform(0.38, 0.5)
    frame = pal.wood(rng) if rng.random() < 0.6 else pal.paint(rng)
    seat = frame if rng.random() < 0.5 else pal.fabric(rng, patterned=False)[0]
    parts = [box((w, d, t), (0, 0, seat_h - t / 2), seat)]
    parts += _legs(w, d, seat_h - t, 0.035, 0.006, frame)
    parts.append(box((w - 0.012, 0.03, back_h + SINK), (0, d / 2 - 0.021, seat_h + back_h / 2 - SINK / 2), frame))
    return Template("chair", parts)


def stool(rng: U) -> Template:
    r, h = rng.uniform(0.16, 0.2), rng.uniform(0.5, 0.72)
    mat = pal.wood(rng) if rng.random() < 0.5 else pal.paint(rng, pal.BRIGHT)
    legs_mat = pal.metal(rng)
    parts = [frustum(r, r, 0.04, (0, 0, h - 0.04), mat)]
    for k in range(4):
        a = k * math.pi / 2 + math.pi / 4
        parts.append(frustum(0.014, 0.014, h - 0.04 + SINK, (0.7 * r * math.cos(a), 0.7 * r * math.sin(a), 0), legs_mat))
    parts.append(frustum(0.55 * r, 0.55 * r, 0.02, (0, 0, h * 0.35), legs_mat))
    return Template("stool", parts)


def _upholstered(rng: U, w: float, d: float, category: str) -> Template:
    mat, deps = pal.fabric(rng)
    legs = pal.wood(rng)
    base_z, seat_top, arm_w, back_d = 0.08, rng.uniform(0.4, 0.46), rng.uniform(0.12, 0.18), rng.uniform(0.16, 0.22)
    back_h = rng.uniform(0.75, 0.9)
    arm_h = seat_top + rng.uniform(0.14, 0.22)
    # Base, back and arms are offset by a centimetre from each other's outer faces: coplanar
    # overlapping faces would make the nearest hit (and so the texture) ambiguous.
    parts = _legs(w, d, base_z, 0.05, 0.04, legs, round_=True)
    parts.append(box((w - 0.02, d - 0.03, seat_top - 0.1 - base_z), (0, 0.005, (base_z + seat_top - 0.1) / 2), mat))
    parts.append(box((w - 0.02, back_d, back_h - base_z - 0.01), (0, d / 2 - back_d / 2, (back_h + base_z + 0.01) / 2), mat))
    for sx in (-1, 1):
        parts.append(box((arm_w, d - back_d + SINK, arm_h - base_z - 0.01), (sx * (w / 2 - arm_w / 2), -back_d / 2 + SINK / 2, (arm_h + base_z + 0.01) / 2), mat))
    inner = w - 2 * arm_w
    n = 1 if inner < 1.0 else (2 if inner < 1.7 else 3)
    cushion_mat = Material(pal.jitter(rng, mat.color, 0.03), mat.color2, mat.pattern, mat.scale, mat.axis)
    for k in range(n):
        cw = inner / n
        x = -inner / 2 + cw * (k + 0.5)
        parts.append(box((cw - 0.01, d - back_d - 0.02, 0.1 + SINK), (x, -back_d / 2 - 0.01 + SINK, seat_top - 0.05 - SINK / 2), cushion_mat))
    seat = Surface((-inner / 2 + 0.05, d / 2 - back_d - 0.22, inner / 2 - 0.05, d / 2 - back_d - 0.02), seat_top, math.inf, "seat")
    return Template(category, parts, [seat], deps)


def armchair(rng: U) -> Template:
    return _upholstered(rng, rng.uniform(0.75, 0.9), rng.uniform(0.75, 0.85), "armchair")


def sofa(rng: U) -> Template:
    return _upholstered(rng, rng.uniform(1.7, 2.3), rng.uniform(0.85, 0.95), "sofa")


def _table(rng: U, w: float, d: float, h: float, category: str, round_legs: bool) -> Template:
    top_mat = pal.wood(rng) if rng.random() < 0.75 else pal.paint(rng)
    leg_mat = top_mat if rng.random() < 0.6 else pal.metal(rng)
    t = 0.04
    parts = [box((w, d, t), (0, 0, h - t / 2), top_mat)]
    parts += _legs(w, d, h - t, 0.05, 0.05, leg_mat, round_=round_legs)
    return Template(category, parts, [Surface((-w / 2 + 0.06, -d / 2 + 0.06, w / 2 - 0.06, d / 2 - 0.06), h, math.inf, "top")])


def table(rng: U) -> Template:
    return _table(rng, rng.uniform(1.2, 1.7), rng.uniform(0.78, 0.95), rng.uniform(0.72, 0.77), "table", rng.random() < 0.4)


def coffee_table(rng: U) -> Template:
    return _table(rng, rng.uniform(0.9, 1.2), rng.uniform(0.5, 0.65), rng.uniform(0.4, 0.46), "coffee table", rng.random() < 0.5)


def desk(rng: U) -> Template:
    w, d, h = rng.uniform(1.2, 1.5), rng.uniform(0.6, 0.72), rng.uniform(0.73, 0.76)
    top = pal.wood(rng) if rng.random() < 0.6 else pal.paint(rng)
    body = top if rng.random() < 0.5 else pal.paint(rng)
    t, uw = 0.035, rng.uniform(0.38, 0.45)
    side = 1 if rng.random() < 0.5 else -1
    parts = [box((w, d, t), (0, 0, h - t / 2), top)]
    parts.append(box((uw, d - 0.04, h - t + SINK), (side * (w / 2 - uw / 2 - 0.01), 0, (h - t + SINK) / 2), body))
    for k in range(3):
        z = (h - t) * (k + 0.5) / 3
        parts.append(box((uw - 0.04, 0.02, (h - t) / 3 - 0.03), (side * (w / 2 - uw / 2 - 0.01), -(d - 0.04) / 2 - 0.008, z), pal.solid(pal.jitter(rng, body.color, 0.04))))
        parts.append(box((0.1, 0.02, 0.015), (side * (w / 2 - uw / 2 - 0.01), -(d - 0.04) / 2 - 0.025, z + 0.04), pal.metal(rng)))
    parts.append(box((0.04, d - 0.04, h - t + SINK), (-side * (w / 2 - 0.03), 0, (h - t + SINK) / 2), body))
    parts.append(box((w - uw - 0.06, 0.02, 0.35), (-side * (uw / 2 + 0.015), d / 2 - 0.04, h - t - 0.175 + SINK), body))
    return Template("desk", parts, [Surface((-w / 2 + 0.05, -d / 2 + 0.05, w / 2 - 0.05, d / 2 - 0.04), h, math.inf, "top")])


def office_chair(rng: U) -> Template:
    fab, _ = pal.fabric(rng, patterned=False, colors=((0.12, 0.12, 0.14), (0.2, 0.25, 0.4), (0.45, 0.12, 0.12), (0.35, 0.35, 0.37)))
    dark = pal.solid((0.08, 0.08, 0.09))
    seat_h = rng.uniform(0.46, 0.52)
    parts = [box((0.48, 0.46, 0.08), (0, 0, seat_h - 0.04), fab)]
    parts.append(frustum(0.025, 0.025, seat_h - 0.08 - 0.06 + SINK, (0, 0, 0.06), pal.metal(rng)))
    spin = rng.uniform(0, 2 * math.pi / 5)
    for k in range(5):
        a = spin + k * 2 * math.pi / 5
        arm = Part("box", (0.3, 0.04, 0.03), rot_z(a) @ translation(0.15, 0, 0.06), dark)
        parts.append(arm)
        parts.append(ellipsoid((0.025, 0.025, 0.025), (0.28 * math.cos(a), 0.28 * math.sin(a), 0.025), dark))
    back = Part("box", (0.44, 0.05, 0.5), translation(0, 0.22, seat_h + 0.02) @ rot_x(-0.12) @ translation(0, 0, 0.25), fab)
    parts.append(back)
    return Template("office chair", parts)


def bed(rng: U) -> Template:
    w, d = rng.uniform(1.4, 1.8), rng.uniform(2.0, 2.1)
    frame, linen = pal.wood(rng), pal.solid(pal.jitter(rng, (0.93, 0.93, 0.9), 0.03))
    duvet, deps = pal.fabric(rng)
    fh, mh = 0.32, 0.2
    parts = [box((w, d, fh), (0, 0, fh / 2), frame)]
    parts.append(box((w - 0.06, d - 0.1, mh + SINK), (0, -0.02, fh + mh / 2 - SINK / 2), linen))
    dl = d * 0.68
    parts.append(box((w - 0.02, dl, 0.05), (0, -d / 2 + dl / 2 - 0.03, fh + mh + 0.02), duvet))
    parts.append(box((w + 0.04, 0.08, rng.uniform(0.9, 1.15)), (0, d / 2 - 0.04, rng.uniform(0.45, 0.57)), frame))
    pillows = Surface((-w / 2 + 0.08, d / 2 - 0.62, w / 2 - 0.08, d / 2 - 0.12), fh + mh, math.inf, "mattress")
    return Template("bed", parts, [pillows], deps)


def bookshelf(rng: U) -> Template:
    w, d, h = rng.uniform(0.8, 1.2), rng.uniform(0.3, 0.38), rng.uniform(1.6, 2.0)
    mat = pal.wood(rng) if rng.random() < 0.6 else pal.paint(rng)
    b, plinth = 0.02, 0.06
    inner_w = w - 2 * b + 2 * SINK
    # Boards are recessed a few millimetres from the side panels' faces (no coplanar faces).
    parts = [box((b, d, h - b + SINK), (s * (w / 2 - b / 2), 0, (h - b + SINK) / 2), mat) for s in (-1, 1)]
    parts.append(box((w + 0.01, d + 0.01, b), (0, 0, h - b / 2), mat))
    parts.append(box((inner_w, 0.01, h - b), (0, d / 2 - 0.008, (h - b) / 2 + SINK), pal.solid(pal.jitter(rng, mat.color, 0.05))))
    parts.append(box((inner_w, d - 0.03, plinth), (0, -0.005, plinth / 2 + 0.002), mat))
    n = int(rng.integers(3, 6))
    levels = np.linspace(plinth, h - b, n + 1)
    surfaces = []
    for k, z in enumerate(levels[:-1]):
        top = z + 0.002 if k == 0 else z + b / 2
        if k > 0:
            parts.append(box((inner_w, d - 0.016, b), (0, -0.001, z), mat))
        clear = levels[k + 1] - b / 2 - top - 0.02
        surfaces.append(Surface((-w / 2 + b + 0.01, -d / 2 + 0.02, w / 2 - b - 0.01, d / 2 - 0.02), top, clear, "shelf"))
    surfaces.append(Surface((-w / 2 + 0.05, -d / 2 + 0.04, w / 2 - 0.05, d / 2 - 0.04), h, math.inf, "top"))
    return Template("bookshelf", parts, surfaces)


def _cupboard(rng: U, w: float, d: float, h: float, category: str, doors: int, top_surface: bool) -> Template:
    body = pal.wood(rng) if rng.random() < 0.5 else pal.paint(rng)
    front = pal.solid(pal.jitter(rng, body.color, 0.05)) if rng.random() < 0.5 else body
    handle = pal.metal(rng)
    plinth = 0.06
    parts = [box((w, d, h - plinth + SINK), (0, 0, plinth + (h - plinth) / 2 - SINK / 2), body)]
    parts.append(box((w - 0.04, d - 0.04, plinth), (0, 0, plinth / 2), pal.solid((0.15, 0.15, 0.15))))
    dw = (w - 0.02) / doors
    for k in range(doors):
        x = -w / 2 + 0.01 + dw * (k + 0.5)
        parts.append(box((dw - 0.01, 0.02, h - plinth - 0.03), (x, -d / 2 - 0.008, plinth + (h - plinth) / 2), front))
        hx = x + (dw / 2 - 0.05) * (1 if k % 2 == 0 else -1) if doors > 1 else x
        hz = plinth + (h - plinth) * (0.55 if h > 1.2 else 0.8)
        parts.append(box((0.02, 0.025, 0.12 if h > 1.2 else 0.02), (hx, -d / 2 - 0.03, hz), handle))
    surfaces = [Surface((-w / 2 + 0.04, -d / 2 + 0.04, w / 2 - 0.04, d / 2 - 0.04), h, math.inf, "top")] if top_surface else []
    return Template(category, parts, surfaces)


def cabinet(rng: U) -> Template:
    w = rng.uniform(0.8, 1.4)
    return _cupboard(rng, w, rng.uniform(0.4, 0.5), rng.uniform(0.75, 0.95), "cabinet", 2 if w < 1.1 else 3, True)


def wardrobe(rng: U) -> Template:
    return _cupboard(rng, rng.uniform(1.0, 1.4), rng.uniform(0.55, 0.62), rng.uniform(1.9, 2.1), "wardrobe", 2, False)


def nightstand(rng: U) -> Template:
    return _cupboard(rng, rng.uniform(0.4, 0.5), rng.uniform(0.36, 0.42), rng.uniform(0.5, 0.6), "nightstand", 1, True)


def tv_stand(rng: U) -> Template:
    return _cupboard(rng, rng.uniform(1.3, 1.8), rng.uniform(0.38, 0.45), rng.uniform(0.42, 0.52), "tv stand", 3, True)


def rug(rng: U) -> Template:
    mat, deps = pal.fabric(rng, colors=pal.FABRICS + pal.BRIGHT)
    w, d = rng.uniform(1.4, 2.4), rng.uniform(1.0, 1.7)
    return Template("rug", [box((w, d, 0.012), (0, 0, 0.006), mat)], [], deps)


def trash_bin(rng: U) -> Template:
    r, h = rng.uniform(0.12, 0.16), rng.uniform(0.3, 0.42)
    mat = pal.paint(rng, pal.BRIGHT + pal.METALS)
    return Template("trash bin", [frustum(r * 0.85, r, h, (0, 0, 0), mat), frustum(r * 1.03, r * 1.03, 0.02, (0, 0, h - 0.015), pal.solid(pal.jitter(rng, mat.color, 0.1)))])


def potted_plant(rng: U, scale: float = 1.0) -> Template:
    pot_mat = pal.paint(rng, ((0.72, 0.38, 0.22), (0.9, 0.9, 0.88), (0.2, 0.2, 0.22), (0.35, 0.45, 0.6)))
    leaf = Material(pal.jitter(rng, (0.2, 0.5, 0.18), 0.08), (0.1, 0.3, 0.08), Pattern.NOISE, 30.0)
    rb, h = rng.uniform(0.1, 0.17) * scale, rng.uniform(0.22, 0.35) * scale
    rt = rb * 1.25
    parts = [frustum(rb, rt, h, (0, 0, 0), pot_mat), frustum(rt * 0.93, rt * 0.93, 0.015, (0, 0, h - 0.01), pal.solid((0.25, 0.17, 0.1)))]
    n = int(rng.integers(3, 7))
    top = h + rng.uniform(0.35, 0.7) * scale
    for _ in range(n):
        a = rng.uniform(0, 2 * math.pi)
        off = rng.uniform(0, rt * 0.9)
        z = rng.uniform(h + 0.08 * scale, top)
        rad = rng.uniform(0.12, 0.2) * scale
        parts.append(ellipsoid((rad, rad * rng.uniform(0.7, 1.0), rad * rng.uniform(0.8, 1.3)), (off * math.cos(a), off * math.sin(a), z), leaf))
    parts.append(frustum(0.012 * scale, 0.012 * scale, top - h, (0, 0, h - 0.005), pal.solid((0.3, 0.22, 0.1))))
    return Template("potted plant", parts)


def floor_lamp(rng: U) -> Template:
    pole = pal.metal(rng)
    shade = pal.solid(pal.jitter(rng, (0.95, 0.9, 0.78), 0.04))
    h = rng.uniform(1.45, 1.7)
    rs = rng.uniform(0.18, 0.24)
    return Template("floor lamp", [
        frustum(0.15, 0.14, 0.03, (0, 0, 0), pole),
        frustum(0.014, 0.014, h - 0.03 + SINK, (0, 0, 0.03 - SINK), pole),
        frustum(rs, rs * 0.65, 0.32, (0, 0, h - 0.1), shade),
    ])


def radiator(rng: U) -> Template:
    w, h = rng.uniform(0.6, 1.2), rng.uniform(0.45, 0.6)
    mat = Material(pal.jitter(rng, (0.93, 0.93, 0.92), 0.02), (0.7, 0.7, 0.7), Pattern.STRIPES, 28.0, 0)
    parts = [box((w, 0.09, h), (0, 0, 0.12 + h / 2), mat)]
    parts += [box((0.03, 0.05, 0.12 + SINK), (s * (w / 2 - 0.08), 0, (0.12 + SINK) / 2), pal.solid((0.8, 0.8, 0.8))) for s in (-1, 1)]
    return Template("radiator", parts)


def picture_frame(rng: U) -> Template:
    w, h = rng.uniform(0.4, 1.0), rng.uniform(0.3, 0.75)
    border = rng.uniform(0.03, 0.06)
    frame = pal.wood(rng) if rng.random() < 0.5 else pal.solid(pal.pick(rng, ((0.1, 0.1, 0.1), (0.8, 0.65, 0.3), (0.95, 0.95, 0.95))))
    motif = int(rng.integers(len(MOTIFS)))
    canvas = Material(pal.jitter(rng, (0.95, 0.95, 0.95), 0.03), None, Pattern.PICTURE, 1.0, 0, motif)
    parts = [box((w, 0.03, h), (0, 0, h / 2), frame), box((w - 2 * border, 0.012, h - 2 * border), (0, -0.015 - 0.004, h / 2), canvas)]
    return Template("picture frame", parts, [], MOTIF_DEPICTIONS[MOTIFS[motif]])


def whiteboard(rng: U) -> Template:
    w, h = rng.uniform(1.2, 1.8), rng.uniform(0.8, 1.1)
    alu = pal.solid((0.72, 0.73, 0.75))
    parts = [box((w, 0.02, h), (0, 0, h / 2), alu), box((w - 0.04, 0.012, h - 0.04), (0, -0.014, h / 2), Material((0.97, 0.97, 0.97), (0.85, 0.87, 0.9), Pattern.NOISE, 3.0))]
    parts.append(box((w * 0.6, 0.06, 0.02), (0, -0.04, 0.0 + 0.01), alu))
    return Template("whiteboard", parts)


def clock(rng: U) -> Template:
    r = rng.uniform(0.13, 0.18)
    rim = pal.pick(rng, ((0.1, 0.1, 0.1), (0.55, 0.37, 0.22), (0.75, 0.76, 0.78), (0.8, 0.2, 0.2)))
    face = Material((0.96, 0.96, 0.94), rim, Pattern.CLOCK, 1.0, 0, int(rng.integers(720)))
    part = Part("frustum", (r, r, 0.04), translation(0, -0.02, r) @ rot_x(math.pi / 2), face)
    return Template("clock", [part])


FURNITURE: dict[str, Callable[[U], Template]] = {
    "chair": chair, "stool": stool, "armchair": armchair, "sofa": sofa, "table": table,
    "coffee table": coffee_table, "desk": desk, "office chair": office_chair, "bed": bed,
    "bookshelf": bookshelf, "cabinet": cabinet, "wardrobe": wardrobe, "nightstand": nightstand,
    "tv stand": tv_stand, "rug": rug, "trash bin": trash_bin, "potted plant": potted_plant,
    "floor lamp": floor_lamp, "radiator": radiator, "picture frame": picture_frame,
    "whiteboard": whiteboard, "clock": clock,
}
"""Builders of the pieces a room is furnished with (small objects are in ``items``)."""

WALL_HUNG = {"picture frame": 1.55, "whiteboard": 1.4, "clock": 1.9}
"""Wall-hung categories and the height of their centre (m)."""
