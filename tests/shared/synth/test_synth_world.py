"""World layout, furniture and the camera walk, without writing a sequence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.geometry import is_rigid
from shared.synth.config import preset_config
from shared.synth.freespace import free_space
from shared.synth.furniture import FURNITURE
from shared.synth.items import ITEMS
from shared.synth.primitives import Part, contains, local_mesh
from shared.synth.trajectory import build_trajectory
from shared.synth.world import build_world


@pytest.mark.parametrize("part", [Part("box", (0.4, 0.2, 1.0)), Part("frustum", (0.3, 0.1, 0.5)), Part("ellipsoid", (0.2, 0.3, 0.1))])
def test_primitive_meshes_are_closed_outward_and_match_inside_test(part):
    v, f = local_mesh(part)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() > 0, "faces wound outward"
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all(), "every edge shared by two faces (closed mesh)"
    assert contains(part, np.zeros((1, 3)))[0]
    assert not contains(part, v * 1.01).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_builders_give_normalized_templates(seed):
    rng = np.random.default_rng(seed)
    for name, build in {**FURNITURE, **ITEMS}.items():
        t = build(rng).normalized()
        lo, hi = t.bounds()
        assert abs(lo[2]) < 1e-9, name
        assert np.allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-9), name
        assert (hi - lo > 0.005).all(), name


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_small_world_is_furnished_and_consistent(seed):
    cfg = preset_config("small")
    world = build_world(cfg, seed)
    things = [o for o in world.objects if not o.structural]
    assert len(things) >= 15
    assert [o.id for o in world.objects] == list(range(len(world.objects)))
    cats = {o.category for o in world.objects}
    assert {"wall", "floor", "ceiling"} <= cats
    by_id = {o.id: o for o in world.objects}
    items = [o for o in things if o.mount == "item"]
    assert items, "small objects stand on furniture"
    for o in items:
        sup = by_id[o.support]
        # Standing on the support: within its footprint and above its base.
        assert sup.lo[0] - 1e-6 <= o.lo[0] and o.hi[0] <= sup.hi[0] + 1e-6
        assert sup.lo[1] - 1e-6 <= o.lo[1] and o.hi[1] <= sup.hi[1] + 1e-6
        assert sup.lo[2] < o.lo[2] <= sup.hi[2] + 0.01
    floor = [o for o in things if o.mount == "floor"]
    for i, a in enumerate(floor):
        for b in floor[i + 1:]:
            overlap = np.minimum(a.hi, b.hi) - np.maximum(a.lo, b.lo)
            assert (overlap <= 0).any(), f"{a.category} {a.id} and {b.category} {b.id} intersect"


def test_same_seed_same_world_other_seed_other_world():
    cfg = preset_config("small")
    a, b, c = build_world(cfg, 5), build_world(cfg, 5), build_world(cfg, 6)
    sig = [(o.category, tuple(np.round(o.lo, 9))) for o in a.objects]
    assert sig == [(o.category, tuple(np.round(o.lo, 9))) for o in b.objects]
    assert sig != [(o.category, tuple(np.round(o.lo, 9))) for o in c.objects]


@pytest.mark.parametrize("preset,seed", [("small", 0), ("small", 3), ("demo", 0), ("demo", 2), ("revisit", 1)])
def test_walk_keeps_clear_turns_smoothly_and_poses_are_rigid(preset, seed):
    cfg = preset_config(preset)
    world = build_world(cfg, seed)
    traj = build_trajectory(world, cfg.camera)
    assert traj.poses.shape == (cfg.camera.frames, 4, 4)
    assert all(is_rigid(T) for T in traj.poses)
    fs = free_space(world)
    # The grid measures clearance between cell centres: allow one cell of slack.
    assert fs.clearance_at(traj.positions[:, :2]).min() >= cfg.camera.clearance - fs.res
    steps = np.degrees(np.abs(np.diff(traj.yaw)))
    assert steps.max() <= cfg.camera.max_yaw_step_deg + 1e-6
    z = traj.positions[:, 2]
    assert np.all(np.abs(z - cfg.camera.eye_height) <= cfg.camera.bob + 1e-9)
    # OpenCV axes: image y (down) points down in the z-up world.
    assert (traj.poses[:, 2, 1] < 0).all()
    hops = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)
    assert hops.max() < 3 * np.median(hops) + 1e-3, "frames evenly spaced along the walk"


def test_revisit_goes_far_and_comes_back_to_the_same_view():
    from shared.geometry import Intrinsics
    from shared.synth.render import Renderer

    cfg = preset_config("revisit", {"camera": {"width": 96, "height": 72}})
    world = build_world(cfg, 0)
    traj = build_trajectory(world, cfg.camera)
    first = world.layout.rooms[0]
    dist = np.linalg.norm(traj.positions[:, :2] - np.array(first.center()), axis=1)
    assert dist.max() > 8.0
    x0, y0, x1, y1 = first.inner(world.layout.wall_thickness)
    end = traj.positions[-1]
    assert x0 < end[0] < x1 and y0 < end[1] < y1, "the walk ends back in the first room"
    f = cfg.focal()
    K = Intrinsics(fx=f, fy=f, cx=(cfg.camera.width - 1) / 2, cy=(cfg.camera.height - 1) / 2,
                   width=cfg.camera.width, height=cfg.camera.height)
    renderer = Renderer(world, K, cfg.render)

    def seen(indices) -> set[int]:
        ids: set[int] = set()
        for i in indices:
            gid = renderer.cast(traj.poses[i])["geometry_ids"]
            ids |= {int(renderer.geom_obj[g]) for g in np.unique(gid) if g != np.iinfo(np.uint32).max}
        return {i for i in ids if not world.objects[i].structural}

    n = len(traj.poses)
    start, finish = seen(range(0, 15)), seen(range(n - 15, n))
    assert start and len(start & finish) >= 3, (start, finish)


def test_look_direction_changes_smoothly():
    cfg = preset_config("small")
    traj = build_trajectory(build_world(cfg, 1), cfg.camera)
    fwd = traj.poses[:, :3, 2]
    cos = np.einsum("ij,ij->i", fwd[1:], fwd[:-1])
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < cfg.camera.max_yaw_step_deg + 2.0
    assert math.isclose(float(np.linalg.norm(fwd, axis=1).max()), 1.0, abs_tol=1e-9)
