"""What a finished map folder holds besides the graph store: ``mesh.ply`` with segment ids,
the OpenLex3D prediction files, and ``run.json``. Written the same way by ``trackgraph map``
and by the fusion service at the end of its sequence."""

from __future__ import annotations

import io
import platform
import resource
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from shared.config.root import TrackGraphConfig
from shared.io import atomic_write_bytes


def peak_rss_mb() -> float:
    """This process's peak resident memory since it started, in MB.

    /proc's VmHWM, not getrusage's ru_maxrss: Linux carries ru_maxrss across fork and exec, so
    a service started by a 5 GB parent (a bench holding CLIP weights) reported at least 5 GB
    whatever it used itself."""
    from shared.procfs import status_mb

    return status_mb("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_summary(cfg: TrackGraphConfig, fusion, snapshot, *, frames: int, seconds: float, sequence: Path | str | None) -> dict[str, Any]:
    """``run.json``: what was mapped, how fast, with what, on what (the in-process pipeline
    and the fusion service write the same keys; RAM and GPU memory are this process's)."""
    return {
        "frames": frames,
        "seconds": round(seconds, 3),
        "hz": round(frames / seconds, 3) if seconds > 0 else None,
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "segments": len(fusion.segments.segments),
        "gpu_peak_mb": _gpu_peak_mb(),
        "graph_seq": snapshot.graph_seq,
        "places": len(snapshot.places),
        "rooms": len(snapshot.rooms),
        "sequence": None if sequence is None else str(sequence),
        "corrections": fusion.corrections.as_dict(),
        "backends": {
            "tracker": cfg.tracker.mode,
            "dense_features": cfg.tracker.features.backend,
            "segmenter": cfg.keyframe_vl.segmenter.backend,
            "vl_encoder": cfg.keyframe_vl.vl.backend,
        },
        "precision": {
            # Backends without a network (classical, simulated) or running an export in its
            # own precision (the ONNX ones) have no precision setting.
            "dense_features": getattr(cfg.tracker.features, "precision", None),
            "segmenter": getattr(cfg.keyframe_vl.segmenter, "precision", None),
            "vl_encoder": getattr(cfg.keyframe_vl.vl, "precision", None),
        },
        "devices": {"tracker": cfg.tracker.device, "keyframe_vl": cfg.keyframe_vl.device, "query": cfg.query.device},
        "voxel_size": cfg.fusion.tsdf.voxel_size,
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
    }


def service_summary(
    cfg: TrackGraphConfig, fusion, snapshot, *, frames: int, first_at: float | None, last_at: float | None, now: float, delivery: dict[str, Any],
) -> dict[str, Any]:  # fmt: skip
    """The fusion service's ``run.json``: :func:`run_summary`'s keys over the frames it fused
    (``first_at`` to ``now``), then ``service``, ``fused_seconds`` and the ``delivery`` figures."""
    summary = run_summary(cfg, fusion, snapshot, frames=frames, seconds=now - (first_at or now), sequence=None)
    # From the first frame fused to the last, without the final save: what a live source's
    # rate is compared with (``trackgraph bench run``).
    summary.update(service="fusion", fused_seconds=round((last_at or 0.0) - (first_at or 0.0), 3), **delivery)
    return summary


SEGMENT_IDS_FILE = "segment_ids.npy"
"""Row k of the OpenLex3D export is segment ``segment_ids[k]``."""
ROOMS_FILE = "rooms.npz"
"""The rooms' footprints (:mod:`shared.graph.roomgrid`)."""


def export_map(out: Path, fusion) -> None:
    """``mesh.ply`` with segment ids, the OpenLex3D prediction (point cloud, one embedding
    per segment, a segment index per point), each row's segment id and ``rooms.npz``, the
    rooms' footprints."""
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
    # The rooms' footprints, for `trackgraph eval rooms` (none before the first rebuild).
    grid = fusion.room_grid()
    if grid is not None:
        from shared.graph.roomgrid import save_room_grid

        save_room_grid(out / ROOMS_FILE, grid)


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
