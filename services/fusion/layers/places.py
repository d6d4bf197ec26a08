"""Sparse free-space places: Hydra's places layer, built in 2.5D from the mapped surfaces.

Deviation from the paper, which keeps Hydra's places (docs/method.md, F5): Hydra builds them
as a generalised Voronoi diagram of the 3D ESDF of free space; this is a documented 2.5D
equivalent on a gravity-aligned grid, with no separate ESDF to maintain. The method, all
vectorised numpy/scipy:

1. **Floor height**: the lowest *dense* horizontal layer of the surface points. A z histogram
   in ``floor_bin_m`` bins; the floor is the median z of the lowest bin holding at least
   ``floor_min_fraction`` of the fullest bin, so sparse outliers below the floor are ignored.
2. **2D grid** at ``resolution_m``, cells indexed globally (``floor(xy / resolution)``) so
   binning and cell centres (and thus place positions) stay put when the map grows. A cell is *occupied*
   when a surface point lies in it between ``obstacle_min_m`` and ``obstacle_max_m`` above
   the floor (the band the robot's body sweeps; the ceiling and floor clutter are not
   obstacles); a one-cell closing seals pinholes between sparse vertices. A cell is
   *observed floor* when a point lies within ``floor_band_m`` of the floor. Cells the camera
   passed through are known free.
3. **Free space**: non-occupied cells inside the observed floor (closed over holes up to
   ``floor_fill_m``) or on the trajectory, kept only in the connected components that contain
   observed floor or trajectory. Without floor points the whole bounding box supports free
   space. Components reaching the grid border (the outside) are always dropped. Unobserved
   cells count as obstacles: a place never sits in unknown space.
4. **ESDF**: Euclidean distance transform of the free mask (between cell centres). A place's
   radius is that distance less half a cell diagonal, the farthest an obstacle point can sit
   from its cell's centre, so the radius never overstates the clearance.
5. **GVD**: the transform's feature map gives each free cell its nearest obstacle cell; a cell
   is on the generalised Voronoi diagram when a neighbour's nearest obstacle lies at least
   ``gvd_min_separation_m`` from its own (the two are closest to different walls). GVD cells
   with radius below ``min_clearance_m`` are dropped: too tight for the robot, and they are
   the short spurs into room corners.
6. **Sparsification**: greedy non-maximum suppression over GVD cells in order of decreasing
   clearance with radius ``GraphConfig.place_spacing_m``; every GVD cell ends up within the
   spacing of a place, and places prefer the middle of open space. A free component with
   enough clearance but no GVD cell (a round room) gets its widest cell as a place.
7. **Edges**: every free cell goes to its geodesically nearest place (multi-source Dijkstra on
   the 4-connected free grid). Two places are joined when their regions touch, which means a
   collision-free path links them inside those two regions.

The layer is 2.5D: one floor, places at ``place_height_m`` above it, in a world frame whose
z axis points up (gravity-aligned). A multi-storey map needs one builder per storey, and a
map whose floor is barely seen should pass ``floor_z`` explicitly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from shared.config.fusion import GraphConfig

log = logging.getLogger(__name__)

_HALF_DIAGONAL = float(np.sqrt(0.5))

_CROSS = ndimage.generate_binary_structure(2, 1)
"""4-connectivity: a diagonal gap between two wall cells is not a passage."""


@dataclass(frozen=True)
class FreeSpaceParams:
    """Geometry of the free-space grid; the defaults suit a ground robot or a handheld
    camera indoors."""

    resolution_m: float = 0.1
    """Edge of a 2D grid cell."""
    floor_bin_m: float = 0.05
    """Height bin of the floor histogram."""
    floor_min_fraction: float = 0.2
    """A height bin is a floor candidate when it holds this share of the fullest bin."""
    floor_band_m: float = 0.1
    """Points within this of the floor height are floor."""
    obstacle_min_m: float = 0.2
    """Points lower than this above the floor are clutter the robot passes over."""
    obstacle_max_m: float = 1.8
    """Points higher than this above the floor (ceiling, lamps) do not block."""
    wall_min_m: float = 1.4
    """Bottom of the wall band: surfaces this high above the floor are walls (or tall
    cabinets standing against them), not furniture. Tables, beds, sofas and chairs end below
    it; on the synthetic scenes everything taller than 1.3 m but lamps and shelves hangs on
    a wall."""
    wall_max_m: float = 1.95
    """Top of the wall band, kept under the top of a doorway (2.0-2.1 m in most buildings)
    so that a door is a gap in the band, while the lintel above it is not seen."""
    place_height_m: float = 1.0
    """Height of the place nodes above the floor."""
    min_clearance_m: float = 0.2
    """Places need at least this radius."""
    gvd_min_separation_m: float = 0.35
    """Nearest obstacles of neighbouring cells this far apart put the cells on the GVD."""
    floor_fill_m: float = 0.3
    """Holes in the observed floor up to about this size are filled."""
    margin_cells: int = 3
    """Empty cells around the mapped extent."""
    max_cells: int = 16_000_000
    """Upper bound on the grid size; the resolution is coarsened past it."""


@dataclass
class FreeSpaceMap:
    """A 2D free-space grid. Axis 0 is world x, axis 1 world y."""

    origin_cell: Annotated[np.ndarray, "(2,) int64 global index of cell (0, 0)"]
    """Cells are indexed globally as floor(xy / resolution), so binning and cell centres do
    not depend on where the grid starts."""
    resolution: float
    floor_z: float
    place_z: float
    free: Annotated[np.ndarray, "(H, W) bool"]
    occupied: Annotated[np.ndarray, "(H, W) bool"]
    esdf: Annotated[np.ndarray, "(H, W) float32 metres, centre-to-centre distance to non-free"]
    feature: Annotated[np.ndarray, "(2, H, W) int32 nearest non-free cell of each cell"]
    wall: Annotated[np.ndarray, "(H, W) bool"] | None = None
    """Cells with a surface in the wall band (``wall_min_m`` to ``wall_max_m``)."""
    interior: Annotated[np.ndarray, "(H, W) bool"] | None = None
    """The floor inside the walls, furniture footprints included: what rooms divide. None
    (use ``free``) when no wall was seen."""

    @property
    def shape(self) -> tuple[int, int]:
        return self.free.shape  # type: ignore[return-value]

    @property
    def origin(self) -> Annotated[np.ndarray, "(2,) float64 world xy of the corner of cell (0, 0)"]:
        return self.origin_cell * self.resolution

    def cell_of(self, xy: Annotated[np.ndarray, "(N, 2+) float world"]) -> Annotated[np.ndarray, "(N, 2) int64, may lie outside"]:
        return _global_cells(np.asarray(xy, np.float64), self.resolution) - self.origin_cell

    def center_of(self, cells: Annotated[np.ndarray, "(N, 2) int"]) -> Annotated[np.ndarray, "(N, 2) float64 world xy"]:
        return (np.asarray(cells, np.int64) + self.origin_cell + 0.5) * self.resolution

    def clip(self, cells: Annotated[np.ndarray, "(N, 2) int"]) -> Annotated[np.ndarray, "(N, 2) int64"]:
        h, w = self.shape
        return np.stack([np.clip(cells[:, 0], 0, h - 1), np.clip(cells[:, 1], 0, w - 1)], axis=1)

    def radius_at(self, cells: Annotated[np.ndarray, "(N, 2) int"]) -> Annotated[np.ndarray, "(N,) float64 metres"]:
        """Clearance of free cells: ESDF less half a cell diagonal (module docstring, 4)."""
        d = self.esdf[cells[:, 0], cells[:, 1]].astype(np.float64)
        return np.maximum(d - _HALF_DIAGONAL * self.resolution, 0.0)


@dataclass
class PlaceLayout:
    """Places of one rebuild, indexed 0..P-1 (ids are given by the hierarchy builder)."""

    freespace: FreeSpaceMap
    cells: Annotated[np.ndarray, "(P, 2) int64 grid cell of each place"]
    positions: Annotated[np.ndarray, "(P, 3) float64 world metres"]
    radii: Annotated[np.ndarray, "(P,) float64 metres to the nearest obstacle"]
    edges: Annotated[np.ndarray, "(E, 2) int64 place indices, first < second, unique"]
    owner: Annotated[np.ndarray, "(H, W) int32 geodesically nearest place, -1 outside free space"]
    nearest: Annotated[np.ndarray, "(H, W) int32 place owning the nearest owned cell, -1 if none"]

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def place_index_of(self, points: Annotated[np.ndarray, "(N, 3) float world"]) -> Annotated[np.ndarray, "(N,) int64 place index, -1 if none"]:
        """The place whose free-space region is nearest to each point. Going through the
        grid rather than straight-line distance keeps an object on one side of a wall
        attached to a place on that side."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if len(self) == 0 or pts.shape[0] == 0:
            return np.full(pts.shape[0], -1, np.int64)
        c = self.freespace.clip(self.freespace.cell_of(pts))
        return self.nearest[c[:, 0], c[:, 1]].astype(np.int64)


