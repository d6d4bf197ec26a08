"""Checkpoints of the paper's real architectures with random weights, for benchmarks and
tests: the same FLOPs and the same loading path as the real weights, which cannot be
downloaded where this project is built. Never use them to measure accuracy."""

from __future__ import annotations

from pathlib import Path


def save_random_fastsam(path: str | Path, variant: str = "x", seed: int = 0, alive: bool = False) -> Path:
    """FastSAM is YOLOv8-seg with one class; FastSAM-x is the ``x`` scale. Saved the way
    ultralytics saves checkpoints, so ``FastSAM(path)`` loads it.

    ``alive``: PyTorch's default init fades activations until every anchor gets the same
    score and no mask passes a threshold. He init with the head scaled to logits of order one
    keeps scores spread, so confidence thresholds and NMS cost what they do with real weights.
    """
    import torch

    from shared.perception.segmenters.fastsam import import_ultralytics

    import_ultralytics()  # before any ultralytics module: it leaves PIL as it was
    from ultralytics.nn.tasks import SegmentationModel, yaml_model_load

    torch.manual_seed(seed)
    spec = yaml_model_load(f"yolov8{variant}-seg.yaml")  # ships inside ultralytics
    spec["nc"] = 1
    model = SegmentationModel(spec, ch=3, nc=1, verbose=False)
    model.task = "segment"
    if alive:
        _keep_alive(model)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": model.half(), "ema": None, "train_args": {"task": "segment", "imgsz": 1024}}, path)
    return path


def _keep_alive(model) -> None:
    import torch

    for module in model.modules():
        if isinstance(module, torch.nn.Conv2d) and module.weight.requires_grad:  # not the fixed DFL conv
            torch.nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
    head = model.model[-1]
    with torch.no_grad():
        for conv in (seq[-1] for seq in head.cv3):
            torch.nn.init.normal_(conv.weight, 0.0, 40.0)
            torch.nn.init.constant_(conv.bias, -1.5)
        for conv in (seq[-1] for seq in head.cv4):
            conv.weight.mul_(100.0)
        for conv in (seq[-1] for seq in head.cv2):
            torch.nn.init.normal_(conv.weight, 0.0, 30.0)
            torch.nn.init.constant_(conv.bias, 1.0)


def save_random_openclip(path: str | Path, arch: str = "ViT-H-14", seed: int = 0) -> Path:
    """An OpenCLIP state dict of ``arch`` that ``open_clip`` loads from a file path."""
    import open_clip
    import torch

    torch.manual_seed(seed)
    model = open_clip.create_model(arch, pretrained=None)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), path)
    return path


def save_random_dinov3_timm(path: str | Path, seed: int = 0) -> Path:
    """DINOv3 ViT-S+/16 as timm's ``vit_small_plus_patch16_dinov3`` state dict (``loader: timm``)."""
    import timm
    import torch

    torch.manual_seed(seed)
    model = timm.create_model("vit_small_plus_patch16_dinov3", pretrained=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), path)
    return path


RANDOM_DINOV3_FILE = "dinov3_vits16plus_timm.pth"


RANDOM_MAX_MASKS = 24
"""Masks per keyframe from random FastSAM weights: the objects of 100 px or more that a view
of the synthetic ``demo`` scene holds, on average (benchmarks/RESULTS.md, keyframe_vl)."""


def random_weight_overrides(cfg, folder: str | Path, seed: int = 0, max_masks: int = RANDOM_MAX_MASKS) -> dict:
    """Random-weight files, in ``folder``, of every model backend ``cfg`` (a
    ``TrackGraphConfig``) names, and the config overrides that point it at them: timings of
    the paper's architectures where their weights are absent. A file already there is
    reused, so a bench of several configs writes ViT-H-14's 4 GB once.

    FastSAM is built ``alive`` and takes every detection (``conf`` 0): untrained scores sit
    below the real threshold, and a segmenter that returns no mask would leave CLIP, keyframe
    correction and propagation with nothing to do. ``max_masks`` then caps the count at about
    what a trained one finds in a view. Maps made this way are meaningless;
    only their times and memory count.
    """
    folder = Path(folder).resolve()  # services may run from another folder
    out: dict = {}
    seg, vl, feats = cfg.keyframe_vl.segmenter, cfg.keyframe_vl.vl, cfg.tracker.features
    if seg.backend == "fastsam":
        stem = Path(seg.weights).stem.lower()
        variant = stem.rsplit("-", 1)[-1] if "-" in stem else "x"
        if variant not in ("n", "s", "m", "l", "x"):
            raise ValueError(f"keyframe_vl.segmenter.weights: {seg.weights!r} names no FastSAM scale (FastSAM-x.pt, FastSAM-s.pt)")
        path = folder / f"FastSAM-{variant}-random.pt"
        if not path.is_file():
            save_random_fastsam(path, variant, seed=seed, alive=True)
        out["keyframe_vl"] = {"segmenter": {"weights": str(path), "conf": 0.0, "max_masks": int(max_masks)}}
    if vl.backend == "openclip":
        path = folder / f"open_clip_{vl.model}-random.bin"
        if not path.is_file():
            save_random_openclip(path, vl.model, seed=seed)
        out.setdefault("keyframe_vl", {})["vl"] = {"weights": str(path)}
    if feats.backend == "dinov3":
        path = folder / RANDOM_DINOV3_FILE
        if not path.is_file():
            save_random_dinov3_timm(path, seed=seed)
        out["tracker"] = {"features": {"loader": "timm", "weights": str(path)}}
    return out
