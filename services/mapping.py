"""``trackgraph map``: the in-process pipeline, source -> tracker core -> fusion core.

It composes the same cores as the distributed services, with no Zenoh: keyframes are
segmented and embedded at once, so every keyframe's masks are applied before the next frame.
"""

from __future__ import annotations

import io
import json
import logging
import platform
import resource
import time
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from services.source.core import planned_indices
from shared.config.base import save_resolved
from shared.config.root import TrackGraphConfig
from shared.datasets import open_sequence
from shared.datasets.base import DatasetError
from shared.io import atomic_write_bytes, atomic_write_text

log = logging.getLogger(__name__)


def prepare_config(cfg: TrackGraphConfig, seq_dir: Path) -> TrackGraphConfig:
    """Point every simulated backend whose ground truth is unset at the sequence, when it is
    synthetic (no message carries ground truth; see ``TrackGraphConfig.with_ground_truth``)."""
    return cfg.with_ground_truth(seq_dir)


def build_tracker(cfg: TrackGraphConfig, with_keyframes: bool = True):
    """The tracker core of ``cfg.tracker.mode`` and, unless ground truth or not asked for (the
    distributed tracker gets its masks over Zenoh), the keyframe core."""
    from services.keyframe_vl.core import KeyframeVLCore, resolve_device

    if cfg.tracker.mode == "ground_truth":
        from services.keyframe_vl.encoders import make_vl_encoder
        from services.tracker.oracle import GroundTruthTracker

        encoder = make_vl_encoder(cfg.keyframe_vl.vl, device=resolve_device(cfg.keyframe_vl.device))
        return GroundTruthTracker(cfg.tracker.keyframe_interval, encoder, cfg.tracker.oracle_retire_frames, ground_truth=cfg.tracker.ground_truth), None
    from services.tracker.core import TrackerCore
    from services.tracker.features import make_dense_features

    device = resolve_device(cfg.tracker.device)
    features = make_dense_features(cfg.tracker.features, device=device, fp16=device.startswith("cuda"))
    return TrackerCore(cfg.tracker, features), (KeyframeVLCore(cfg.keyframe_vl) if with_keyframes else None)


