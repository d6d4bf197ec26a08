"""The whole-map surface sample that places and rooms are built from: one point per cell of
everything ever meshed, each with the frame it was meshed from, so a pose correction can move
it (:meth:`SurfaceSample.move`)."""

from __future__ import annotations

from typing import Annotated

import numpy as np

from services.fusion.corrections.poses import Motion
from services.fusion.volume.window import pack_keys


class SurfaceSample:
    """Points kept one per ``cell``-metre cube, the first to arrive in each, in arrival order
    (a batch in cell order)."""

    def __init__(self, cell: float) -> None:
        self.cell = float(cell)
        self._rows: dict[int, int] = {}
        self._points = np.zeros((0, 3), np.float32)
        self._anchors = np.zeros(0, np.int32)

    def __len__(self) -> int:
        return len(self._points)

    @property
    def points(self) -> Annotated[np.ndarray, "(N, 3) float32"]:
        return self._points

    @property
    def anchors(self) -> Annotated[np.ndarray, "(N,) int32 frame index, -1 = unknown"]:
        return self._anchors

    def add(self, points: Annotated[np.ndarray, "(V, 3) float"], anchors: Annotated[np.ndarray, "(V,) int"]) -> None:
        """Keep the points of cells not sampled yet (the first point of each)."""
        if len(points) == 0:
            return
        # in the points' own precision, as the cells were always computed
        codes = pack_keys(np.floor(np.asarray(points) / self.cell).astype(np.int64))
        uniq, first = np.unique(codes, return_index=True)
        rows = self._rows
        new = np.fromiter((c not in rows for c in uniq.tolist()), bool, len(uniq))
        if not new.any():
            return
        take = first[new]
        start = len(self._points)
        rows.update(zip(uniq[new].tolist(), range(start, start + len(take)), strict=True))
        self._points = np.concatenate([self._points, np.asarray(points, np.float32)[take]])
        self._anchors = np.concatenate([self._anchors, np.asarray(anchors, np.int32)[take]])

    def move(self, motion: Motion) -> bool:
        """Every point moved with its anchor frame, cells sampled anew; False if none moved."""
        points, hit = motion.apply(self._points, self._anchors)
        if not hit.any():
            return False
        anchors = self._anchors
        self.clear()
        self.add(points, anchors)
        return True

    def clear(self) -> None:
        self._rows = {}
        self._points = np.zeros((0, 3), np.float32)
        self._anchors = np.zeros(0, np.int32)
