"""``trackgraph export-onnx``: the configured FastSAM, CLIP towers and DINOv3 as ONNX files,
for onnxruntime or TensorRT on a Jetson. Point a config's ``fastsam_onnx``, ``clip_onnx`` and
``dinov3_onnx`` backends at the results.

FastSAM is exported with dynamic height and width, so the ``fastsam_onnx`` backend can
letterbox each frame exactly as the .pt path does (480x640 at imgsz 1024 to 768x1024) and give
its masks; a static square export pads such frames to 1024x1024 and finds other masks (TensorRT
builds a dynamic-shape ONNX file with an optimisation profile: ``--minShapes``/``--optShapes``)."""

from __future__ import annotations

import logging
from pathlib import Path

from shared.config.root import TrackGraphConfig

log = logging.getLogger(__name__)


def export_all(
    cfg: TrackGraphConfig, out: Path, only: set[str] | None = None, fastsam_static: bool = False
) -> dict[str, str]:
    """Export every learned model of ``cfg`` (or the ``only`` roles) under ``out``. FastSAM's
    input is dynamic unless ``fastsam_static``, which fixes it at ``imgsz`` x ``imgsz`` (masks of
    non-square frames then differ from the .pt path's)."""
    out = Path(out)
    done: dict[str, str] = {}
    seg, vl, feats = cfg.keyframe_vl.segmenter, cfg.keyframe_vl.vl, cfg.tracker.features
    want = only or {"segmenter", "vl_encoder", "dense_features"}
    torch_backends = {"segmenter": seg.backend == "fastsam", "vl_encoder": vl.backend == "openclip", "dense_features": feats.backend == "dinov3"}
    if not any(torch_backends[r] for r in want):
        raise ValueError("nothing to export: the config names no torch backend (fastsam, openclip, dinov3)")
    out.mkdir(parents=True, exist_ok=True)
    if "segmenter" in want and seg.backend == "fastsam":
        from shared.perception.segmenters.fastsam_onnx import export_fastsam_onnx

        done["segmenter"] = str(export_fastsam_onnx(seg.weights, out / "fastsam.onnx", seg.imgsz, dynamic=not fastsam_static))
    if "vl_encoder" in want and vl.backend == "openclip":
        from shared.perception.encoders.clip_onnx import export_clip_onnx

        done["vl_encoder"] = str(export_clip_onnx(vl.model, vl.weights, out / "clip"))
    if "dense_features" in want and feats.backend == "dinov3":
        from shared.perception.features import export_dinov3_onnx

        done["dense_features"] = str(export_dinov3_onnx(feats, out / "dinov3.onnx"))
    for role, path in done.items():
        log.info("exported %s to %s", role, path)
    return done
