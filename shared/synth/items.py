"""Builders of small objects that stand on furniture (the clutter of a room)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from shared.synth import palette as pal
from shared.synth.furniture import SINK, potted_plant
from shared.synth.primitives import (
    Material,
    Part,
    Pattern,
    box,
    ellipsoid,
    frustum,
    rot_x,
    translation,
)
from shared.synth.templates import Template, lay_down

U = np.random.Generator

SCREEN_DARK = Material((0.04, 0.04, 0.05), (0.2, 0.22, 0.26), Pattern.SCREEN)


def _display(rng: U, category: str, w: float, neck: float, depth: float) -> Template:
    h = w * 0.5625 + 0.04
    shell = pal.solid(pal.pick(rng, ((0.08, 0.08, 0.09), (0.2, 0.2, 0.22), (0.75, 0.76, 0.78))))
    return Template(category, [
        box((max(0.22, w * 0.3), 0.18, 0.02), (0, 0, 0.01), shell),
        box((0.05, 0.03, neck + SINK * 2), (0, 0.02, 0.02 + neck / 2), shell),
        box((w, depth, h), (0, 0, 0.02 + neck + h / 2), SCREEN_DARK),
        box((w * 0.5, 0.03, h * 0.5), (0, depth / 2 + 0.012, 0.02 + neck + h / 2), shell),
    ])


def tv(rng: U) -> Template:
    return _display(rng, "tv", rng.uniform(0.9, 1.25), rng.uniform(0.05, 0.08), 0.05)


def monitor(rng: U) -> Template:
    return _display(rng, "monitor", rng.uniform(0.5, 0.65), rng.uniform(0.1, 0.16), 0.03)


def keyboard(rng: U) -> Template:
    dark = rng.random() < 0.6
    c1, c2 = ((0.12, 0.12, 0.13), (0.3, 0.3, 0.32)) if dark else ((0.92, 0.92, 0.9), (0.7, 0.7, 0.7))
    keys = Material(c1, c2, Pattern.CHECKER, 55.0)
    return Template("keyboard", [box((rng.uniform(0.4, 0.46), 0.14, 0.022), (0, 0, 0.011), keys)])


def laptop(rng: U) -> Template:
    w, d = rng.uniform(0.3, 0.36), rng.uniform(0.21, 0.25)
    shell = pal.solid(pal.pick(rng, ((0.7, 0.71, 0.73), (0.15, 0.15, 0.16), (0.85, 0.85, 0.86))))
    lid_h, tilt = d * 0.95, rng.uniform(0.2, 0.4)
    base = box((w, d, 0.02), (0, 0, 0.01), shell)
    keys = box((w * 0.85, d * 0.45, 0.004), (0, 0.0, 0.02), Material((0.1, 0.1, 0.1), (0.3, 0.3, 0.3), Pattern.CHECKER, 60.0))
    hinge = translation(0, d / 2 - 0.006, 0.015) @ rot_x(-tilt)
    lid = Part("box", (w, 0.008, lid_h), hinge @ translation(0, 0, lid_h / 2), shell)
    screen = Part("box", (w * 0.9, 0.004, lid_h * 0.85), hinge @ translation(0, -0.005, lid_h / 2), SCREEN_DARK)
    return Template("laptop", [base, keys, lid, screen])


def table_lamp(rng: U) -> Template:
    base = pal.paint(rng, pal.METALS + pal.BRIGHT)
    shade = pal.solid(pal.jitter(rng, (0.95, 0.9, 0.78), 0.05))
    stem = rng.uniform(0.22, 0.35)
    rs = rng.uniform(0.11, 0.16)
    return Template("table lamp", [
        frustum(0.08, 0.07, 0.03, (0, 0, 0), base),
        frustum(0.012, 0.012, stem + SINK, (0, 0, 0.03 - SINK), base),
        frustum(rs, rs * 0.6, rs * 1.2, (0, 0, stem), shade),
    ])


def small_plant(rng: U) -> Template:
    return potted_plant(rng, scale=float(rng.uniform(0.4, 0.6)))


def vase(rng: U) -> Template:
    mat = pal.paint(rng, pal.BRIGHT + pal.PAINTS) if rng.random() < 0.6 else pal.fabric(rng)[0]
    r, h = rng.uniform(0.05, 0.09), rng.uniform(0.16, 0.3)
    if rng.random() < 0.5:
        body = ellipsoid((r, r, h * 0.35), (0, 0, h * 0.35), mat)
        neck = frustum(r * 0.45, r * 0.55, h * 0.4, (0, 0, h * 0.62), mat)
    else:
        body = frustum(r * 0.7, r, h * 0.75, (0, 0, 0), mat)
        neck = frustum(r * 0.6, r * 0.75, h * 0.25, (0, 0, h * 0.75 - SINK), mat)
    return Template("vase", [body, neck])


def bottle(rng: U) -> Template:
    glass = pal.solid(pal.pick(rng, ((0.1, 0.4, 0.15), (0.35, 0.2, 0.08), (0.2, 0.4, 0.75), (0.75, 0.85, 0.85))))
    cap = pal.solid(pal.pick(rng, pal.BRIGHT))
    r, h = rng.uniform(0.03, 0.04), rng.uniform(0.16, 0.24)
    label = Material(pal.pick(rng, pal.BRIGHT), (0.95, 0.95, 0.95), Pattern.STRIPES, 40.0, 2)
    return Template("bottle", [
        frustum(r, r, h, (0, 0, 0), glass),
        frustum(r * 1.02, r * 1.02, h * 0.35, (0, 0, h * 0.3), label),
        frustum(r, r * 0.35, 0.05, (0, 0, h - SINK), glass),
        frustum(r * 0.35, r * 0.35, 0.04, (0, 0, h + 0.05 - 2 * SINK), glass),
        frustum(r * 0.4, r * 0.4, 0.015, (0, 0, h + 0.09 - 3 * SINK), cap),
    ])


def mug(rng: U) -> Template:
    mat = pal.paint(rng, pal.BRIGHT + pal.PAINTS)
    r, h = rng.uniform(0.035, 0.045), rng.uniform(0.085, 0.105)
    return Template("mug", [
        frustum(r * 0.92, r, h, (0, 0, 0), mat),
        frustum(r * 0.8, r * 0.8, 0.004, (0, 0, h - 0.003), pal.solid((0.25, 0.13, 0.06))),
        box((0.03, 0.012, h * 0.6), (r + 0.012, 0, h * 0.5), mat),
    ])


def bowl(rng: U) -> Template:
    mat = pal.paint(rng, pal.BRIGHT + pal.PAINTS)
    r = rng.uniform(0.08, 0.12)
    return Template("bowl", [frustum(r * 0.5, r, r * 0.6, (0, 0, 0), mat), frustum(r * 0.85, r * 0.85, 0.004, (0, 0, r * 0.6 - 0.003), pal.solid(pal.jitter(rng, mat.color, 0.15)))])


def book_standing(rng: U) -> Template:
    t, d, h = rng.uniform(0.02, 0.05), rng.uniform(0.15, 0.22), rng.uniform(0.18, 0.3)
    cover = pal.solid(pal.pick(rng, pal.BRIGHT + pal.FABRICS))
    pages = pal.solid((0.93, 0.91, 0.85))
    c = 0.003
    return Template("book", [
        box((c, d, h), (-t / 2 + c / 2, 0, h / 2), cover),
        box((c, d, h), (t / 2 - c / 2, 0, h / 2), cover),
        box((t - 2 * c + 2 * SINK, c, h), (0, -d / 2 + c / 2, h / 2), cover),
        box((t - 2 * c + 2 * SINK, d - c - 0.006, h - 0.008), (0, c / 2 - 0.003 + SINK / 2, h / 2), pages),
    ])


def book_lying(rng: U) -> Template:
    return lay_down(book_standing(rng))


def storage_box(rng: U, scale: float = 1.0) -> Template:
    w, d, h = (rng.uniform(0.2, 0.4) * scale, rng.uniform(0.15, 0.3) * scale, rng.uniform(0.1, 0.25) * scale)
    if rng.random() < 0.5:
        mat = Material(pal.jitter(rng, (0.68, 0.5, 0.32), 0.04), (0.55, 0.4, 0.25), Pattern.NOISE, 20.0)
        tape = pal.solid((0.8, 0.72, 0.55))
        return Template("box", [box((w, d, h), (0, 0, h / 2), mat), box((w + 0.002, 0.05, 0.003), (0, 0, h + 0.001), tape)])
    mat, _ = pal.fabric(rng, colors=pal.BRIGHT)
    lid = pal.solid(pal.jitter(rng, mat.color, 0.1))
    return Template("box", [box((w, d, h - 0.02), (0, 0, (h - 0.02) / 2), mat), box((w + 0.01, d + 0.01, 0.025), (0, 0, h - 0.0125), lid)])


def cushion(rng: U) -> Template:
    mat, deps = pal.fabric(rng)
    s = rng.uniform(0.18, 0.23)
    # Upright against the sofa back, leaning back a little.
    part = Part("ellipsoid", (s, 0.07, s * 0.95), translation(0, 0, s * 0.95) @ rot_x(-0.25), mat)
    return Template("cushion", [part], [], deps)


def pillow(rng: U) -> Template:
    mat, deps = pal.fabric(rng, colors=pal.FABRICS + ((0.95, 0.95, 0.93),) * 3)
    rx, ry = rng.uniform(0.26, 0.32), rng.uniform(0.17, 0.21)
    return Template("pillow", [ellipsoid((rx, ry, 0.07), (0, 0, 0.07), mat)], [], deps)


ITEMS: dict[str, Callable[[U], Template]] = {
    "tv": tv, "monitor": monitor, "keyboard": keyboard, "laptop": laptop, "table lamp": table_lamp,
    "small plant": small_plant, "vase": vase, "bottle": bottle, "mug": mug, "bowl": bowl,
    "book": book_lying, "standing book": book_standing, "box": lambda r: storage_box(r),
    "big box": lambda r: storage_box(r, 1.6), "cushion": cushion,
    "pillow": pillow,
}
"""Builders of small objects by placement kind (a "standing book" is a "book", a "small plant"
a "potted plant"; the template's category says which)."""

SURFACE_ITEMS: dict[str, tuple[str, ...]] = {
    "top": ("book", "mug", "vase", "bottle", "bowl", "box", "small plant", "laptop", "table lamp"),
    "shelf": ("standing book", "standing book", "standing book", "box", "vase", "bowl", "small plant", "book"),
    "seat": ("cushion",),
    "mattress": ("pillow",),
}
"""Small objects drawn for each kind of supporting surface (repeats weigh the draw)."""