# ---------------------------------------------------------------- free space


def estimate_floor_height(
    z: Annotated[np.ndarray, "(N,) float heights"], params: FreeSpaceParams | None = None
) -> float | None:
    """Median height of the lowest dense horizontal layer, or None without points."""
    p = params or FreeSpaceParams()
    z = np.asarray(z, np.float64).ravel()
    z = z[np.isfinite(z)]
    if z.size == 0:
        return None
    lo = np.floor(z.min() / p.floor_bin_m)
    bins = (np.floor(z / p.floor_bin_m) - lo).astype(np.int64)
    counts = np.bincount(bins)
    first = int(np.flatnonzero(counts >= p.floor_min_fraction * counts.max())[0])
    # A floor lying on a bin edge splits over two bins: take the median of a window of
    # one bin either side of the dense bin's centre, which its sparse neighbours cannot bias.
    centre = (lo + first + 0.5) * p.floor_bin_m
    return float(np.median(z[np.abs(z - centre) <= p.floor_bin_m]))


def _global_cells(xy: np.ndarray, res: float) -> np.ndarray:
    return np.floor(xy[:, :2] / res).astype(np.int64)


def _disk(radius_cells: int) -> np.ndarray:
    r = max(int(radius_cells), 0)
    ii, jj = np.mgrid[-r : r + 1, -r : r + 1]
    return (ii * ii + jj * jj) <= r * r


