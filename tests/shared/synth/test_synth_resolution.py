"""``trackgraph synth --resolution WxH``: any preset at another image size, the same world and
walk, the preset's horizontal field of view with square pixels, ground truth consistent."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from shared.config.base import ConfigError
from shared.geometry import Intrinsics, backproject, project, transform
from shared.synth.config import PRESETS, parse_resolution, preset_config
from shared.synth.pipeline import intrinsics
from shared.synth.trajectory import build_trajectory
from shared.synth.world import build_world
from tests.shared.synth.conftest import shrink_synth

TINY = {"camera": {"frames": 3}, "gt": {"point_spacing": 0.05}}
"""Three frames; the image size comes from the preset or ``resolution``."""


def load_poses(root: Path) -> np.ndarray:
    return np.loadtxt(root / "traj.txt").reshape(-1, 4, 4)


def load_frame(root: Path, i: int, depth_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(depth in metres, object id or -1) of frame ``i``."""
    depth = np.asarray(Image.open(root / "results" / f"depth{i:06d}.png")).astype(np.float64) / depth_scale
    inst = np.asarray(Image.open(root / "instances" / f"instance{i:06d}.png")).astype(np.int64) - 1
    return depth, inst


def load_intrinsics(root: Path) -> Intrinsics:
    intr = json.loads((root / "intrinsics.json").read_text())
    return Intrinsics(**{k: v for k, v in intr.items() if k != "depth_scale"})


# ----------------------------------------------------------------------------- the flag's text


@pytest.mark.parametrize("text,expected", [("1200x680", (1200, 680)), ("32X32", (32, 32)), ("4096x4096", (4096, 4096)),
                                           ("0640x0480", (640, 480))])
def test_parse_resolution(text, expected):
    assert parse_resolution(text) == expected


@pytest.mark.parametrize("text", ["", "1200", "1200x", "x680", "1200x680x3", "1200*680", "1200 x 680", "-64x48", "64x-48",
                                  "1200.0x680", "31x480", "640x31", "4097x480", "640x100000", "axb", "0x0"])
def test_parse_resolution_refuses(text):
    with pytest.raises(ValueError, match=r"expected WxH, width and height in pixels from 32 to 4096"):
        parse_resolution(text)


def test_preset_config_resolution_sets_the_image_size_and_nothing_else():
    for preset in PRESETS:
        plain = preset_config(preset).model_dump()
        sized = preset_config(preset, resolution=(1200, 680)).model_dump()
        assert (sized["camera"]["width"], sized["camera"]["height"]) == (1200, 680)
        sized["camera"]["width"], sized["camera"]["height"] = plain["camera"]["width"], plain["camera"]["height"]
        assert sized == plain, preset
    same = preset_config("small", {"camera": {"width": 96, "frames": 5}}, resolution=(96, 54))
    assert (same.camera.width, same.camera.height, same.camera.frames) == (96, 54, 5)
    with pytest.raises(ConfigError, match=r"camera\.width 100 disagrees with resolution 96x54"):
        preset_config("small", {"camera": {"width": 100}}, resolution=(96, 54))
    for bad in ((16, 16), (5000, 480), (640.0, 480), (True, 480)):
        with pytest.raises(ConfigError, match="resolution"):
            preset_config("small", resolution=bad)


# --------------------------------------------------------------- world, walk and intrinsics


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_same_world_and_walk_at_any_resolution(preset):
    base = preset_config(preset)
    wide = preset_config(preset, resolution=(1200, 680))
    a, b = build_world(base, 2), build_world(wide, 2)
    assert [(o.id, o.category, o.room, tuple(o.lo), tuple(o.hi)) for o in a.objects] == \
           [(o.id, o.category, o.room, tuple(o.lo), tuple(o.hi)) for o in b.objects]
    assert np.array_equal(build_trajectory(a, base.camera).poses, build_trajectory(b, wide.camera).poses)


