"""The palette segments are drawn with, the same in the Rerun recording, the PNG renders and
the saved ``.sparkdsg`` (so a segment looks alike in our viewer and in Hydra's tools)."""

from __future__ import annotations

from typing import Annotated

import numpy as np

NONE_COLOR = (160, 160, 160)
"""Grey: a vertex or node of no segment."""


def segment_colors(ids: Annotated[np.ndarray, "(N,) int"]) -> Annotated[np.ndarray, "(N, 3) uint8"]:
    """A stable, distinct colour per id (golden-ratio hues, three saturation/value tiers),
    grey for negative ids. Stable so a segment keeps its colour across graph versions and
    between the recording and the PNG renders."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    valid = ids >= 0
    k = np.where(valid, ids, 0)
    h = np.mod(k * 0.618033988749895 + 0.07, 1.0)
    tier = (k * 7) % 3
    s = np.array([0.85, 0.6, 0.75])[tier]
    v = np.array([0.9, 0.95, 0.7])[tier]
    out = hsv_to_rgb(h, s, v)
    out[~valid] = NONE_COLOR
    return out


def segment_color(i: int) -> tuple[int, int, int]:
    r, g, b = segment_colors(np.array([i]))[0]
    return int(r), int(g), int(b)


def hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> Annotated[np.ndarray, "(N, 3) uint8"]:
    """HSV in [0, 1] to 8-bit RGB, vectorised."""
    i = np.floor(h * 6).astype(np.int64) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    table = np.stack(
        [np.stack(c, axis=-1) for c in ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))]
    )
    rgb = table[i, np.arange(h.size)]
    return np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8).reshape(-1, 3)
