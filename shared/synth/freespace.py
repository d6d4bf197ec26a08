"""A 2D grid of the floor: where the camera may stand, how far each cell is from walls and
furniture, and shortest paths that keep away from both."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from shared.synth.world import World

XY = Annotated[np.ndarray, "(N, 2) float metres"]

PREFERRED_CLEARANCE = 0.9
"""Paths pay extra for passing closer than this to an obstacle (m)."""


@dataclass
class FreeSpace:
    origin: tuple[float, float]
    res: float
    interior: Annotated[np.ndarray, "(NX, NY) bool: inside a room or a doorway"]
    clearance: Annotated[np.ndarray, "(NX, NY) float: distance to walls or furniture (m)"]
    wall_clearance: Annotated[np.ndarray, "(NX, NY) float: distance to walls only (m)"]

    def index(self, xy: XY) -> tuple[np.ndarray, np.ndarray]:
        xy = np.atleast_2d(xy)
        i = np.clip(np.floor((xy[:, 0] - self.origin[0]) / self.res).astype(int), 0, self.interior.shape[0] - 1)
        j = np.clip(np.floor((xy[:, 1] - self.origin[1]) / self.res).astype(int), 0, self.interior.shape[1] - 1)
        return i, j

    def centers(self, i: np.ndarray, j: np.ndarray) -> XY:
        return np.stack([self.origin[0] + (i + 0.5) * self.res, self.origin[1] + (j + 0.5) * self.res], axis=1)

    def clearance_at(self, xy: XY) -> Annotated[np.ndarray, "(N,) float"]:
        return self.clearance[self.index(xy)]

    def wall_clearance_at(self, xy: XY) -> Annotated[np.ndarray, "(N,) float"]:
        return self.wall_clearance[self.index(xy)]


def _fill(mask: np.ndarray, origin: tuple[float, float], res: float, rect: tuple[float, float, float, float], value: bool) -> None:
    x0, y0, x1, y1 = rect
    i0 = int(np.ceil((x0 - origin[0]) / res - 0.5))
    i1 = int(np.floor((x1 - origin[0]) / res - 0.5))
    j0 = int(np.ceil((y0 - origin[1]) / res - 0.5))
    j1 = int(np.floor((y1 - origin[1]) / res - 0.5))
    mask[max(i0, 0):max(i1 + 1, 0), max(j0, 0):max(j1 + 1, 0)] = value


def free_space(world: World, res: float = 0.05) -> FreeSpace:
    """Rasterise rooms, doorways and floor-standing furniture."""
    layout = world.layout
    bx0, by0, bx1, by1 = layout.bounds()
    origin = (bx0 - 0.5, by0 - 0.5)
    shape = (int(np.ceil((bx1 - bx0 + 1.0) / res)), int(np.ceil((by1 - by0 + 1.0) / res)))
    interior = np.zeros(shape, bool)
    for room in layout.rooms:
        _fill(interior, origin, res, room.inner(layout.wall_thickness), True)
    for door in layout.doors:
        _fill(interior, origin, res, door.passage(layout.wall_thickness), True)
    walls_only = interior.copy()
    free = interior.copy()
    for o in world.objects:
        if o.mount == "floor":
            _fill(free, origin, res, (o.lo[0], o.lo[1], o.hi[0], o.hi[1]), False)
    # Distances are measured between cell centres; half a cell is the worst-case error.
    clearance = ndimage.distance_transform_edt(free) * res - res / 2
    wall_clearance = ndimage.distance_transform_edt(walls_only) * res - res / 2
    return FreeSpace(origin, res, interior, np.maximum(clearance, 0), np.maximum(wall_clearance, 0))


class PathPlanner:
    """Shortest paths on the cells at least ``min_clearance`` from any obstacle."""

    def __init__(self, fs: FreeSpace, min_clearance: float):
        self.fs = fs
        ok = fs.clearance >= min_clearance
        nx, ny = ok.shape
        self.node = -np.ones(ok.shape, np.int64)
        # Only the largest walkable region counts: pockets between furniture are unreachable.
        labels, n = ndimage.label(ok, structure=np.ones((3, 3)))
        if n > 1:
            ok = labels == 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
        self.ok = ok
        ii, jj = np.nonzero(ok)
        self.node[ii, jj] = np.arange(len(ii))
        self.cells = np.stack([ii, jj], axis=1)
        penalty = 1.0 + 3.0 * np.clip((PREFERRED_CLEARANCE - fs.clearance) / PREFERRED_CLEARANCE, 0, 1)
        rows, cols, weights = [], [], []
        for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
            a_i, a_j = ii, jj
            b_i, b_j = ii + di, jj + dj
            valid = (b_i >= 0) & (b_i < nx) & (b_j >= 0) & (b_j < ny)
            a_i, a_j, b_i, b_j = a_i[valid], a_j[valid], b_i[valid], b_j[valid]
            keep = ok[b_i, b_j]
            a_i, a_j, b_i, b_j = a_i[keep], a_j[keep], b_i[keep], b_j[keep]
            step = fs.res * (np.sqrt(2.0) if di and dj else 1.0)
            w = step * 0.5 * (penalty[a_i, a_j] + penalty[b_i, b_j])
            rows.append(self.node[a_i, a_j])
            cols.append(self.node[b_i, b_j])
            weights.append(w)
        r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
        n = len(ii)
        self.graph = csr_matrix((np.concatenate([w, w]), (np.concatenate([r, c]), np.concatenate([c, r]))), shape=(n, n))

    def snap(self, target: tuple[float, float], within: tuple[float, float, float, float] | None = None) -> tuple[float, float] | None:
        """The walkable cell nearest ``target`` (inside ``within`` if given), preferring open space."""
        xy = self.fs.centers(self.cells[:, 0], self.cells[:, 1])
        mask = np.ones(len(xy), bool)
        if within is not None:
            x0, y0, x1, y1 = within
            mask = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
        if not mask.any():
            return None
        clear = self.fs.clearance[self.cells[:, 0], self.cells[:, 1]]
        cost = np.hypot(xy[:, 0] - target[0], xy[:, 1] - target[1]) - 0.6 * np.minimum(clear, PREFERRED_CLEARANCE)
        cost[~mask] = np.inf
        k = int(np.argmin(cost))
        return float(xy[k, 0]), float(xy[k, 1])

    def path(self, a: tuple[float, float], b: tuple[float, float]) -> XY | None:
        """Cell centres from ``a`` to ``b`` (both must be walkable), or None if unreachable."""
        ia, ja = self.fs.index(np.array([a]))
        ib, jb = self.fs.index(np.array([b]))
        na, nb = int(self.node[ia[0], ja[0]]), int(self.node[ib[0], jb[0]])
        if na < 0 or nb < 0:
            return None
        if na == nb:
            return np.array([a, b], float)
        dist, pred = dijkstra(self.graph, indices=na, return_predecessors=True)
        if not np.isfinite(dist[nb]):
            return None
        seq = [nb]
        while seq[-1] != na:
            seq.append(int(pred[seq[-1]]))
        cells = self.cells[np.array(seq[::-1])]
        return self.fs.centers(cells[:, 0], cells[:, 1])