@pytest.mark.parametrize("size", [(640, 480), (1280, 960), (96, 72), (48, 36)])
def test_same_aspect_scales_the_intrinsics_like_a_camera(size):
    base = intrinsics(preset_config("small"))
    K = intrinsics(preset_config("small", resolution=size))
    expected = base.scaled(*size)
    for name in ("fx", "fy", "cx", "cy"):
        assert math.isclose(getattr(K, name), getattr(expected, name), rel_tol=1e-12, abs_tol=1e-9), name
    assert (K.width, K.height) == size
    # Any point in view lands at the same fraction of the image (pixel centres at integers).
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-2, 2, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(0.3, 8, 200)])
    (uv0, _), (uv1, _) = project(base, pts), project(K, pts)
    np.testing.assert_allclose((uv1 + 0.5) / size, (uv0 + 0.5) / (base.width, base.height), rtol=0, atol=1e-12)


def test_other_aspect_keeps_horizontal_field_and_square_pixels():
    cfg = preset_config("small")
    K = intrinsics(preset_config("small", resolution=(1200, 680)))
    assert K.fx == K.fy, "square pixels"
    assert (K.cx, K.cy) == (599.5, 339.5), "principal point at the centre"
    assert math.isclose(2 * math.degrees(math.atan(K.width / 2 / K.fx)), cfg.camera.hfov_deg, rel_tol=1e-12)
    # 4:3 to about 16:9 at the same horizontal field: the vertical field narrows.
    base = intrinsics(cfg)
    vfov = 2 * math.degrees(math.atan(K.height / 2 / K.fy))
    assert vfov < 2 * math.degrees(math.atan(base.height / 2 / base.fy)) - 10


# ----------------------------------------------------------------------- rendered sequences


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, tuple[Path, dict]]:
    """``small`` seed 0, three frames: at the preset's 320x240, at 128x96 (same aspect), at
    96x54 (16:9) and at 320x240 asked for explicitly."""
    from shared.synth import run_synth

    root = tmp_path_factory.mktemp("resolution")
    out = {}
    for name, size in (("preset", None), ("same_aspect", (128, 96)), ("wide", (96, 54)), ("explicit", (320, 240))):
        out[name] = (root / name, run_synth("small", 0, root / name, TINY, progress=False, resolution=size))
    return out


def hashes(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_poses_byte_identical_and_intrinsics_written(runs):
    preset_dir, preset_result = runs["preset"]
    assert "resolution" not in preset_result
    for name in ("same_aspect", "wide"):
        root, result = runs[name]
        assert (root / "traj.txt").read_bytes() == (preset_dir / "traj.txt").read_bytes(), name
        K = load_intrinsics(root)
        assert [K.width, K.height] == result["resolution"]
        cfg = preset_config("small", TINY, resolution=tuple(result["resolution"]))
        assert K == intrinsics(cfg)
        assert json.loads((root / "gt" / "scene.json").read_text())["config"] == cfg.model_dump(mode="json")
        for i in range(3):
            depth, inst = load_frame(root, i, 6553.5)
            assert depth.shape == inst.shape == (K.height, K.width)


@pytest.mark.slow
def test_the_preset_size_asked_for_explicitly_changes_no_byte(runs):
    explicit_dir, explicit = runs["explicit"]
    preset_dir, _ = runs["preset"]
    assert explicit["resolution"] == [320, 240]
    assert hashes(explicit_dir) == hashes(preset_dir)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["same_aspect", "wide"])
def test_depth_and_instances_agree_with_the_preset_size(runs, name):
    """A pixel of the preset-size frame, back-projected with its depth and projected into the
    frame at the other size, finds the same depth and the same object there."""
    preset_dir, _ = runs["preset"]
    root, _ = runs[name]
    K0, K1 = load_intrinsics(preset_dir), load_intrinsics(root)
    for i in range(3):
        d0, i0 = load_frame(preset_dir, i, 6553.5)
        d1, i1 = load_frame(root, i, 6553.5)
        pts = backproject(K0, d0)[d0 > 0]
        ids = i0[d0 > 0]
        uv, z = project(K1, pts)  # same pose: camera frame points carry over
        u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        ok = (u >= 0) & (u < K1.width) & (v >= 0) & (v < K1.height)
        if name == "same_aspect":
            assert ok.all(), "same field of view both ways"
        else:
            assert 0.4 < ok.mean() < 0.9, "the wide frame shows the middle band of the 4:3 one"
        u, v, z, ids = u[ok], v[ok], z[ok], ids[ok]
        other = d1[v, u]
        close = np.abs(other - z) < 0.02 + 0.02 * z
        assert close.mean() > 0.9, (i, close.mean())
        assert (i1[v, u][close] == ids[close]).mean() > 0.97


