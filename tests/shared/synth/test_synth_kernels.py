"""The numba kernels of shared.synth.kernels give their numpy references' results bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from shared.synth import groundtruth, kernels, textures  # noqa: E402
from shared.synth.config import preset_config  # noqa: E402
from shared.synth.pipeline import intrinsics  # noqa: E402
from shared.synth.primitives import Material, Part, Pattern, translation  # noqa: E402
from shared.synth.trajectory import build_trajectory  # noqa: E402
from shared.synth.world import build_world  # noqa: E402


@pytest.fixture
def reference(monkeypatch: pytest.MonkeyPatch):
    """Call ``fn(*args)`` with the kernels off (the numpy references)."""

    def call(fn, *args, **kwargs):
        with monkeypatch.context() as m:
            m.setattr(kernels, "ENABLED", False)
            return fn(*args, **kwargs)

    return call


def test_value_noise_matches_numpy(reference):
    rng = np.random.default_rng(0)
    # Negative coordinates, lattice wrap-around (period 64) and exact lattice points.
    p = np.vstack([rng.uniform(-200, 200, (20000, 3)), rng.integers(-70, 70, (500, 3))]).astype(np.float32)
    got = textures.value_noise(p)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, reference(textures.value_noise, p))
    np.testing.assert_array_equal(got, textures.value_noise_numpy(p))


def test_tiles_and_checker_match_numpy(reference):
    rng = np.random.default_rng(1)
    parts = [Part("box", (1.0, 2.0, 0.5), translation(0, 0, 0), Material((0.8, 0.7, 0.6), pattern=kind, scale=sc))
             for kind in (Pattern.TILES, Pattern.CHECKER) for sc in (3.0, 7.5, 12.0)]
    table = textures.MaterialTable.from_parts(parts)
    n = 30000
    part_idx = rng.integers(0, len(parts), n).astype(np.int32)
    local = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    # Points on tile edges and grout borders, where the rounding decides.
    local[:3000] = (np.round(local[:3000] * 12) / 12).astype(np.float32)
    pat = table.pattern.take(part_idx)
    kinds = [Pattern.TILES, Pattern.CHECKER]
    got = np.zeros((n, 3), np.float32)
    textures.apply_patterns(table, part_idx, local, pat, kinds, got)
    want = np.zeros((n, 3), np.float32)
    reference(textures.apply_patterns, table, part_idx, local, pat, kinds, want)
    np.testing.assert_array_equal(got, want)
    assert len(np.unique(got, axis=0)) > 50, "tiles, grout and both checker colours all occur"


def _scene(preset: str, overrides: dict):
    from shared.synth.render import Renderer

    cfg = preset_config(preset, overrides)
    world = build_world(cfg, 2)
    traj = build_trajectory(world, cfg.camera)
    K = intrinsics(cfg)
    return cfg, world, traj, K, Renderer(world, K, cfg.render)


def _assert_same_frame(a, b) -> None:
    for name in ("rgb", "depth", "instances"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.slow
@pytest.mark.parametrize("render", [
    {},
    {"textures": False, "rgb_noise_std": 0.0},
    {"depth_noise_std": 0.01, "depth_max": 3.3, "rgb_noise_std": 7.5, "lamp_strength": 1.3},
])
def test_render_matches_numpy(reference, render):
    cfg, world, traj, K, renderer = _scene("small", {"camera": {"width": 160, "height": 120, "frames": 12}, "render": render})
    for i in range(0, 12, 3):
        # The float colour before rounding to bytes, which hides most one-ulp slips.
        hits = renderer.cast(traj.poses[i])
        hit, obj, color = reference(renderer.shade_numpy, hits)
        k_obj, light, base, shade = renderer.shade_kernels(hits)
        if cfg.render.textures:
            base = np.clip(base * shade[:, None], 0, 1)
        np.testing.assert_array_equal(k_obj, obj)
        np.testing.assert_array_equal(base * (light * np.float32(255.0))[:, None], color)
        got = renderer.render(traj.poses[i], np.random.default_rng([5, i]))
        want = reference(renderer.render_numpy, traj.poses[i], np.random.default_rng([5, i]))
        _assert_same_frame(got, want)
    # A camera outside the house looking past its corner: rays that miss take the other path.
    lo = np.min([o.lo for o in world.objects], axis=0)
    hi = np.max([o.hi for o in world.objects], axis=0)
    pose = np.eye(4)
    # OpenCV axes: z forward along world +x, y down along world -z.
    pose[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pose[:3, 3] = [lo[0] - 3.0, hi[1] - 0.5, 1.2]
    got = renderer.render(pose, np.random.default_rng(9))
    assert 0 < (got.instances >= 0).sum() < got.instances.size, "the view has hits and misses"
    _assert_same_frame(got, reference(renderer.render_numpy, pose, np.random.default_rng(9)))


@pytest.mark.slow
def test_observed_points_match_numpy(reference):
    cfg, world, traj, K, renderer = _scene("small", {"camera": {"width": 160, "height": 120, "frames": 8}})
    cloud = groundtruth.sample_cloud(world, {o.id for o in world.objects}, 0.02, 2)
    reference_cloud = reference(groundtruth.sample_cloud, world, {o.id for o in world.objects}, 0.02, 2)
    np.testing.assert_array_equal(cloud.points, reference_cloud.points)
    np.testing.assert_array_equal(cloud.colors, reference_cloud.colors)
    points = cloud.points
    labels = cloud.labels
    for i in range(0, 8, 2):
        pose = traj.poses[i]
        frame = renderer.render(pose)
        # Extra points on pixel edges and at the depth tolerance: the kernel must hand these
        # back to numpy rather than guess.
        v, u = np.nonzero(frame.depth > 0)
        pick = np.random.default_rng(i).choice(len(u), 300, replace=False)
        u, v, d = u[pick], v[pick], frame.depth[v[pick], u[pick]].astype(np.float64)
        z = np.concatenate([d, d, d + (0.02 + np.float32(0.01) * d.astype(np.float32)).astype(np.float64)])
        x = np.concatenate([u - 0.5, u + 0.25, u + 0.25])
        y = np.concatenate([v + 0.25, v - 0.5, v + 0.25])
        cam = np.stack([(x - K.cx) / K.fx * z, (y - K.cy) / K.fy * z, z], axis=1)
        edge = (cam @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
        pts = np.vstack([points, edge])
        lab = np.concatenate([labels, frame.instances[np.tile(v, 3), np.tile(u, 3)]])
        chunks = groundtruth.point_chunks(pts, lab, len(world.objects))
        shown = np.flatnonzero(np.bincount(frame.instances[frame.instances >= 0], minlength=len(world.objects)))
        seen = np.empty(len(pts), np.int64)
        unsure = np.empty(len(pts), np.int64)
        _, n_unsure = kernels.observed_points(
            pts, chunks.order, chunks.object_chunks, chunks.chunk_start, chunks.lo, chunks.hi, shown, frame.depth,
            pose[:3, :3].copy(), pose[:3, 3].copy(), K.fx, K.fy, K.cx, K.cy, np.float32(groundtruth.SEEN_TOL),
            seen, unsure)
        assert n_unsure > 0, "the edge points reach the numpy fallback"
        got = groundtruth.observed_objects(pts, chunks, shown, frame.depth, K, pose)
        # The reference projects every point of the shown objects, unchunked.
        want = reference(groundtruth.observed_objects, pts, chunks, shown, frame.depth, K, pose)
        assert len(want) > 100
        np.testing.assert_array_equal(np.sort(got), np.sort(want))


def test_point_chunks_cover_each_object_once():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-3, 3, (4000, 3)).astype(np.float32)
    labels = rng.integers(0, 7, 4000).astype(np.int32)
    labels[labels == 5] = 6  # an object without points
    chunks = groundtruth.point_chunks(pts, labels, 8)
    assert sorted(chunks.order.tolist()) == list(range(4000))
    for o in range(8):
        mine = chunks.order[chunks.bounds[o]:chunks.bounds[o + 1]]
        assert sorted(mine.tolist()) == np.flatnonzero(labels == o).tolist()
        for c in range(chunks.object_chunks[o], chunks.object_chunks[o + 1]):
            p = pts[chunks.order[chunks.chunk_start[c]:chunks.chunk_start[c + 1]]]
            np.testing.assert_array_equal(p.min(axis=0), chunks.lo[c])
            np.testing.assert_array_equal(p.max(axis=0), chunks.hi[c])
            assert (np.ptp(p, axis=0) < groundtruth.CHUNK_SIZE).all()
    assert chunks.object_chunks[-1] > 8 * 10, "objects are split into many chunks"


def test_in_box_matches_numpy():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, (5000, 3))
    pts[:200, 0] = 0.25  # on a face of the box: closed bounds keep them
    pts[200:300, 1] = 0.7
    origin, size = pts[:, :2].min(axis=0), 0.1
    nx, ny = (np.floor((pts[:, :2].max(axis=0) - origin) / size).astype(np.int64) + 1).tolist()
    cell_start = np.zeros(nx * ny + 1, np.int64)
    members = np.empty(len(pts), np.int64)
    kernels.grid_points(pts, origin, size, nx, ny, cell_start, members)
    assert sorted(members.tolist()) == list(range(len(pts)))
    out = np.empty(len(pts), np.int64)
    for lo, hi in [([-0.5, -0.2, -0.9], [0.25, 0.7, 0.1]), ([-3, -3, -3], [3, 3, 3]), ([0.2, 0.2, 0.2], [0.21, 0.21, 0.21]),
                   ([1.5, 0, 0], [2, 1, 1])]:
        lo, hi = np.array(lo, float), np.array(hi, float)
        n = kernels.in_box(pts, cell_start, members, origin, size, nx, ny, lo, hi, out)
        want = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))
        np.testing.assert_array_equal(np.sort(out[:n]), want)
