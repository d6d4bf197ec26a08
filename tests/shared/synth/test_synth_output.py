"""A generated ``small`` sequence: layout, geometric exactness, ground truth, determinism."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from shared.geometry import Intrinsics, backproject, transform
from shared.synth import OutputExistsError, SynthConfig, generate, run_synth

pytestmark = pytest.mark.slow


def hashes(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


def load_poses(root: Path) -> np.ndarray:
    rows = [list(map(float, line.split())) for line in (root / "traj.txt").read_text().splitlines()]
    assert all(len(r) == 16 for r in rows)
    return np.array(rows).reshape(-1, 4, 4)


def test_layout_and_result(small_run):
    out, result, seconds = small_run
    assert result["frames"] == 120 and result["out"] == str(out)
    assert seconds < 60, f"small preset took {seconds:.1f} s"
    intr = json.loads((out / "intrinsics.json").read_text())
    assert set(intr) == {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"}
    assert (intr["width"], intr["height"], intr["cx"], intr["cy"], intr["depth_scale"]) == (320, 240, 159.5, 119.5, 6553.5)
    assert intr["fx"] == intr["fy"]
    assert len(load_poses(out)) == 120
    for i in (0, 119):
        rgb = Image.open(out / "results" / f"frame{i:06d}.jpg")
        depth = Image.open(out / "results" / f"depth{i:06d}.png")
        inst = Image.open(out / "instances" / f"instance{i:06d}.png")
        assert rgb.mode == "RGB" and rgb.size == (320, 240)
        assert depth.mode in ("I;16", "I") and depth.size == (320, 240)
        assert np.asarray(depth).dtype in (np.uint16, np.int32)
        assert inst.size == (320, 240)
    assert len(list((out / "results").glob("frame*.jpg"))) == 120
    for name in ("contact_sheet.png", "topdown.png"):
        assert Image.open(out / name).size[0] > 800


def test_depth_backprojects_onto_the_geometry(small_run):
    from shared.o3d import import_open3d
    from shared.synth.render import Renderer
    from shared.synth.world import build_world

    o3d = import_open3d()
    out, _, _ = small_run
    scene = json.loads((out / "gt" / "scene.json").read_text())
    cfg = SynthConfig.model_validate(scene["config"])
    intr = json.loads((out / "intrinsics.json").read_text())
    K = Intrinsics(**{k: v for k, v in intr.items() if k != "depth_scale"})
    world = build_world(cfg, scene["seed"])
    raycast = Renderer(world, K, cfg.render).scene
    poses = load_poses(out)
    medians = []
    for i in range(0, len(poses), 6):
        z = np.asarray(Image.open(out / "results" / f"depth{i:06d}.png")).astype(np.float64) / intr["depth_scale"]
        assert (z > 0).mean() > 0.95, "the rooms are closed: nearly every pixel has a reading"
        pts = transform(poses[i], backproject(K, z)[z > 0])
        dist = raycast.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
        medians.append(float(np.median(dist)))
    assert max(medians) < 0.005


def test_ground_truth_matches_the_frames(small_run):
    out, result, _ = small_run
    gt = out / "gt"
    cats = json.loads((gt / "gt_categories.json").read_text())
    samples = cats["dataset"]["samples"]
    ids = {s["object_id"] for s in samples}
    assert result["objects"] == len(samples)
    things = [s for s in samples if s["name"] not in ("wall", "floor", "ceiling")]
    assert len(things) >= 15
    for s in samples:
        attrs = s["labels"]["image_attributes"]
        assert set(attrs) == {"synonyms", "depictions", "vis_sim", "clutter"}
        assert attrs["synonyms"] and s["name"] in attrs["synonyms"]
        assert all(isinstance(c, str) and int(c) in ids and int(c) != s["object_id"] for c in attrs["clutter"])
    by_id = {s["object_id"]: s for s in samples}
    for s in samples:
        for c in s["labels"]["image_attributes"]["clutter"]:
            assert str(s["object_id"]) in by_id[int(c)]["labels"]["image_attributes"]["clutter"], "clutter is symmetric"
    assert any(s["labels"]["image_attributes"]["clutter"] for s in things), "small objects clutter their supports"

    seen: set[int] = set()
    min_depth = np.inf
    for p in sorted((out / "instances").glob("instance*.png")):
        inst = np.asarray(Image.open(p)).astype(np.int64)
        seen |= {int(v) - 1 for v in np.unique(inst) if v > 0}
        depth = np.asarray(Image.open(out / "results" / p.name.replace("instance", "depth"))).astype(np.float64)
        min_depth = min(min_depth, depth[depth > 0].min() / 6553.5)
    assert seen <= ids, "every object in an instance image is a ground-truth object"
    assert ids <= seen, "every ground-truth object appears in at least one frame"
    assert min_depth > 0.15, "the camera never touches anything"

    points = np.load(gt / "points.npy")
    labels = np.load(gt / "labels.npy")
    colors = np.load(gt / "colors.npy")
    assert points.dtype == np.float32 and points.shape[1] == 3
    assert labels.dtype == np.int32 and colors.dtype == np.uint8
    assert len(points) == len(labels) == len(colors) > 10000
    assert set(np.unique(labels).tolist()) == ids, "every ground-truth object has points"
    ply = (gt / "point_cloud.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian 1.0\n") and f"element vertex {len(points)}\n".encode() in ply

    prompts = (gt / "prompt_list.txt").read_text().splitlines()
    assert prompts == sorted(set(prompts)) and "chair" in prompts
    for s in samples:
        for tier in ("synonyms", "depictions", "vis_sim"):
            assert set(s["labels"]["image_attributes"][tier]) <= set(prompts)
    mapping = json.loads((gt / "gt_categories_query_to_object_mapping_all.json").read_text())
    level0 = mapping["level0"]
    assert "wall" not in level0 and "floor" not in level0
    for query, objs in level0.items():
        assert objs and all(query in by_id[o]["labels"]["image_attributes"]["synonyms"] for o in objs)

    meta = json.loads((gt / "scene.json").read_text())
    assert meta["seed"] == 0 and meta["rooms"] and meta["mesh_bounds"]["min"][2] < 0
    assert {o["id"] for o in meta["objects"] if o["in_gt"]} == ids


def test_same_seed_gives_identical_files_other_seed_differs(small_run, tmp_path):
    out, _, _ = small_run
    again = tmp_path / "again"
    generate("small", 0, again, progress=False)
    assert hashes(again) == hashes(out)
    other = tmp_path / "other"
    run_synth("small", 1, other, {"camera": {"frames": 6}}, progress=False)
    a, b = hashes(out), hashes(other)
    assert a["results/frame000000.jpg"] != b["results/frame000000.jpg"]
    assert a["gt/gt_categories.json"] != b["gt/gt_categories.json"]


def test_refuses_a_non_empty_folder(tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match=re.escape(str(out))):
        generate("small", 0, out, progress=False)
    with pytest.raises(OutputExistsError, match="not a synth output"):
        generate("small", 0, out, overwrite=True, progress=False)
    assert (out / "keep.txt").read_text() == "mine"
    assert [p.name for p in tmp_path.iterdir()] == ["busy"], "no staging folder left behind"


def test_overwrite_replaces_a_previous_output(tmp_path):
    out = tmp_path / "seq"
    tiny = {"camera": {"frames": 3, "width": 64, "height": 48}, "gt": {"point_spacing": 0.05}}
    run_synth("small", 0, out, tiny, progress=False)
    first = hashes(out)
    with pytest.raises(OutputExistsError):
        run_synth("small", 0, out, tiny, progress=False)
    run_synth("small", 2, out, tiny, overwrite=True, progress=False)
    assert hashes(out) != first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]