@pytest.mark.slow
@pytest.mark.parametrize("name", ["same_aspect", "wide"])
def test_ground_truth_matches_the_geometry_at_the_new_size(runs, name):
    """Depth lands on the surfaces of the world and each pixel's object is the surface it hits."""
    from shared.o3d import import_open3d
    from shared.synth.render import Renderer

    o3d = import_open3d()
    root, result = runs[name]
    K = load_intrinsics(root)
    cfg = preset_config("small", TINY, resolution=tuple(result["resolution"]))
    world = build_world(cfg, 0)
    renderer = Renderer(world, K, cfg.render)
    poses = load_poses(root)
    seen: set[int] = set()
    for i in range(3):
        depth, inst = load_frame(root, i, 6553.5)
        valid = depth > 0
        assert valid.mean() > 0.95
        pts = transform(poses[i], backproject(K, depth)[valid]).astype(np.float32)
        closest = renderer.scene.compute_closest_points(o3d.core.Tensor(pts))
        dist = np.linalg.norm(closest["points"].numpy() - pts, axis=1)
        assert np.median(dist) < 0.005
        owner = renderer.geom_obj[closest["geometry_ids"].numpy().astype(np.int64)]
        assert (owner == inst[valid]).mean() > 0.97
        seen |= set(np.unique(inst[valid]).tolist())
    gt = json.loads((root / "gt" / "gt_categories.json").read_text())
    assert {s["object_id"] for s in gt["dataset"]["samples"]} == seen
    assert set(np.unique(np.load(root / "gt" / "labels.npy")).tolist()) == seen


# ------------------------------------------------------------------------------- the CLI


@pytest.fixture
def three_frames(monkeypatch):
    """``trackgraph synth`` renders three frames of its preset (resolution passed through)."""
    shrink_synth(monkeypatch, TINY)


@pytest.mark.slow
def test_cli_resolution_json(tmp_path, capsys, three_frames):
    from services.cli import main

    out = tmp_path / "wide"
    assert main(["synth", "--preset", "small", "--seed", "0", "--out", str(out), "--resolution", "96x54", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert {"frames", "objects", "out"} <= set(result) and result["resolution"] == [96, 54]
    K = load_intrinsics(out)
    assert (K.width, K.height) == (96, 54) and K.fx == K.fy
    assert Image.open(out / "results" / "frame000000.jpg").size == (96, 54)

    plain = tmp_path / "plain"
    assert main(["synth", "--preset", "small", "--seed", "0", "--out", str(plain), "--json"]) == 0
    assert "resolution" not in json.loads(capsys.readouterr().out)
    assert (plain / "traj.txt").read_bytes() == (out / "traj.txt").read_bytes()

    text = tmp_path / "text"
    assert main(["synth", "--preset", "small", "--seed", "0", "--out", str(text), "--resolution", "64x48"]) == 0
    assert "resolution: 64x48" in capsys.readouterr().out


@pytest.mark.parametrize("value", ["1200", "0x680", "1200x680x2", "-640x480", "9000x680", "wide"])
def test_cli_refuses_a_bad_resolution(tmp_path, capsys, three_frames, value):
    from services.cli import main

    out = tmp_path / "seq"
    assert main(["synth", "--out", str(out), f"--resolution={value}", "--json"]) != 0
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "--resolution" in err[0] and "WxH" in err[0] and repr(value) in err[0], err
    assert not out.exists()
