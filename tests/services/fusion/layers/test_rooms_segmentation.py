"""Room segmentation by eroded free space, and stable place/room ids across rebuilds."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.layers.places import extract_places
from services.fusion.layers.rooms import (
    HierarchyBuilder,
    match_by_distance,
    match_by_votes,
    segment_rooms,
)
from shared.config.fusion import GraphConfig


def _wall(p0, p1, step=0.03, height=2.5):
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(int(np.linalg.norm(p1 - p0) / step), 1) + 1
    xy = p0 + np.linspace(0, 1, n)[:, None] * (p1 - p0)
    z = np.arange(0, height + 1e-9, 0.05)
    return np.column_stack([np.repeat(xy, z.size, axis=0), np.tile(z, n)])


def flat(door=(1.6, 2.3), closet=False):
    """Room A [0,4]x[0,4] and room B [4,8]x[0,3] with a door in x = 4; optionally a
    1.4 m x 1.2 m closet off room B at [6.6,8]x[3,4.2] through a 0.6 m opening."""
    walls = [
        ((0, 0), (8, 0)), ((0, 4), (4, 4)), ((0, 0), (0, 4)), ((8, 0), (8, 3)),
        ((4, 3), (4, 4)), ((4, 0), (4, door[0])), ((4, door[1]), (4, 3)),
    ]  # fmt: skip
    floor = np.mgrid[0:8:0.05, 0:4:0.05].reshape(2, -1).T
    inside = (floor[:, 0] <= 4) | (floor[:, 1] <= 3)
    if closet:
        walls += [((4, 3), (7.0, 3)), ((7.6, 3), (8, 3)), ((6.6, 3), (6.6, 4.2)), ((6.6, 4.2), (8, 4.2)), ((8, 3), (8, 4.2))]
        floor = np.mgrid[0:8:0.05, 0:4.2:0.05].reshape(2, -1).T
        inside = (floor[:, 0] <= 4) & (floor[:, 1] <= 4) | (floor[:, 1] <= 3) | (floor[:, 0] >= 6.6)
    else:
        walls.append(((4, 3), (8, 3)))
    g = floor[inside]
    return np.concatenate([*(_wall(a, b) for a, b in walls), np.column_stack([g, np.zeros(len(g))])])


def test_two_rooms_split_at_the_door():
    cfg = GraphConfig()
    layout = extract_places(flat(), cfg=cfg)
    rooms = segment_rooms(layout.freespace, layout.cells, layout.positions, cfg)
    assert len(rooms) == 2
    # Largest first: A (16 m2) then B (12 m2), minus the walls' cells.
    assert rooms.areas_m2[0] > rooms.areas_m2[1] > cfg.min_room_area_m2
    assert rooms.areas_m2[0] == pytest.approx(14.5, abs=1.5)
    x = layout.positions[:, 0]
    assert np.all(rooms.place_room >= 0)
    assert np.all(rooms.place_room[x < 3.9] == 0)
    assert np.all(rooms.place_room[x > 4.2] == 1)
    assert (rooms.place_room == 0).sum() >= 5 and (rooms.place_room == 1).sum() >= 5
    assert rooms.centroids[0][0] < 4 < rooms.centroids[1][0]
    # Every free cell belongs to a room; nothing else does.
    assert np.array_equal(rooms.labels >= 0, layout.freespace.free)


def test_a_wide_opening_makes_one_room():
    layout = extract_places(flat(door=(0.3, 2.7)))
    rooms = segment_rooms(layout.freespace, layout.cells, layout.positions, GraphConfig())
    assert len(rooms) == 1


def test_small_rooms_join_their_neighbour():
    cfg = GraphConfig(min_room_area_m2=2.0)
    layout = extract_places(flat(closet=True), cfg=cfg)
    rooms = segment_rooms(layout.freespace, layout.cells, layout.positions, cfg)
    assert len(rooms) == 2
    fs = layout.freespace
    c = fs.cell_of(np.array([[7.35, 3.65]]))[0]
    assert fs.free[c[0], c[1]]
    assert rooms.labels[c[0], c[1]] == 1  # the closet is part of room B
    # A lower threshold makes the closet its own room.
    small = segment_rooms(fs, layout.cells, layout.positions, GraphConfig(min_room_area_m2=1.0))
    assert len(small) == 3
    assert small.labels[c[0], c[1]] == 2 and 1.0 < small.areas_m2[2] < 2.0


def test_no_free_space_no_rooms():
    layout = extract_places(np.zeros((0, 3)))
    rooms = segment_rooms(layout.freespace, layout.cells, layout.positions, GraphConfig())
    assert len(rooms) == 0 and rooms.place_room.shape == (0,)


def test_matching_helpers():
    prev_ids = np.array([10, 11, 12])
    prev = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)
    new = np.array([[1.05, 0, 0], [0.1, 0, 0], [5, 0, 0], [1.1, 0, 0]], float)
    assert match_by_distance(prev_ids, prev, new, 0.25).tolist() == [11, 10, -1, -1]
    votes = np.array([[0, 7], [0, 7], [0, 8], [1, 7], [1, 8], [1, 8], [2, 8]])
    assert match_by_votes(votes, 3).tolist() == [7, 8, -1]


def test_builder_keeps_ids_and_assigns_rooms():
    builder = HierarchyBuilder(GraphConfig())
    pts = flat()
    h1 = builder.build(pts)
    h2 = builder.build(pts)
    key = [(p.id, p.room, tuple(p.position)) for p in h1.places.nodes]
    assert key == [(p.id, p.room, tuple(p.position)) for p in h2.places.nodes]
    assert [r.id for r in h1.rooms] == [r.id for r in h2.rooms] == [0, 1]
    by_id = {p.id: p for p in h1.places.nodes}
    assert all(a in by_id and b in by_id for a, b in h1.places.edges)
    assert {p.room for p in h1.places.nodes} == {0, 1}

    # Mapping more of the world (a third room) keeps the old ids and adds new ones.
    extra = np.concatenate([_wall((8, 0), (11, 0)), _wall((11, 0), (11, 3)), _wall((8, 3), (11, 3))])
    g = np.mgrid[8:11:0.05, 0:3:0.05].reshape(2, -1).T
    # Open the wall x = 8 with a door at y in [1.0, 1.6].
    keep = ~((np.abs(pts[:, 0] - 8) < 1e-9) & (pts[:, 1] > 1.0) & (pts[:, 1] < 1.6))
    bigger = np.concatenate([pts[keep], extra, np.column_stack([g, np.zeros(len(g))])])
    h3 = builder.build(bigger)
    assert len(h3.rooms) == 3
    old_a = {p.id for p in h1.places.nodes if p.room == 0}
    new_a = {p.id for p in h3.places.nodes if p.room == 0}
    assert len(old_a & new_a) >= 0.8 * len(old_a)
    assert max(p.id for p in h3.places.nodes) > max(by_id)
    assert {r.id for r in h3.rooms} == {0, 1, 2}

    # After a restart the builder continues from the saved layers.
    fresh = HierarchyBuilder(GraphConfig())
    fresh.restore(h3.places.nodes, h3.rooms)
    h4 = fresh.build(bigger)
    assert [(p.id, p.room) for p in h4.places.nodes] == [(p.id, p.room) for p in h3.places.nodes]


def test_locator_maps_points_to_place_ids():
    h = HierarchyBuilder().build(flat())
    ids = h.places.locate(np.array([[1.0, 1.0, 0.5], [6.0, 1.5, 0.5]]))
    by_id = {p.id: p for p in h.places.nodes}
    assert by_id[int(ids[0])].room == 0 and by_id[int(ids[1])].room == 1


def _box(lo, hi, step=0.05):
    """The surface points of a piece of furniture: an axis-aligned box's faces."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    g = [np.arange(a, b + 1e-9, step) for a, b in zip(lo, hi, strict=True)]
    pts = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    on_face = np.isclose(pts, lo).any(axis=1) | np.isclose(pts, hi).any(axis=1)
    return pts[on_face]


