"""Synthetic indoor RGB-D sequences with ground truth (``trackgraph synth``).

A procedural world, deterministic by seed: rooms with walls, floors, ceilings and doorways,
furnished with textured objects of about 35 categories built from primitives, small objects
standing on larger ones; rendered by ray casting along a smooth walk through the rooms.

Output folder (Replica NICE-SLAM layout plus ground truth)::

    results/frame000000.jpg        RGB, JPEG quality 95
    results/depth000000.png        uint16 z-depth, metres = value / 6553.5, 0 = no reading
    instances/instance000000.png   uint16 instance ids: 0 = no object, else object id + 1
    traj.txt                       one row-major 4x4 camera-to-world per line (OpenCV axes)
    intrinsics.json                {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"}
    gt/gt_categories.json          OpenLex3D: dataset.samples[*] = {object_id, name, room,
                                   labels.image_attributes.{synonyms, depictions, vis_sim,
                                   clutter (ids as strings)}}
    gt/gt_categories_query_to_object_mapping_all.json   {"level0": {synonym: [object ids]}}
    gt/prompt_list.txt             every label of every tier, sorted, one per line
    gt/points.npy, labels.npy, colors.npy   (N, 3) float32, (N,) int32 object ids, (N, 3) uint8
    gt/point_cloud.ply             the same cloud (x y z, red green blue, object_id)
    gt/scene.json                  rooms, doorways, object boxes, mesh bounds, config, seed
    contact_sheet.png, topdown.png overview pictures

With ``--drift RATE`` (:mod:`shared.synth.drift`) ``traj.txt`` holds drifting odometry and
three more files come with it::

    traj_gt.txt                    the true poses (the images are rendered from them)
    corrections.jsonl              one PoseCorrection per loop closure: the true poses so far
    drift.png                      true and drifted walks from above, closures marked

The world frame is z up with the floor at z = 0 (metres). Ground truth lists the objects that
appear in at least one frame; walls, floors and ceilings are objects too (categories wall,
floor, ceiling), which OpenLex3D's evaluation excludes by name.

Importing this package is light (no Open3D or matplotlib until ``generate`` runs).
"""

from shared.synth.config import PRESETS, SynthConfig, preset_config
from shared.synth.pipeline import generate, intrinsics, run_synth
from shared.synth.writer import OutputExistsError

__all__ = ["PRESETS", "OutputExistsError", "SynthConfig", "generate", "intrinsics", "preset_config", "run_synth"]
