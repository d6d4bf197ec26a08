"""``generate``: world, walk, frames, ground truth and pictures, written into one folder."""

from __future__ import annotations

import logging
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from shared.geometry import Intrinsics
from shared.synth import writer
from shared.synth.config import PRESETS, SynthConfig, preset_config
from shared.synth.layout import ROOM_TYPES, Layout
from shared.synth.vocabulary import prompt_list

log = logging.getLogger(__name__)


def intrinsics(cfg: SynthConfig) -> Intrinsics:
    """fx = fy from the horizontal field of view; principal point at the image centre.

    At another resolution (``run_synth(..., resolution=(W, H))``, ``trackgraph synth
    --resolution WxH``) the camera keeps the preset's horizontal field of view and square
    pixels, as a sensor read out in another mode does: at the preset's aspect ratio this is
    :meth:`Intrinsics.scaled` exactly (every point lands at the same fraction of the image);
    at another aspect ratio the vertical field follows (1200x680 from a 4:3 preset shows less
    above and below), rather than fx and fy scaling apart into non-square pixels."""
    c = cfg.camera
    f = cfg.focal()
    return Intrinsics(fx=f, fy=f, cx=(c.width - 1) / 2, cy=(c.height - 1) / 2, width=c.width, height=c.height)


def _progress(enabled: bool):
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn("[bold]synth[/bold] {task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True), disable=not enabled, transient=False,
    )


def _rounded(a: np.ndarray, nd: int = 6) -> list:
    return np.round(np.asarray(a, np.float64), nd).tolist()


ROOMS_FILE = "rooms.json"
"""Room ground truth in ``gt/``: see :func:`rooms_json`."""
ROOMS_FORMAT = "trackgraph-rooms"
ROOMS_VERSION = 1


def rooms_json(layout: Layout) -> dict:
    """``gt/rooms.json``: each room's ``id`` (its index in the layout), ``name``, ``type`` (the
    natural label of its kind, :data:`ROOM_TYPES`) and ``footprint``: the room's inner free
    floor (wall faces, not centre lines), a counter-clockwise polygon of world xy metres."""
    rooms = []
    for i, r in enumerate(layout.rooms):
        if r.kind not in ROOM_TYPES:
            raise ValueError(f"room {r.name!r} has kind {r.kind!r}, which ROOM_TYPES has no label for")
        x0, y0, x1, y1 = r.inner(layout.wall_thickness)
        rooms.append({
            "id": i, "name": r.name, "kind": r.kind, "type": ROOM_TYPES[r.kind],
            "footprint": _rounded([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]),
        })  # fmt: skip
    return {
        "format": ROOMS_FORMAT,
        "version": ROOMS_VERSION,
        "frame": "world, metres, z up",
        "footprint": "inner free floor of the room (inside the wall faces), counter-clockwise xy polygon",
        "rooms": rooms,
    }


