"""Free space, GVD places and their edges on a synthetic two-room flat."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.fusion.layers.places import (
    FreeSpaceParams,
    build_free_space,
    estimate_floor_height,
    extract_places,
)
from shared.config.fusion import GraphConfig


def _wall(p0, p1, step=0.03, height=2.5):
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(int(np.linalg.norm(p1 - p0) / step), 1) + 1
    xy = p0 + np.linspace(0, 1, n)[:, None] * (p1 - p0)
    z = np.arange(0, height + 1e-9, 0.05)
    return np.column_stack([np.repeat(xy, z.size, axis=0), np.tile(z, n)])


def two_rooms(door=(1.6, 2.3), floor=True, floor_z=0.0):
    """Room A [0,4]x[0,4] and room B [4,8]x[0,3], joined by a door in the wall x = 4."""
    walls = [
        ((0, 0), (8, 0)), ((0, 4), (4, 4)), ((4, 3), (8, 3)), ((0, 0), (0, 4)), ((8, 0), (8, 3)),
        ((4, 3), (4, 4)), ((4, 0), (4, door[0])), ((4, door[1]), (4, 3)),
    ]  # fmt: skip
    pts = [_wall(a, b) for a, b in walls]
    if floor:
        g = np.mgrid[0:8:0.05, 0:4:0.05].reshape(2, -1).T
        g = g[(g[:, 0] <= 4) | (g[:, 1] <= 3)]
        pts.append(np.column_stack([g, np.zeros(len(g))]))
    out = np.concatenate(pts)
    out[:, 2] += floor_z
    return out


def _wall_xy():
    pts = two_rooms(floor=False)
    return pts[pts[:, 2] == 1.0][:, :2]


def _connected(n, edges):
    parent = list(range(n))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for a, b in edges:
        parent[root(a)] = root(b)
    return len({root(i) for i in range(n)}) == 1


def test_floor_height_is_the_lowest_dense_layer():
    rng = np.random.default_rng(0)
    floor = rng.normal(0.8, 0.005, 5000)
    ceiling = rng.normal(3.3, 0.005, 5000)
    outliers = rng.uniform(-1.0, 0.7, 40)
    walls = rng.uniform(0.8, 3.3, 3000)
    z = np.concatenate([floor, ceiling, outliers, walls])
    assert estimate_floor_height(z) == pytest.approx(0.8, abs=0.01)
    assert estimate_floor_height(np.zeros(0)) is None


@pytest.mark.parametrize("floor_z", [0.0, 1.37])
def test_places_lie_in_free_space_and_are_connected(floor_z):
    cfg = GraphConfig()
    params = FreeSpaceParams()
    layout = extract_places(two_rooms(floor_z=floor_z), cfg=cfg, params=params)
    fs = layout.freespace
    assert fs.floor_z == pytest.approx(floor_z, abs=0.03)
    assert len(layout) > 10
    # Radii are clearances: positive, at least the minimum, and no wall point inside.
    assert np.all(layout.radii >= params.min_clearance_m)
    d, _ = cKDTree(_wall_xy()).query(layout.positions[:, :2])
    assert np.all(d >= layout.radii - 1e-6)
    assert np.all(d <= layout.radii + 1.5 * fs.resolution)
    assert np.all(fs.free[layout.cells[:, 0], layout.cells[:, 1]])
    assert np.allclose(layout.positions[:, 2], floor_z + params.place_height_m, atol=0.03)
    # Spaced out, inside the flat, in both rooms, one connected graph through the door.
    nn, _ = cKDTree(layout.positions).query(layout.positions, k=2)
    assert nn[:, 1].min() >= cfg.place_spacing_m - 1e-9
    x, y = layout.positions[:, 0], layout.positions[:, 1]
    assert np.all((x > 0) & (x < 8) & (y > 0) & (y < 4))
    assert (x < 4).any() and (x > 4).any()
    assert layout.edges.shape[1] == 2 and np.all(layout.edges[:, 0] < layout.edges[:, 1])
    assert _connected(len(layout), layout.edges)
    crossing = [(a, b) for a, b in layout.edges if (x[a] < 4) != (x[b] < 4)]
    assert crossing and all(1.5 < y[a] < 2.4 and 1.5 < y[b] < 2.4 for a, b in crossing)


def test_edges_never_cross_a_wall():
    layout = extract_places(two_rooms())
    fs = layout.freespace
    a, b = layout.cells[layout.edges[:, 0]], layout.cells[layout.edges[:, 1]]
    # Both regions of an edge touch, so some free path joins them; a straight edge that is
    # kept must not pass through an occupied cell.
    t = np.linspace(0, 1, 50)
    for p, q in zip(a, b, strict=True):
        cells = np.floor(p + t[:, None] * (q - p) + 0.5).astype(int)
        assert fs.free[cells[:, 0], cells[:, 1]].mean() > 0.5


def test_walls_only_with_trajectory_or_enclosure():
    walls = two_rooms(floor=False)
    traj = np.array([[1.0, 1.0, 1.4], [2.5, 2.0, 1.4], [4.0, 2.0, 1.4], [6.0, 1.5, 1.4]])
    with_traj = extract_places(walls, traj)
    enclosed = extract_places(walls)
    for layout in (with_traj, enclosed):
        assert len(layout) > 10
        assert _connected(len(layout), layout.edges)
        # The outside of the flat is not free space.
        fs = layout.freespace
        assert not fs.free[0].any() and not fs.free[-1].any()


def test_open_ended_map_keeps_only_what_the_camera_saw():
    # A single wall with floor observed on one side only: free space is the observed floor.
    wall = _wall((0, 0), (5, 0))
    g = np.mgrid[0:5:0.05, 0.05:3:0.05].reshape(2, -1).T
    pts = np.concatenate([wall, np.column_stack([g, np.zeros(len(g))])])
    layout = extract_places(pts)
    assert len(layout) > 0
    assert np.all(layout.positions[:, 1] > 0)


def test_empty_and_tiny_inputs():
    empty = extract_places(np.zeros((0, 3)))
    assert len(empty) == 0 and empty.edges.shape == (0, 2)
    assert np.all(empty.place_index_of(np.zeros((3, 3))) == -1)
    traj_only = extract_places(np.zeros((0, 3)), np.array([[0.0, 0.0, 1.5]]))
    assert len(traj_only) == 0  # one free cell is too tight for a place


def test_locator_keeps_wall_objects_on_their_side():
    layout = extract_places(two_rooms())
    x = layout.positions[:, 0]
    # A picture on each face of the shared wall (x = 4), off the wall's own grid cell.
    idx = layout.place_index_of(np.array([[4.15, 0.7, 1.5], [3.9, 0.7, 1.5]]))
    assert x[idx[0]] > 4 and x[idx[1]] < 4


def test_grid_is_anchored_so_places_do_not_shift_when_the_map_grows():
    base = two_rooms()
    more = np.concatenate([base, np.array([[-3.33, -2.71, 0.0]])])  # a far outlier floor point
    a, b = extract_places(base), extract_places(more)
    pa = {tuple(np.round(p, 6)) for p in a.positions}
    pb = {tuple(np.round(p, 6)) for p in b.positions}
    assert pa == pb


def test_free_space_treats_unobserved_as_blocked():
    fs = build_free_space(two_rooms())
    # Under the walls nothing is free, and the outside beyond the walls is not free.
    c = fs.cell_of(np.array([[4.0, 0.5], [9.0, 1.0], [2.0, 2.0]]))
    c = fs.clip(c)
    assert not fs.free[c[0, 0], c[0, 1]]
    assert not fs.free[c[1, 0], c[1, 1]]
    assert fs.free[c[2, 0], c[2, 1]]


def test_region_outline_is_the_outer_counter_clockwise_corner_loop():
    from services.fusion.layers.places import region_outline

    square = np.zeros((4, 4), bool)
    square[1:3, 1:3] = True
    assert region_outline(square).tolist() == [[1, 1], [3, 1], [3, 3], [1, 3]]
    ell = np.zeros((5, 5), bool)
    ell[0:3, 0] = ell[0, 0:3] = True
    assert region_outline(ell).tolist() == [[0, 0], [3, 0], [3, 1], [1, 1], [1, 3], [0, 3]]
    # A region around a hole: the outline is the outer loop, not the hole's (clockwise) one.
    ring = np.ones((5, 5), bool)
    ring[2, 2] = False
    assert region_outline(ring).tolist() == [[0, 0], [5, 0], [5, 5], [0, 5]]
    assert region_outline(np.zeros((3, 3), bool)).shape == (0, 2)


def test_outlines_from_the_cache_equal_traced_ones_as_the_map_grows(monkeypatch):
    """A rebuild reuses the outline of every place region it traced before; the outlines equal
    those traced afresh, and the cache keeps only the last rebuild's regions."""
    import services.fusion.layers.places as places

    small = two_rooms()
    floor = np.column_stack([np.mgrid[8:11:0.05, 0:3:0.05].reshape(2, -1).T, np.zeros(60 * 60)])
    grown = np.concatenate([small, _wall((8, 0), (11, 0)), _wall((8, 3), (11, 3)), _wall((11, 0), (11, 3)), floor])
    traced, calls = places.region_outline, []
    cache: dict = {}
    traces = []
    for pts in (small, grown, grown):
        lay = extract_places(pts)
        fresh = places.place_outlines(lay.freespace, lay.owner, len(lay))
        calls.clear()
        monkeypatch.setattr(places, "region_outline", lambda m: calls.append(1) or traced(m))
        cached = places.place_outlines(lay.freespace, lay.owner, len(lay), cache)
        monkeypatch.setattr(places, "region_outline", traced)
        assert len(cached) == len(fresh) > 2
        for a, b in zip(fresh, cached, strict=True):
            np.testing.assert_array_equal(a, b)
        assert len(cache) <= len(lay)
        traces.append((len(calls), len(lay)))
    (first, n1), (second, n2), (third, n3) = traces
    assert first == n1 and 0 < second < n2 and third == 0, traces