def furnished(door_lintel=True):
    """Room A of :func:`flat` with a table and a sofa in the middle of it and a sideboard
    along a wall (all under 1 m), and walls whose doorway has a lintel above 2.1 m."""
    pts = flat()
    if door_lintel:
        lintel = _wall((4, 1.6), (4, 2.3), height=0.4)
        pts = np.concatenate([pts, lintel + np.array([0, 0, 2.15])])
    furniture = [((1.2, 1.2, 0), (2.8, 2.0, 0.75)), ((0.9, 2.6, 0), (3.1, 3.3, 0.9)), ((0.1, 0.1, 0), (2.0, 0.6, 0.9))]
    return np.concatenate([pts, *(_box(lo, hi) for lo, hi in furniture)])


def test_furniture_does_not_split_a_room():
    cfg = GraphConfig()
    layout = extract_places(furnished(), cfg=cfg)
    fs = layout.freespace
    # The eroded free space alone (the method before the wall band) falls apart around the
    # table and the sofa: more than one core in room A.
    from scipy import ndimage

    cores, n = ndimage.label(fs.free & (fs.esdf > cfg.room_erosion_m))
    a = fs.center_of(np.argwhere(cores > 0))[:, 0] < 4
    assert len(np.unique(cores[cores > 0][a])) >= 2
    rooms = segment_rooms(fs, layout.cells, layout.positions, cfg)
    assert len(rooms) == 2
    # Room A keeps the floor under its table: the footprint is the wall-bounded floor.
    table = fs.cell_of(np.array([[2.0, 1.6]]))[0]
    assert not fs.free[table[0], table[1]] and rooms.labels[table[0], table[1]] == 0
    assert rooms.areas_m2[0] == pytest.approx(16.0, abs=1.6)


def test_builder_outlines_places_and_boxes_rooms():
    pts = furnished()
    h = HierarchyBuilder(GraphConfig()).build(pts, active=(np.array([1.0, 1.0, 1.0]), 2.0))
    fs = h.layout.freespace
    for p in sorted(h.places.nodes, key=lambda p: p.id):
        assert p.boundary.shape[0] >= 4 and p.boundary.shape[1] == 2
        # The outline encloses the place's own cell (shoelace area > 0: counter-clockwise).
        x, y = p.boundary[:, 0], p.boundary[:, 1]
        assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0
        assert x.min() <= p.position[0] <= x.max() and y.min() <= p.position[1] <= y.max()
        assert p.active == (np.linalg.norm(p.position - [1.0, 1.0, 1.0]) <= 2.0)
    assert any(p.active for p in h.places.nodes) and not all(p.active for p in h.places.nodes)
    a, b = sorted(h.rooms, key=lambda r: r.bbox_min[0])
    assert a.bbox_min[0] == pytest.approx(0.0, abs=0.15) and a.bbox_max[0] == pytest.approx(4.0, abs=0.15)
    assert a.bbox_min[2] == pytest.approx(fs.floor_z) and a.bbox_max[2] == pytest.approx(2.5, abs=0.05)
    assert b.bbox_max[0] == pytest.approx(8.0, abs=0.15) and a.area_m2 > b.area_m2 > 0
