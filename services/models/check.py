"""``trackgraph models check``: every weight file a config needs, whether it is present and
loads, and where to obtain it. Weights are never downloaded by the project."""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

from shared.config.root import TrackGraphConfig

log = logging.getLogger(__name__)

FASTSAM_SOURCE = (
    "FastSAM-x.pt from the FastSAM releases (github.com/CASIA-IVA-Lab/FastSAM) or the Ultralytics "
    "assets release (github.com/ultralytics/assets, FastSAM-x.pt); export ONNX with `trackgraph export-onnx`"
)
DINOV3_SOURCE = (
    "DINOv3 ViT-S+/16 (LVD-1689M) from the Hugging Face repository "
    "facebook/dinov3-vits16plus-pretrain-lvd1689m (transformers folder, or timm "
    "vit_small_plus_patch16_dinov3 weights), or the official dinov3 .pth; access must be "
    "requested on the hub, then copy the files here"
)
"""Where DINOv3 comes from when the torch side (dinov3.WHERE, per loader) is not installed."""

ONNX_EXPORT = "an ONNX export written by `trackgraph export-onnx --config FILE --out DIR` from "


@dataclass
class ModelEntry:
    role: str
    backend: str
    path: str
    """As the config gives it (relative paths are read from the working directory)."""
    present: bool
    loads: bool | None
    error: str | None
    source: str
    resolved: str = ""
    """``path`` made absolute: the file the loader actually reads."""
    loader: str | None = None
    """The DINOv3 weight layout (tracker.features.loader); None for the other roles."""


def dinov3_source(loader: str) -> str:
    """Where the weights of DINOv3 ``loader`` (transformers / timm / hub) come from."""
    try:
        from shared.perception.features.dinov3 import WHERE
    except ImportError:  # no torch here: the loader could not run either, the general text will do
        return DINOV3_SOURCE
    return f"DINOv3 ViT-S+/16 for tracker.features.loader {loader}: {WHERE[loader]}"


def needed(cfg: TrackGraphConfig) -> list[tuple[str, str, str, str]]:
    """(role, backend, path, source) of every weight file the config's backends read; the
    source is that backend's and loader's own (an ONNX backend's names the export too)."""
    from shared.perception.encoders.weights import weights_hint

    out = []
    seg = cfg.keyframe_vl.segmenter
    if seg.backend in ("fastsam", "fastsam_onnx"):
        out.append(("segmenter", seg.backend, seg.weights, FASTSAM_SOURCE))
    vl = cfg.keyframe_vl.vl
    if vl.backend in ("openclip", "clip_onnx"):
        source = weights_hint(vl.model)
        if vl.backend == "clip_onnx":
            source = f"{ONNX_EXPORT}the OpenCLIP {vl.model} checkpoint: {source}"
        out.append(("vl_encoder", vl.backend, vl.weights, source))
    feats = cfg.tracker.features
    if cfg.tracker.mode != "ground_truth" and feats.backend in ("dinov3", "dinov3_onnx"):
        source = dinov3_source(feats.loader)  # both DINOv3 backends have one
        if feats.backend == "dinov3_onnx":
            source = ONNX_EXPORT + source
        out.append(("dense_features", feats.backend, feats.weights, source))
    return out


def _load(cfg: TrackGraphConfig, role: str) -> None:
    if role == "segmenter":
        from shared.perception.segmenters import make_segmenter

        make_segmenter(cfg.keyframe_vl.segmenter)
    elif role == "vl_encoder":
        from shared.perception.encoders import make_vl_encoder

        make_vl_encoder(cfg.keyframe_vl.vl)
    else:
        from shared.perception.features import make_dense_features

        make_dense_features(cfg.tracker.features)


def check_models(cfg: TrackGraphConfig, load: bool = True) -> dict:
    """``{"ok", "missing": [paths], "models": [entries]}``; ``ok`` when every file is present
    and (with ``load``) builds through the same code path mapping uses."""
    entries = []
    for role, backend, path, source in needed(cfg):
        resolved = Path(path).expanduser().resolve()
        present = resolved.exists()
        loads, error = None, None
        if present and load:
            try:
                _load(cfg, role)
                loads = True
            except Exception as exc:  # noqa: BLE001 - report any loader failure to the user
                # A file of the wrong model lands here too (the loaders refuse it, naming the
                # keys that do not fit), so a present file is not a usable one.
                loads, error = False, f"{type(exc).__name__}: {exc}"
        elif not present:
            error = f"{resolved} not found"
        loader = cfg.tracker.features.loader if role == "dense_features" else None
        entries.append(ModelEntry(role, backend, str(path), present, loads, error, source, str(resolved), loader))
    missing = [e.path for e in entries if not e.present]
    ok = not missing and all(e.loads is not False for e in entries)
    return {"ok": ok, "missing": missing, "models": [asdict(e) for e in entries]}
