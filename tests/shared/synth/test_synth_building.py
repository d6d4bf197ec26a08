"""The ``building`` preset: ten or more furnished rooms round a corridor and a walk of at least
2,000 frames through all of them, checked without rendering the walk."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.config.base import ConfigError
from shared.geometry import is_rigid
from shared.synth.config import PRESETS, preset_config
from shared.synth.freespace import free_space
from shared.synth.layout import ROOM_TYPES
from shared.synth.pipeline import rooms_json
from shared.synth.trajectory import build_trajectory
from shared.synth.world import build_world


def inside(rect: tuple[float, float, float, float], xy: np.ndarray) -> np.ndarray:
    x0, y0, x1, y1 = rect
    return (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)


@pytest.fixture(scope="module", params=[0, 1])
def building(request):
    """(config, world, walk) of the building preset for seeds 0 and 1."""
    cfg = preset_config("building")
    world = build_world(cfg, request.param)
    return cfg, world, build_trajectory(world, cfg.camera)


def test_building_is_registered_and_sized_like_demo():
    assert "building" in PRESETS
    cfg, demo = preset_config("building"), preset_config("demo")
    assert cfg.layout.kind == "building" and cfg.layout.rooms >= 10
    assert cfg.camera.frames >= 2000
    assert (cfg.camera.width, cfg.camera.height, cfg.camera.hfov_deg) == (demo.camera.width, demo.camera.height, demo.camera.hfov_deg)


def test_floor_plan_rooms_on_both_sides_of_one_corridor(building):
    cfg, world, _ = building
    layout = world.layout
    furnished = [r for r in layout.rooms if r.furnished]
    assert len(furnished) >= 10
    assert [r.name for r in furnished] == [f"room{i}" for i in range(len(furnished))]
    (corridor,) = [r for r in layout.rooms if r.kind == "corridor"]
    assert {r.kind for r in furnished} == {"living", "bedroom", "office", "dining"}
    for room in furnished:
        doors = layout.doors_of(room.name)
        assert len(doors) == 1 and set(doors[0].rooms) == {room.name, "corridor"}
        # The doorway lies on the wall the room shares with the corridor, within both spans.
        door_x, door_y = doors[0].point()
        assert door_y in (corridor.rect[1], corridor.rect[3]) and door_y in (room.rect[1], room.rect[3])
        half = doors[0].width / 2
        assert max(room.rect[0], corridor.rect[0]) < door_x - half and door_x + half < min(room.rect[2], corridor.rect[2])
    north = [r for r in furnished if r.rect[1] >= corridor.rect[3]]
    south = [r for r in furnished if r.rect[3] <= corridor.rect[1]]
    assert len(north) + len(south) == len(furnished) and abs(len(north) - len(south)) <= 1
    # No two rooms overlap (they may share a wall centre line).
    rects = np.array([r.rect for r in layout.rooms])
    for i in range(len(rects)):
        for j in range(i + 1, len(rects)):
            a, b = rects[i], rects[j]
            assert min(a[2], b[2]) - max(a[0], b[0]) <= 1e-9 or min(a[3], b[3]) - max(a[1], b[1]) <= 1e-9, (i, j)
    body = rooms_json(layout)
    assert [r["type"] for r in body["rooms"]].count("corridor") == 1
    assert all(r["type"] == ROOM_TYPES[r["kind"]] for r in body["rooms"])
    assert not layout.return_to_start


def test_every_room_is_furnished(building):
    _, world, _ = building
    for room in (r for r in world.layout.rooms if r.furnished):
        things = [o for o in world.objects if o.room == room.name and not o.structural]
        standing = [o for o in things if o.mount == "floor"]
        assert len(standing) >= 4 and len(things) >= 10, (room.name, room.kind, len(standing), len(things))
        x0, y0, x1, y1 = room.inner(world.layout.wall_thickness)
        for o in things:
            assert x0 - 1e-6 <= o.lo[0] and o.hi[0] <= x1 + 1e-6 and y0 - 1e-6 <= o.lo[1] and o.hi[1] <= y1 + 1e-6, o.category


def test_walk_tours_every_room_in_order_and_keeps_clear(building):
    cfg, world, traj = building
    cam = cfg.camera
    layout = world.layout
    assert traj.poses.shape == (cam.frames, 4, 4)
    xy = traj.positions[:, :2]
    furnished = [r for r in layout.rooms if r.furnished]
    first_frame = []
    for room in furnished:
        here = inside(room.inner(layout.wall_thickness), xy)
        # A real tour, not a glance through the door: many frames, far into the room.
        assert here.sum() >= 60, (room.name, int(here.sum()))
        depth_in = np.abs(xy[here, 1] - layout.doors_of(room.name)[0].line).max()
        assert depth_in > 0.4 * (room.rect[3] - room.rect[1]), room.name
        first_frame.append(int(np.argmax(here)))
    assert first_frame == sorted(first_frame), "rooms are toured in floor-plan order"
    rooms_or_doors = np.zeros(len(xy), bool)
    for room in layout.rooms:
        rooms_or_doors |= inside(room.inner(layout.wall_thickness), xy)
    for door in layout.doors:
        rooms_or_doors |= inside(door.passage(layout.wall_thickness), xy)
    assert rooms_or_doors.all(), "the camera never stands in a wall"
    assert all(is_rigid(T) for T in traj.poses)
    fs = free_space(world)
    # The grid measures clearance between cell centres: allow one cell of slack.
    assert fs.clearance_at(xy).min() >= cam.clearance - fs.res, "the camera never stands in furniture"
    assert np.degrees(np.abs(np.diff(traj.yaw))).max() <= cam.max_yaw_step_deg + 1e-6
    hops = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)
    assert hops.max() < 3 * np.median(hops) + 1e-3, "frames evenly spaced along the walk"
    assert 0.03 <= traj.length / (cam.frames - 1) <= 0.09, "frames as far apart as demo's to revisit's"
    x0, y0, x1, y1 = furnished[-1].inner(layout.wall_thickness)
    assert x0 < xy[-1, 0] < x1 and y0 < xy[-1, 1] < y1, "the walk ends in the last room, it does not go back"


def test_building_size_is_bounded_and_a_suite_stays_one_row():
    assert len([r for r in build_world(preset_config("building", {"layout": {"rooms": 3}}), 0).layout.rooms if r.furnished]) == 3
    with pytest.raises(ConfigError, match="layout.rooms"):
        preset_config("building", {"layout": {"rooms": 25}})
    with pytest.raises(ConfigError, match="at most 5 rooms"):
        preset_config("demo", {"layout": {"rooms": 6}})


@pytest.mark.slow
def test_building_renders_small(tmp_path):
    from PIL import Image

    from shared.synth import run_synth

    out = tmp_path / "building"
    result = run_synth("building", 0, out, {"camera": {"frames": 4, "width": 64, "height": 48}, "gt": {"point_spacing": 0.05}},
                       progress=False)
    assert result["frames"] == 4 and result["objects"] > 0
    scene = json.loads((out / "gt" / "scene.json").read_text())
    rooms = json.loads((out / "gt" / "rooms.json").read_text())
    assert len(rooms["rooms"]) == len(scene["rooms"]) >= 11
    assert scene["preset"] == "building" and scene["config"]["layout"]["kind"] == "building"
    inst = np.asarray(Image.open(out / "instances" / "instance000000.png"))
    depth = np.asarray(Image.open(out / "results" / "depth000000.png"))
    assert inst.shape == depth.shape == (48, 64) and (depth > 0).mean() > 0.95
    assert Image.open(out / "topdown.png").size[0] > 800