def generate(config: SynthConfig | str, seed: int, out_dir: str | Path, *, overwrite: bool = False,
             progress: bool | None = None, workers: int | None = None, name: str | None = None,
             drift: float | None = None) -> dict:
    """Generate a synthetic RGB-D sequence with ground truth into ``out_dir``.

    ``config`` is a :class:`SynthConfig` or a preset name (:data:`PRESETS`). The same
    config and seed give byte-identical files. Raises :class:`writer.OutputExistsError` if
    ``out_dir`` is a non-empty folder (unless ``overwrite`` and it is a previous synth output).
    ``name`` labels the scene in the ground truth (default: the preset name, or "custom").
    ``drift``: odometry drift in metres per metre travelled (0 < drift <= 0.5; the seed drives
    it too): ``traj.txt`` becomes the drifted odometry, with ``traj_gt.txt`` and
    ``corrections.jsonl`` beside it (:func:`shared.synth.drift.add_drift`); a bad rate raises
    ValueError before any work.
    Returns ``{"frames", "objects", "out"}`` plus a few statistics, and with ``drift`` also
    ``"drift"`` (the rate) and ``"corrections"`` (how many).
    """
    from shared.synth import groundtruth, pictures
    from shared.synth.render import Renderer
    from shared.synth.trajectory import build_trajectory
    from shared.synth.world import build_world, world_clutter

    started = time.perf_counter()
    name = name or (config if isinstance(config, str) else None)
    cfg = preset_config(config) if isinstance(config, str) else config
    if drift is not None:
        from shared.synth.drift import validate_rate

        drift = validate_rate(drift)
    out = Path(out_dir).expanduser().absolute()
    writer.check_output(out, overwrite)
    if progress is None:
        progress = sys.stderr.isatty()
    staging = writer.staging_dir(out)
    try:
        world = build_world(cfg, seed)
        traj = build_trajectory(world, cfg.camera)
        K = intrinsics(cfg)
        renderer = Renderer(world, K, cfg.render)
        n = cfg.camera.frames
        n_ids = len(world.objects)
        sheet_idx = sorted({int(round(i)) for i in np.linspace(0, n - 1, min(cfg.gt.contact_sheet_frames, n))})
        sheet: dict[int, tuple] = {}
        rc = cfg.render

        # Sampled before rendering so each frame can mark the points it sees (see groundtruth).
        cloud = groundtruth.sample_cloud(world, {o.id for o in world.objects}, cfg.gt.point_spacing, seed, rc.textures)
        observed = np.zeros(len(cloud.points), bool)
        # Points grouped by object (and place), so each frame projects only the objects its
        # pixels show (and of those only the parts in view).
        chunks = groundtruth.point_chunks(cloud.points, cloud.labels, len(world.objects))

        def one(i: int) -> tuple[np.ndarray, np.ndarray]:
            fr = renderer.render(traj.poses[i], np.random.default_rng([seed, 11, i]))
            inst_u16 = (fr.instances + 1).astype(np.uint16)
            counts = np.bincount(inst_u16.ravel(), minlength=n_ids + 1)
            shown = np.flatnonzero(counts[1:])
            seen = groundtruth.observed_objects(cloud.points, chunks, shown, fr.depth, K, traj.poses[i])
            depth_u16 = writer.depth_units(fr.depth, rc.depth_scale)
            writer.write_bytes(staging / "results" / f"frame{i:06d}.jpg", writer.jpeg(fr.rgb, rc.jpeg_quality))
            writer.write_bytes(staging / "results" / f"depth{i:06d}.png", writer.png_u16(depth_u16))
            writer.write_bytes(staging / "instances" / f"instance{i:06d}.png", writer.png_u16(inst_u16))
            if i in sheet_idx:
                sheet[i] = (i, fr.rgb, depth_u16.astype(np.float32) / np.float32(rc.depth_scale), inst_u16)
            return counts, seen

        pixels = np.zeros(n_ids + 1, np.int64)
        frames_seen = np.zeros(n_ids + 1, np.int64)
        (staging / "results").mkdir(parents=True, exist_ok=True)
        (staging / "instances").mkdir(parents=True, exist_ok=True)
        # Threads: numpy, numba and PIL release the GIL for the heavy parts, so two frames in
        # flight keep two cores busy; results do not depend on the order frames finish in.
        # (Open3D's ray casting holds the GIL but uses all cores itself: leave it so.)
        n_workers = workers or max(1, min(4, os.cpu_count() or 1))
        with _progress(progress) as bar, ThreadPoolExecutor(n_workers) as pool:
            task = bar.add_task(f"{n} frames {K.width}x{K.height}", total=n)
            for counts, seen in pool.map(one, range(n)):
                observed[seen] = True
                pixels += counts
                frames_seen += counts > 0
                bar.advance(task)
        log.info("rendered %d frames (%d triangles)", n, renderer.triangles)

        writer.write_bytes(staging / "traj.txt", writer.traj_text(traj.poses).encode("ascii"))
        writer.write_json(staging / "intrinsics.json", {
            "fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "width": K.width, "height": K.height,
            "depth_scale": rc.depth_scale,
        })

        keep = {o.id for o in world.objects if pixels[o.id + 1] > 0}
        clutter = world_clutter(world, cfg.furnish.clutter_margin, cfg.furnish.structure_in_clutter)
        cloud = groundtruth.keep_observed(cloud, observed, keep)
        gt = staging / "gt"
        scene_name = f"synth_{name or 'custom'}_seed{seed}"
        writer.write_json(gt / "gt_categories.json", groundtruth.categories_json(world, keep, clutter, scene_name))
        writer.write_json(gt / "gt_categories_query_to_object_mapping_all.json", groundtruth.query_mapping(world, keep))
        writer.write_bytes(gt / "prompt_list.txt", ("\n".join(prompt_list()) + "\n").encode("utf-8"))
        writer.write_bytes(gt / "points.npy", writer.npy_bytes(cloud.points))
        writer.write_bytes(gt / "labels.npy", writer.npy_bytes(cloud.labels))
        writer.write_bytes(gt / "colors.npy", writer.npy_bytes(cloud.colors))
        writer.write_bytes(gt / "point_cloud.ply", writer.ply_bytes(cloud.points, cloud.colors, cloud.labels))

        lo = np.min([o.lo for o in world.objects], axis=0)
        hi = np.max([o.hi for o in world.objects], axis=0)
        layout = world.layout
        scene = {
            "name": scene_name,
            "preset": name,
            "seed": seed,
            "config": cfg.model_dump(mode="json"),
            "conventions": {
                "world": "metres, z up, floor at z = 0",
                "poses": "traj.txt: row-major 4x4 camera-to-world, OpenCV camera axes (x right, y down, z forward)",
                "depth": f"results/depthNNNNNN.png: uint16, metres = value / {rc.depth_scale}, 0 = no reading",
                "instances": "instances/instanceNNNNNN.png: uint16, 0 = no object, else object id + 1",
            },
            "rooms": [{
                "name": r.name, "kind": r.kind, "footprint": _rounded([[r.rect[0], r.rect[1]], [r.rect[2], r.rect[1]], [r.rect[2], r.rect[3]], [r.rect[0], r.rect[3]]]),
                "inner": _rounded(r.inner(layout.wall_thickness)),
            } for r in layout.rooms],
            "doorways": [{
                "rooms": list(d.rooms), "center": _rounded(d.point()), "axis": d.axis, "width": d.width, "height": d.height,
                "footprint": _rounded(d.passage(layout.wall_thickness)),
            } for d in layout.doors],
            "wall_height": layout.wall_height,
            "wall_thickness": layout.wall_thickness,
            "objects": [{
                "id": o.id, "category": o.category, "room": o.room, "mount": o.mount, "support": o.support,
                "aabb_min": _rounded(o.lo), "aabb_max": _rounded(o.hi), "parts": len(o.parts),
                "in_gt": o.id in keep, "pixels": int(pixels[o.id + 1]), "frames": int(frames_seen[o.id + 1]),
            } for o in world.objects],
            "mesh_bounds": {"min": _rounded(lo), "max": _rounded(hi)},
            "trajectory": {"frames": n, "length_m": round(traj.length, 4), "waypoints": _rounded(traj.waypoints)},
            "gt_points": int(len(cloud.points)),
        }
        writer.write_json(gt / "scene.json", scene)
        writer.write_json(gt / ROOMS_FILE, rooms_json(layout))

        shots = [sheet[i] for i in sheet_idx]
        writer.write_bytes(staging / "contact_sheet.png", pictures.contact_sheet(shots, rc.depth_max, n_ids))
        title = (f"{scene_name}: {len(layout.rooms)} rooms, {len(keep)} ground-truth objects, "
                 f"{n} frames, {traj.length:.1f} m walked")
        writer.write_bytes(staging / "topdown.png", pictures.topdown(world, traj, title))
        drifted = None
        if drift is not None:
            from shared.synth.drift import add_drift

            # In the staging folder, so a sequence with drift appears whole or not at all.
            drifted = add_drift(staging, drift, seed)
        writer.finalize(staging, out, overwrite)
    except BaseException:
        writer.discard(staging)
        raise
    seconds = time.perf_counter() - started
    log.info("synth %s seed %d: %d frames, %d objects in %.1f s -> %s", name or "custom", seed, n, len(keep), seconds, out)
    result = {
        "frames": n,
        "objects": len(keep),
        "out": str(out),
        "categories": len({world.objects[i].category for i in keep}),
        "gt_points": int(len(cloud.points)),
        "seconds": round(seconds, 2),
    }
    if drifted is not None:
        result["drift"] = drifted["rate"]
        result["corrections"] = drifted["corrections"]
    return result