def run_map(
    seq_dir: Path,
    cfg: TrackGraphConfig,
    out: Path,
    *,
    dataset: str | None = None,
    save_tracks: bool = False,
    stride: int | None = None,
    max_frames: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Map a recorded sequence; writes the map folder and returns the ``run.json`` summary."""
    from services.fusion.core import FusionCore
    from shared.eval.track_io import TrackWriter
    from shared.graph.store import MapStore

    seq_dir, out = Path(seq_dir), Path(out)
    cfg = prepare_config(cfg, seq_dir)
    reader = open_sequence(seq_dir, dataset or cfg.source.dataset, cfg.source)
    plan = planned_indices(len(reader), stride or cfg.source.stride, max_frames or cfg.source.max_frames)
    out.mkdir(parents=True, exist_ok=True)
    save_resolved(cfg, out / "config.yaml")

    t0 = time.perf_counter()
    tracker, keyframes = build_tracker(cfg)
    fusion = FusionCore(cfg.fusion, device=cfg.tracker.device)
    writer = TrackWriter(out) if save_tracks else None
    bar = _bar(progress, len(plan))
    t_start = time.perf_counter()
    rejected: list[str] = []
    try:
        for i in plan:
            try:
                frame = reader.frame(i)
            except DatasetError as exc:
                # one corrupt frame (a truncated PNG, a NaN pose) must not cost the map
                rejected.append(str(exc))
                log.warning("frame %d refused: %s", i, exc)
                if bar is not None:
                    bar.update(1)
                continue
            req = tracker.begin_frame(frame)
            if req is not None and keyframes is not None:
                image, masks, _ = keyframes.segment(req)
                tracker.apply_masks(frame.frame_index, masks)
                tracker.apply_features(frame.frame_index, keyframes.features(image, masks).features)
            tracked = tracker.end_frame()
            feats = tracker.take_track_features(frame.frame_index)
            if feats is not None:
                fusion.add_track_features(feats)
            fusion.add_frame(tracked)
            if writer is not None:
                writer.write(frame.frame_index, tracked.track_ids, keyframe=tracked.keyframe)
            if bar is not None:
                bar.update(1)
        fusion.finish()
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
    seconds = time.perf_counter() - t_start
    if len(rejected) == len(plan) and plan:
        raise DatasetError(f"{seq_dir}: no frame could be read; the first error: {rejected[0]}")

    snapshot = fusion.snapshot(whole_map=True)
    MapStore(out / "graph", robot_id=cfg.robot_id).save(snapshot, extra_state=fusion.state_dict(), metadata={"sequence": str(seq_dir)})
    export_map(out, fusion)
    summary = run_summary(cfg, fusion, snapshot, frames=len(plan) - len(rejected), seconds=seconds, sequence=seq_dir)
    summary["setup_seconds"] = round(t_start - t0, 3)
    summary["frames_rejected"] = len(rejected)
    summary["rejected"] = rejected[:20]
    atomic_write_text(out / "run.json", json.dumps(summary, indent=2))
    log.info("mapped %d frames in %.1f s (%.2f Hz): %d segments", len(plan), seconds, summary["hz"] or 0, summary["segments"])
    return summary


def run_summary(cfg: TrackGraphConfig, fusion, snapshot, *, frames: int, seconds: float, sequence: Path | str | None) -> dict[str, Any]:
    """``run.json``: what was mapped, how fast, with what, on what (the in-process pipeline
    and the fusion service write the same keys; RAM and GPU memory are this process's)."""
    return {
        "frames": frames,
        "seconds": round(seconds, 3),
        "hz": round(frames / seconds, 3) if seconds > 0 else None,
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "segments": len(fusion.segments.segments),
        "gpu_peak_mb": _gpu_peak_mb(),
        "graph_seq": snapshot.graph_seq,
        "places": len(snapshot.places),
        "rooms": len(snapshot.rooms),
        "sequence": None if sequence is None else str(sequence),
        "backends": {
            "tracker": cfg.tracker.mode,
            "dense_features": cfg.tracker.features.backend,
            "segmenter": cfg.keyframe_vl.segmenter.backend,
            "vl_encoder": cfg.keyframe_vl.vl.backend,
        },
        "voxel_size": cfg.fusion.tsdf.voxel_size,
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
    }


SEGMENT_IDS_FILE = "segment_ids.npy"
"""Row k of the OpenLex3D export is segment ``segment_ids[k]``."""


def export_map(out: Path, fusion) -> None:
    """``mesh.ply`` with segment ids, the OpenLex3D prediction (point cloud, one embedding
    per segment, a segment index per point) and each row's segment id."""
    from shared.eval.prediction import write_prediction

    chunk = fusion.full_mesh_chunk()
    atomic_write_bytes(out / "mesh.ply", ply_bytes(chunk.vertices, chunk.colors, chunk.faces, chunk.segment_ids))
    segs = [s for s in fusion.segments.segments.values() if s.num_vertices]
    dim = next((len(next(iter(s.gallery.values()))) for s in segs if s.gallery), 1)
    points, index, emb = [], [], []
    for row, s in enumerate(sorted(segs, key=lambda s: s.id)):
        points.append(s.positions)
        index.append(np.full(len(s.positions), row, np.int64))
        emb.append(segment_embedding(s, dim))
    if points:
        write_prediction(out, np.concatenate(points), np.concatenate(index), np.stack(emb))
    else:
        write_prediction(out, np.zeros((0, 3), np.float32), np.zeros(0, np.int64), np.zeros((0, dim), np.float32))
    # Which segment each OpenLex3D instance row is, so evaluations of the query service can
    # score its hits (segment ids) on the same points.
    buf = io.BytesIO()
    np.save(buf, np.array([s.id for s in sorted(segs, key=lambda s: s.id)], np.int64))
    atomic_write_bytes(out / SEGMENT_IDS_FILE, buf.getvalue())


def segment_embedding(segment, dim: int) -> Annotated[np.ndarray, "(D,) float32"]:
    """One vector per segment for the OpenLex3D format, which has no galleries: the unit
    mean of the gallery rows (zeros for a segment without CLIP features). Our own query
    service scores the full gallery by its max (eq. 10)."""
    if not segment.gallery:
        return np.zeros(dim, np.float32)
    rows = np.stack([np.asarray(v, np.float64) for v in segment.gallery.values()])
    rows /= np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12)
    m = rows.mean(0)
    return (m / max(np.linalg.norm(m), 1e-12)).astype(np.float32)


def ply_bytes(
    vertices: Annotated[np.ndarray, "(V, 3) float32"],
    colors: Annotated[np.ndarray, "(V, 3) uint8"],
    faces: Annotated[np.ndarray, "(F, 3) int32"],
    segment_ids: Annotated[np.ndarray, "(V,) int32"],
) -> bytes:
    """Binary little-endian PLY with a per-vertex ``segment`` property (-1 = none)."""
    v = np.zeros(len(vertices), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("segment", "<i4")])
    v["x"], v["y"], v["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    v["red"], v["green"], v["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    v["segment"] = segment_ids
    f = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    f["n"] = 3
    f["i"] = faces
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty int segment\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    return header.encode() + v.tobytes() + f.tobytes()


def _gpu_peak_mb() -> float | None:
    import sys

    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available():
        return None
    return round(torch.cuda.max_memory_allocated() / 2**20, 1)


def _bar(enabled: bool, total: int):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="map")
