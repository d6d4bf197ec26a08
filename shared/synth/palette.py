"""Colour palettes and material factories shared by the object builders."""

from __future__ import annotations

import colorsys

import numpy as np

from shared.synth.primitives import Material, Pattern
from shared.synth.vocabulary import PATTERN_DEPICTIONS

RGB = tuple[float, float, float]

WOODS: tuple[RGB, ...] = ((0.55, 0.37, 0.22), (0.72, 0.55, 0.36), (0.38, 0.24, 0.14), (0.84, 0.72, 0.55), (0.62, 0.45, 0.3))
FABRICS: tuple[RGB, ...] = (
    (0.25, 0.35, 0.6), (0.55, 0.2, 0.2), (0.3, 0.5, 0.35), (0.7, 0.65, 0.55), (0.45, 0.45, 0.48),
    (0.8, 0.55, 0.25), (0.5, 0.3, 0.55), (0.2, 0.5, 0.55), (0.85, 0.8, 0.7),
)
PAINTS: tuple[RGB, ...] = ((0.92, 0.92, 0.9), (0.2, 0.2, 0.22), (0.75, 0.8, 0.85), (0.6, 0.65, 0.55), (0.85, 0.8, 0.7))
METALS: tuple[RGB, ...] = ((0.75, 0.76, 0.78), (0.25, 0.25, 0.27), (0.6, 0.55, 0.45))
BRIGHT: tuple[RGB, ...] = (
    (0.85, 0.2, 0.2), (0.2, 0.45, 0.85), (0.95, 0.75, 0.15), (0.2, 0.65, 0.35), (0.9, 0.5, 0.15),
    (0.6, 0.3, 0.7), (0.95, 0.95, 0.92), (0.15, 0.15, 0.18), (0.3, 0.7, 0.75),
)


def jitter(rng: np.random.Generator, color: RGB, amount: float = 0.06) -> RGB:
    """A nearby colour: small random shifts of hue, saturation and value."""
    h, s, v = colorsys.rgb_to_hsv(*color)
    h = (h + rng.uniform(-amount, amount) * 0.5) % 1.0
    s = float(np.clip(s + rng.uniform(-amount, amount), 0, 1))
    v = float(np.clip(v + rng.uniform(-amount, amount), 0.03, 1))
    return tuple(float(c) for c in colorsys.hsv_to_rgb(h, s, v))  # type: ignore[return-value]


def pick(rng: np.random.Generator, colors: tuple[RGB, ...]) -> RGB:
    return jitter(rng, colors[int(rng.integers(len(colors)))])


def wood(rng: np.random.Generator, axis: int = 0) -> Material:
    c = pick(rng, WOODS)
    return Material(c, tuple(x * 0.72 for x in c), Pattern.WOOD, float(rng.uniform(14, 26)), axis)  # type: ignore[arg-type]


def paint(rng: np.random.Generator, colors: tuple[RGB, ...] = PAINTS) -> Material:
    c = pick(rng, colors)
    return Material(c, tuple(x * 0.9 for x in c), Pattern.NOISE, 12.0)  # type: ignore[arg-type]


def metal(rng: np.random.Generator) -> Material:
    return Material(pick(rng, METALS))


def solid(color: RGB) -> Material:
    return Material(color)


def fabric(rng: np.random.Generator, patterned: bool = True,
           colors: tuple[RGB, ...] = FABRICS) -> tuple[Material, tuple[str, ...]]:
    """A fabric material and the depictions its pattern adds (stripes, checkered)."""
    c = pick(rng, colors)
    kinds = ["noise", "stripes", "checker", "noise"] if patterned else ["noise"]
    kind = kinds[int(rng.integers(len(kinds)))]
    if kind == "noise":
        return Material(c, tuple(x * 0.8 for x in c), Pattern.NOISE, float(rng.uniform(25, 45))), ()  # type: ignore[arg-type]
    c2 = pick(rng, BRIGHT)
    if kind == "stripes":
        mat = Material(c, c2, Pattern.STRIPES, float(rng.uniform(5, 12)), int(rng.integers(3)))
    else:
        mat = Material(c, c2, Pattern.CHECKER, float(rng.uniform(5, 10)))
    return mat, PATTERN_DEPICTIONS[kind]
