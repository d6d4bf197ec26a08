"""A keyframe's masks, each read only inside its bounding box.

A keyframe brings N full-resolution masks (at 1200x680 and 100 masks, 82 MB of bools), and
the correction used to make several whole-image passes per mask: patch-cell coverage for the
prototypes (eq. 2), the pixels per predicted track for the IoUs (eq. 3), the depth points of
its footprint, the painted labels. Most masks cover a small part of the image, so each is
boxed once (:func:`mask_boxes`) and every later pass reads only the box: the same counts,
the same points, in the same order.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np

try:
    import numba
except ImportError:  # numpy does the same over the boxes, slower
    numba = None

Boxes = Annotated[np.ndarray, "(N, 4) int64 y0, y1, x0, x1 (ends exclusive; 0, 0, 0, 0 when empty)"]


def mask_boxes(masks: Annotated[np.ndarray, "(N, H, W) bool"]) -> Boxes:
    """The tight box of each mask: one pass over the rows of all masks, then the columns of
    each mask's rows only."""
    n = masks.shape[0]
    boxes = np.zeros((n, 4), np.int64)
    if n == 0:
        return boxes
    rows = masks.any(axis=2)
    for i in range(n):
        ys = np.flatnonzero(rows[i])
        if len(ys) == 0:
            continue
        y0, y1 = int(ys[0]), int(ys[-1]) + 1
        xs = np.flatnonzero(masks[i, y0:y1].any(axis=0))
        boxes[i] = (y0, y1, int(xs[0]), int(xs[-1]) + 1)
    return boxes


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _cell_counts(masks, boxes, cell_y, cell_x, counts):  # pragma: no cover - compiled
        for n in range(masks.shape[0]):
            y0, y1, x0, x1 = boxes[n, 0], boxes[n, 1], boxes[n, 2], boxes[n, 3]
            for y in range(y0, y1):
                cy = cell_y[y]
                for x in range(x0, x1):
                    if masks[n, y, x]:
                        counts[n, cy, cell_x[x]] += 1

    @numba.njit(cache=True, nogil=True)
    def _slot_counts(slots, masks, boxes, m, inter, area):  # pragma: no cover - compiled
        for n in range(masks.shape[0]):
            y0, y1, x0, x1 = boxes[n, 0], boxes[n, 1], boxes[n, 2], boxes[n, 3]
            total = 0
            for y in range(y0, y1):
                for x in range(x0, x1):
                    if masks[n, y, x]:
                        total += 1
                        s = slots[y, x]
                        if 1 <= s <= m:
                            inter[s - 1, n] += 1
            area[n] = total


def cell_counts(
    masks: Annotated[np.ndarray, "(N, H, W) bool"], boxes: Boxes, h: int, w: int
) -> Annotated[np.ndarray, "(N, h, w) int32"]:
    """Pixels of each mask in each cell of an h x w grid tiling the image as ``floor(y * h /
    H)``, ``floor(x * w / W)``."""
    n, height, width = masks.shape
    cell_y = (np.arange(height, dtype=np.int64) * h) // height
    cell_x = (np.arange(width, dtype=np.int64) * w) // width
    counts = np.zeros((n, h, w), np.int32)
    if numba is not None:
        _cell_counts(masks, boxes, cell_y, cell_x, counts)
        return counts
    for i, (y0, y1, x0, x1) in enumerate(boxes.tolist()):
        ys, xs = np.nonzero(masks[i, y0:y1, x0:x1])
        np.add.at(counts[i], (cell_y[ys + y0], cell_x[xs + x0]), 1)
    return counts


def slot_counts(
    slots: Annotated[np.ndarray, "(H, W) int, 0 = none"], m: int, masks: Annotated[np.ndarray, "(N, H, W) bool"], boxes: Boxes
) -> tuple[Annotated[np.ndarray, "(m, N) int64 pixels of mask j in slot i + 1"], Annotated[np.ndarray, "(N,) int64 pixels"]]:
    """How many pixels of each mask fall in each slot 1..m of a slot image, and each mask's area."""
    n = masks.shape[0]
    inter = np.zeros((m, n), np.int64)
    area = np.zeros(n, np.int64)
    if numba is not None:
        _slot_counts(np.ascontiguousarray(slots, np.int64), masks, boxes, m, inter, area)
        return inter, area
    for j, (y0, y1, x0, x1) in enumerate(boxes.tolist()):
        inside = slots[y0:y1, x0:x1][masks[j, y0:y1, x0:x1]].astype(np.int64)
        area[j] = len(inside)
        inter[:, j] = np.bincount(inside, minlength=m + 1)[1 : m + 1]
    return inter, area


def mask_areas(masks: Annotated[np.ndarray, "(N, H, W) bool"], boxes: Boxes) -> Annotated[np.ndarray, "(N,) int64"]:
    """Pixels of each mask, counted inside its box."""
    return np.array([int(np.count_nonzero(masks[i, y0:y1, x0:x1])) for i, (y0, y1, x0, x1) in enumerate(boxes.tolist())], np.int64)