def run_synth(preset: str, seed: int, out: Path, overrides: dict | None = None, *, overwrite: bool = False,
              progress: bool | None = None, drift: float | None = None,
              resolution: tuple[int, int] | None = None) -> dict:
    """Entry point of ``trackgraph synth --preset P --seed N --out DIR [--drift RATE] [--resolution WxH]``.

    ``overrides`` are nested config keys layered on the preset (``{"camera": {"frames": 30}}``);
    bad keys raise :class:`shared.config.base.ConfigError` naming them. ``drift``: see
    :func:`generate`. ``resolution`` ``(width, height)`` renders the same sequence at another
    image size: the same world (every object, its id and place), the same poses in
    ``traj.txt`` byte for byte, intrinsics as :func:`intrinsics` says. The ground truth lists
    the objects seen in at least one frame, so at another size (above all another aspect
    ratio) an object seen only at an image's edge can come or go. With ``resolution`` the
    result also has ``"resolution": [width, height]``.
    """
    cfg = preset_config(preset, overrides, resolution=resolution)
    result = generate(cfg, seed, out, overwrite=overwrite, progress=progress, name=preset, drift=drift)
    if resolution is not None:
        result["resolution"] = [cfg.camera.width, cfg.camera.height]
    return result


__all__ = ["PRESETS", "generate", "intrinsics", "run_synth"]