def _mark(shape: tuple[int, int], cells: np.ndarray) -> np.ndarray:
    grid = np.zeros(shape, bool)
    if cells.size:
        inside = (cells[:, 0] >= 0) & (cells[:, 0] < shape[0]) & (cells[:, 1] >= 0) & (cells[:, 1] < shape[1])
        grid[cells[inside, 0], cells[inside, 1]] = True
    return grid


def build_free_space(
    points: Annotated[np.ndarray, "(N, 3) float surface points, world metres"],
    trajectory: Annotated[np.ndarray, "(M, 3) float camera positions"] | None = None,
    params: FreeSpaceParams | None = None,
    floor_z: float | None = None,
) -> FreeSpaceMap:
    """The 2D free-space grid with its ESDF (steps 1-4 of the module docstring)."""
    p = params or FreeSpaceParams()
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    traj = np.zeros((0, 3)) if trajectory is None else np.asarray(trajectory, np.float64).reshape(-1, 3)
    traj = traj[np.isfinite(traj).all(axis=1)]

    if floor_z is None:
        floor_z = estimate_floor_height(pts[:, 2], p)
    if floor_z is None:
        floor_z = float(traj[:, 2].min()) - p.place_height_m if traj.size else 0.0

    res = p.resolution_m
    extent = np.concatenate([pts[:, :2], traj[:, :2]]) if (pts.size or traj.size) else np.zeros((1, 2))
    lo, hi = extent.min(axis=0), extent.max(axis=0)
    cells_needed = np.prod((hi - lo) / res + 2 * p.margin_cells + 1)
    if cells_needed > p.max_cells:
        res = res * float(np.sqrt(cells_needed / p.max_cells)) * 1.01
        log.warning("free-space grid would have %.0f cells; coarsening to %.3f m", cells_needed, res)
    origin_cell = _global_cells(lo[None], res)[0] - p.margin_cells
    shape = tuple(_global_cells(hi[None], res)[0] - origin_cell + 1 + p.margin_cells)

    def cells(xy: np.ndarray) -> np.ndarray:
        return _global_cells(xy, res) - origin_cell

    h = pts[:, 2] - floor_z
    occupied = _mark(shape, cells(pts[(h >= p.obstacle_min_m) & (h <= p.obstacle_max_m)]))
    occupied = ndimage.binary_closing(occupied, structure=np.ones((3, 3), bool)) | occupied
    # The foot of a wall is at floor height too; only floor outside obstacles is floor.
    floor_seen = _mark(shape, cells(pts[np.abs(h) <= p.floor_band_m])) & ~occupied
    on_traj = _mark(shape, cells(traj))

    if floor_seen.any():
        fill = _disk(round(p.floor_fill_m / res / 2))
        support = ndimage.binary_closing(floor_seen, structure=fill) | floor_seen | on_traj
    else:
        support = np.ones(shape, bool)
    candidates = support & ~occupied
    labels, n = ndimage.label(candidates, structure=_CROSS)
    seeds = floor_seen | on_traj
    keep = np.unique(labels[seeds & candidates]) if seeds.any() else np.arange(1, n + 1)
    # What reaches the grid border is unbounded: the outside, seen past the walls' ends.
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = np.setdiff1d(keep[keep > 0], border)
    free = np.isin(labels, keep)

    # Rooms are bounded by walls, not by furniture: the floor under a table or bed belongs to
    # its room. The wall band sees walls and not furniture; a doorway is a gap in it.
    wall = _mark(shape, cells(pts[(h >= p.wall_min_m) & (h <= p.wall_max_m)]))
    wall = ndimage.binary_closing(wall, structure=np.ones((3, 3), bool)) | wall
    interior = None
    if wall.any():
        inside = (support | occupied | free) & ~wall
        labels, _ = ndimage.label(inside, structure=_CROSS)
        keep_in = np.unique(labels[free])
        border_in = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        keep_in = np.setdiff1d(keep_in[keep_in > 0], border_in)
        interior = np.isin(labels, keep_in) | free
        # Unseen patches enclosed by the room (under a table, behind a chair) are its floor;
        # an enclosed patch with a wall in it is a pillar or a wall island and stays out.
        holes, nh = ndimage.label(ndimage.binary_fill_holes(interior) & ~interior, structure=_CROSS)
        if nh:
            walled = np.zeros(nh + 1, bool)
            walled[np.unique(holes[wall & (holes > 0)])] = True
            interior |= (holes > 0) & ~walled[holes]

    edt, feature = ndimage.distance_transform_edt(free, return_indices=True)
    return FreeSpaceMap(
        origin_cell=origin_cell.astype(np.int64),
        resolution=float(res),
        floor_z=float(floor_z),
        place_z=float(floor_z + p.place_height_m),
        free=free,
        occupied=occupied,
        esdf=(edt * res).astype(np.float32),
        feature=feature.astype(np.int32),
        wall=wall,
        interior=interior,
    )


# ---------------------------------------------------------------- skeleton and places


def _shifted(h: int, w: int, di: int, dj: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Slices pairing each cell (a) with its neighbour at (+di, +dj) (b); di >= 0."""
    rows_a, rows_b = slice(0, h - di), slice(di, h)
    if dj >= 0:
        cols_a, cols_b = slice(0, w - dj), slice(dj, w)
    else:
        cols_a, cols_b = slice(-dj, w), slice(0, w + dj)
    return (rows_a, cols_a), (rows_b, cols_b)


def gvd_mask(fs: FreeSpaceMap, params: FreeSpaceParams | None = None) -> Annotated[np.ndarray, "(H, W) bool"]:
    """Free cells on the generalised Voronoi diagram with at least the minimum clearance."""
    p = params or FreeSpaceParams()
    free, feat = fs.free, fs.feature.astype(np.int64)
    min_sep2 = max(p.gvd_min_separation_m / fs.resolution, 2.5) ** 2
    gvd = np.zeros_like(free)
    h, w = free.shape
    for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
        a, b = _shifted(h, w, di, dj)
        sep2 = (feat[0][a] - feat[0][b]) ** 2 + (feat[1][a] - feat[1][b]) ** 2
        hit = free[a] & free[b] & (sep2 >= min_sep2)
        gvd[a] |= hit
        gvd[b] |= hit
    clearance = fs.esdf - _HALF_DIAGONAL * fs.resolution
    return gvd & (clearance >= p.min_clearance_m)


def grid_graph(free: Annotated[np.ndarray, "(H, W) bool"]) -> tuple[sparse.csr_matrix, np.ndarray]:
    """The 4-connected graph of free cells: adjacency over compact indices, and the flat
    grid index of each node."""
    h, w = free.shape
    flat = np.flatnonzero(free.ravel())
    compact = np.full(h * w, -1, np.int64)
    compact[flat] = np.arange(flat.size)
    grid = compact.reshape(h, w)
    rows, cols = [], []
    for a, b in ((grid[:-1, :], grid[1:, :]), (grid[:, :-1], grid[:, 1:])):
        m = (a >= 0) & (b >= 0)
        rows.append(a[m])
        cols.append(b[m])
    r, c = np.concatenate(rows), np.concatenate(cols)
    adj = sparse.csr_matrix((np.ones(r.size, np.float32), (r, c)), shape=(flat.size, flat.size))
    return adj, flat


def geodesic_owner(
    free: Annotated[np.ndarray, "(H, W) bool"],
    seed_cells: Annotated[np.ndarray, "(S, 2) int free cells"],
) -> Annotated[np.ndarray, "(H, W) int32 index of the geodesically nearest seed, -1 unreachable"]:
    """Multi-source breadth-first assignment of free cells to seeds (ties go to whichever
    seed Dijkstra's queue reaches first, deterministic for a given input)."""
    h, w = free.shape
    owner = np.full((h, w), -1, np.int32)
    seed_cells = np.asarray(seed_cells, np.int64).reshape(-1, 2)
    if seed_cells.shape[0] == 0 or not free.any():
        return owner
    adj, flat = grid_graph(free)
    compact = np.full(h * w, -1, np.int64)
    compact[flat] = np.arange(flat.size)
    seed_nodes = compact[seed_cells[:, 0] * w + seed_cells[:, 1]]
    if np.any(seed_nodes < 0):
        raise ValueError("every seed must lie in free space")
    _, _, sources = csgraph.dijkstra(
        adj, directed=False, indices=seed_nodes, unweighted=True, min_only=True, return_predecessors=True
    )
    seed_of_node = np.full(flat.size, -1, np.int64)
    seed_of_node[seed_nodes] = np.arange(seed_nodes.size)
    reached = sources >= 0
    vals = np.full(flat.size, -1, np.int64)
    vals[reached] = seed_of_node[sources[reached]]
    owner.ravel()[flat] = vals
    return owner


def touching_pairs(labels: Annotated[np.ndarray, "(H, W) int, -1 = none"]) -> Annotated[np.ndarray, "(E, 2) int64 unique, first < second"]:
    """Label pairs that share a cell side."""
    out = []
    for a, b in ((labels[:-1, :], labels[1:, :]), (labels[:, :-1], labels[:, 1:])):
        m = (a >= 0) & (b >= 0) & (a != b)
        out.append(np.stack([a[m], b[m]], axis=1))
    pairs = np.concatenate(out).astype(np.int64) if out else np.zeros((0, 2), np.int64)
    if pairs.size == 0:
        return np.zeros((0, 2), np.int64)
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _suppress(cells: np.ndarray, score: np.ndarray, radius_cells: float) -> np.ndarray:
    """Greedy non-maximum suppression; returns the kept rows in pick order."""
    if cells.shape[0] == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((cells[:, 1], cells[:, 0], -score))
    cells = cells[order]
    neighbours = cKDTree(cells).query_ball_point(cells, r=radius_cells)
    taken = np.zeros(cells.shape[0], bool)
    keep = []
    for i in range(cells.shape[0]):
        if taken[i]:
            continue
        keep.append(i)
        taken[neighbours[i]] = True
    return order[np.asarray(keep, np.int64)]


def _line_of_sight(fs: FreeSpaceMap, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether the straight segment between cells a[k] and b[k] stays in free space."""
    if a.shape[0] == 0:
        return np.zeros(0, bool)
    steps = int(np.ceil(np.abs(b - a).max() * 2)) + 1
    t = np.linspace(0.0, 1.0, steps)
    pts = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :].astype(np.float64)
    cells = np.floor(pts + 0.5).astype(np.int64)
    return fs.free[cells[..., 0], cells[..., 1]].all(axis=1)


def _traversable_edges(fs: FreeSpaceMap, cells: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Touching regions joined in a straight line are edges; where no straight edge joins two
    parts that touch, the shortest bent one is kept (Kruskal on the rest), so the place
    graph has the connectivity of the free space without long detours across a room."""
    if pairs.shape[0] == 0:
        return pairs
    los = _line_of_sight(fs, cells[pairs[:, 0]], cells[pairs[:, 1]])
    length = np.linalg.norm(cells[pairs[:, 0]] - cells[pairs[:, 1]], axis=1)
    parent = np.arange(cells.shape[0])

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in pairs[los]:
        parent[root(i)] = root(j)
    keep = los.copy()
    for k in np.flatnonzero(~los)[np.argsort(length[~los], kind="stable")]:
        ri, rj = root(pairs[k, 0]), root(pairs[k, 1])
        if ri != rj:
            parent[ri] = rj
            keep[k] = True
    return pairs[keep]


def extract_places(
    points: Annotated[np.ndarray, "(N, 3) float surface points, world metres"],
    trajectory: Annotated[np.ndarray, "(M, 3) float camera positions"] | None = None,
    cfg: GraphConfig | None = None,
    params: FreeSpaceParams | None = None,
    floor_z: float | None = None,
) -> PlaceLayout:
    """Places and their edges from the mapped surfaces (the whole module docstring)."""
    cfg = cfg or GraphConfig()
    p = params or FreeSpaceParams()
    fs = build_free_space(points, trajectory, p, floor_z)
    res = fs.resolution

    gvd = gvd_mask(fs, p)
    cand = np.argwhere(gvd)
    # Components the GVD misses (round rooms, or too small for two walls to be far enough
    # apart) still get a place at their widest cell if the robot fits there.
    labels, n = ndimage.label(fs.free, structure=_CROSS)
    if n:
        has_gvd = np.zeros(n + 1, bool)
        has_gvd[np.unique(labels[gvd])] = True
        idx = ndimage.maximum_position(fs.esdf, labels, index=np.arange(1, n + 1))
        extra = np.array([c for k, c in enumerate(idx, start=1) if not has_gvd[k]], np.int64).reshape(-1, 2)
        if extra.size:
            ok = fs.radius_at(extra) >= p.min_clearance_m
            cand = np.concatenate([cand, extra[ok]])
    score = fs.esdf[cand[:, 0], cand[:, 1]] if cand.size else np.zeros(0)
    picked = cand[_suppress(cand, score, cfg.place_spacing_m / res)] if cand.size else np.zeros((0, 2), np.int64)
    # Row-major order makes place indices independent of the suppression order.
    picked = picked[np.lexsort((picked[:, 1], picked[:, 0]))] if picked.size else picked

    owner = geodesic_owner(fs.free, picked)
    edges = _traversable_edges(fs, picked, touching_pairs(owner))
    if picked.shape[0]:
        _, idx = ndimage.distance_transform_edt(owner < 0, return_indices=True)
        nearest = owner[idx[0], idx[1]]
    else:
        nearest = np.full(fs.shape, -1, np.int32)
    xy = fs.center_of(picked)
    positions = np.column_stack([xy, np.full(xy.shape[0], fs.place_z)])
    log.debug("places: %d GVD cells -> %d places, %d edges", int(gvd.sum()), picked.shape[0], edges.shape[0])
    return PlaceLayout(
        freespace=fs,
        cells=picked.astype(np.int64),
        positions=positions,
        radii=fs.radius_at(picked),
        edges=edges,
        owner=owner,
        nearest=nearest.astype(np.int32),
    )


# ---------------------------------------------------------------- outlines


def region_outline(
    mask: Annotated[np.ndarray, "(h, w) bool one 4-connected region"],
) -> Annotated[np.ndarray, "(B, 2) int64 cell-corner coordinates, counter-clockwise"]:
    """The outer outline of a region of cells, as the corners where it turns.

    Cell (i, j) is the square [i, i+1] x [j, j+1] (axis 0 is x). Each side of a region cell
    facing a non-region cell is a directed edge that keeps the region on its left; the edges
    chain into loops. The outer loop runs counter-clockwise and a hole's clockwise, so the
    outline is the loop of the largest signed area."""
    m = np.asarray(mask, bool)
    if not m.any():
        return np.zeros((0, 2), np.int64)
    p = np.pad(m, 1)
    i, j = np.nonzero(m)
    pi, pj = i + 1, j + 1
    # Per side: which cells expose it, and the start and end corner offsets.
    sides = (
        (~p[pi, pj - 1], 0, 0, 1, 0),  # bottom (y = j), walked +x
        (~p[pi + 1, pj], 1, 0, 1, 1),  # right (x = i + 1), walked +y
        (~p[pi, pj + 1], 1, 1, 0, 1),  # top, walked -x
        (~p[pi - 1, pj], 0, 1, 0, 0),  # left, walked -y
    )
    si = np.concatenate([i[e] + a for e, a, _, _, _ in sides])
    sj = np.concatenate([j[e] + b for e, _, b, _, _ in sides])
    ei = np.concatenate([i[e] + c for e, _, _, c, _ in sides])
    ej = np.concatenate([j[e] + d for e, _, _, _, d in sides])
    nxt: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for a, b, c, d in zip(si.tolist(), sj.tolist(), ei.tolist(), ej.tolist(), strict=True):
        nxt.setdefault((a, b), []).append((c, d))
    best, best_area = np.zeros((0, 2), np.int64), -np.inf
    while nxt:
        start = min(nxt)
        loop, v = [start], start
        while True:
            outs = nxt[v]
            w = outs.pop()
            if not outs:
                del nxt[v]
            if w == start or w not in nxt:
                break
            loop.append(w)
            v = w
        pts = np.asarray(loop, np.int64)
        area = 0.5 * float(np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1]))
        if area > best_area:
            best, best_area = pts, area
    # Keep the corners only: drop vertices on a straight run.
    prev, after = np.roll(best, 1, axis=0), np.roll(best, -1, axis=0)
    cross = (best[:, 0] - prev[:, 0]) * (after[:, 1] - best[:, 1]) - (best[:, 1] - prev[:, 1]) * (after[:, 0] - best[:, 0])
    return best[cross != 0]


def place_outlines(
    fs: FreeSpaceMap,
    owner: Annotated[np.ndarray, "(H, W) int32 place index per cell, -1 none"],
    n: int,
    cache: dict[tuple[tuple[int, int], bytes], np.ndarray] | None = None,
) -> list[Annotated[np.ndarray, "(B, 2) float64 world xy"]]:
    """The outline of each place's free-space region (its geodesic cells), in world xy.

    ``cache`` (kept by the caller between rebuilds) maps a region's mask to its outline:
    away from the robot the regions stay as they were, and tracing them again made a rebuild
    grow with the building. It is left holding this call's regions only."""
    out = [np.zeros((0, 2)) for _ in range(n)]
    seen: dict[tuple[tuple[int, int], bytes], np.ndarray] = {}
    for k, box in enumerate(ndimage.find_objects(owner + 1, max_label=n)):
        if box is None:
            continue
        mask = owner[box] == k
        key = (mask.shape, np.packbits(mask).tobytes())
        corners = cache.get(key) if cache is not None else None
        if corners is None:
            corners = region_outline(mask)
        seen[key] = corners
        offset = np.array([box[0].start, box[1].start], np.int64)
        out[k] = (corners + offset + fs.origin_cell).astype(np.float64) * fs.resolution
    if cache is not None:
        cache.clear()
        cache.update(seen)
    return out
