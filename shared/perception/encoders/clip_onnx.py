"""CLIP towers exported to ONNX and run by onnxruntime (the ``clip_onnx`` VL backend).

:func:`export_clip_onnx` writes, into one folder, ``image.onnx`` (pixels ``(B, 3, S, S)``
float32 -> ``(B, D)``), ``text.onnx`` (tokens ``(B, L)`` int64 -> ``(B, D)``), their external
weight files, and ``clip_onnx.json`` with what the runtime needs to preprocess like OpenCLIP
(architecture, image size, mean, std, interpolation, resize mode, dim, context length).
The towers' outputs are not normalised in the graph; the runtime normalises in float32, as the
torch backend does, so both give the same features.

Images are preprocessed in numpy/PIL exactly as OpenCLIP's inference transform does with
torchvision (resize the short side with PIL, centre crop with torchvision's rounding, scale to
[0, 1], normalise). Text goes through the architecture's OpenCLIP tokenizer, so this backend
still imports open_clip (and with it torch) for tokenising, though not for inference.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from PIL import Image

from shared.perception import KeyframeImage, Masks
from shared.perception.encoders.common import ImageTowerMixin, check_rgb, unit_rows
from shared.perception.encoders.crops import (
    CROP_MODES,
    CropMode,
    batched,
    fill_colour,
    padded_crops,
    shape_crops,
)
from shared.perception.encoders.weights import ONNX_IMAGE, ONNX_META, ONNX_TEXT, resolve_onnx_dir

log = logging.getLogger(__name__)

META_FORMAT = 1
TEXT_BATCH = 256

_PIL_FILTERS = {"bicubic": Image.Resampling.BICUBIC, "bilinear": Image.Resampling.BILINEAR}


def _resized_size(h: int, w: int, size: tuple[int, int], resize_mode: str) -> tuple[int, int]:
    """Output (h, w) of torchvision's Resize as OpenCLIP configures it."""
    if resize_mode == "squash":
        return size
    short, long = (w, h) if w <= h else (h, w)
    new_short, new_long = size[0], int(size[0] * long / short)
    return (new_long, new_short) if w <= h else (new_short, new_long)


def clip_preprocess(
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
    size: tuple[int, int],
    mean: Sequence[float],
    std: Sequence[float],
    interpolation: str = "bicubic",
    resize_mode: str = "shortest",
) -> Annotated[np.ndarray, "(3, size[0], size[1]) float32"]:
    """OpenCLIP's inference transform without torch (``shortest`` or ``squash`` resize)."""
    if resize_mode not in ("shortest", "squash"):
        raise ValueError(f"resize mode {resize_mode!r} is not supported by the ONNX preprocessing")
    if resize_mode == "shortest" and size[0] != size[1]:
        raise ValueError(f"non-square input {size} with resize mode 'shortest' is not supported")
    img = Image.fromarray(rgb)
    h, w = rgb.shape[:2]
    new_h, new_w = _resized_size(h, w, size, resize_mode)
    # torchvision skips the resize when the size already matches; PIL would still filter.
    if (new_h, new_w) != (h, w):
        img = img.resize((new_w, new_h), _PIL_FILTERS.get(interpolation, Image.Resampling.BICUBIC))
    # Python's round (half to even) is what torchvision's centre crop uses.
    top = int(round((new_h - size[0]) / 2.0))
    left = int(round((new_w - size[1]) / 2.0))
    img = img.crop((left, top, left + size[1], top + size[0]))
    x = np.asarray(img, dtype=np.float32) / np.float32(255.0)
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def read_meta(folder: Path) -> dict[str, Any]:
    path = folder / ONNX_META
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable CLIP ONNX description ({exc})") from exc
    need = ("arch", "image_size", "mean", "std", "dim", "context_length")
    missing = [k for k in need if k not in meta]
    if missing:
        raise ValueError(f"{path}: missing {', '.join(missing)}")
    return meta


class ClipOnnxEncoder(ImageTowerMixin):
    """The ``clip_onnx`` VL backend, reading a folder written by :func:`export_clip_onnx`."""

    def __init__(
        self,
        folder: str | Path,
        arch: str | None = None,
        device: str = "cpu",
        crop_padding: float = 0.1,
        batch_size: int = 16,
        crop_mode: CropMode = "pad_square",
    ) -> None:
        import onnxruntime as ort

        from shared.devices import onnx_providers

        if crop_mode not in CROP_MODES:
            raise ValueError(f"crop mode {crop_mode!r}: expected one of {', '.join(CROP_MODES)}")

        from shared.perception.encoders.openclip import _import_open_clip

        self.folder = resolve_onnx_dir(folder)
        meta = read_meta(self.folder)
        if arch is not None and arch != meta["arch"]:
            raise ValueError(
                f"{self.folder / ONNX_META}: exported from {meta['arch']}, but the config names {arch}; "
                "set keyframe_vl.vl.model to match the export"
            )
        self.arch = str(meta["arch"])
        self.name = f"openclip:{self.arch}"
        self.dim = int(meta["dim"])
        self.size = tuple(int(v) for v in meta["image_size"])
        self.mean = tuple(float(v) for v in meta["mean"])
        self.std = tuple(float(v) for v in meta["std"])
        self.interpolation = str(meta.get("interpolation", "bicubic"))
        self.resize_mode = str(meta.get("resize_mode", "shortest"))
        self.crop_padding = float(crop_padding)
        self.batch_size = int(batch_size)
        self.crop_mode: CropMode = crop_mode
        self.fill = fill_colour(self.mean)
        t0 = time.perf_counter()
        providers = onnx_providers(device, "keyframe_vl.device")
        self.image_session = ort.InferenceSession(str(self.folder / ONNX_IMAGE), providers=providers)
        self.text_session = ort.InferenceSession(str(self.folder / ONNX_TEXT), providers=providers)
        self.tokenizer = _import_open_clip().get_tokenizer(self.arch, context_length=int(meta["context_length"]))
        log.info(
            "CLIP ONNX %s loaded from %s (%s) in %.1f s",
            self.arch, self.folder, self.image_session.get_providers()[0], time.perf_counter() - t0,
        )  # fmt: skip

    def preprocess(self, rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]) -> Annotated[np.ndarray, "(3, S, S) float32"]:
        return clip_preprocess(rgb, self.size, self.mean, self.std, self.interpolation, self.resize_mode)

    def _forward_images(self, images: Sequence[np.ndarray]) -> Annotated[np.ndarray, "(N, D) float32"]:
        feats = []
        for chunk in batched(images, self.batch_size):
            x = np.stack([self.preprocess(im) for im in chunk])
            feats.append(self.image_session.run(None, {"pixels": x})[0])
        if not feats:
            return np.zeros((0, self.dim), np.float32)
        return unit_rows(np.concatenate(feats))

    def encode_crops(self, image: KeyframeImage, masks: Masks) -> Annotated[np.ndarray, "(N, D) float32"]:
        rgb = check_rgb(image.rgb)
        if len(masks) == 0:
            return np.zeros((0, self.dim), np.float32)
        crops = padded_crops(rgb, masks.masks, self.crop_padding, masks.boxes)
        return self._forward_images(shape_crops(crops, self.crop_mode, self.fill))

    def encode_text(self, texts: list[str]) -> Annotated[np.ndarray, "(N, D) float32"]:
        feats = []
        for chunk in batched([str(t) for t in texts], TEXT_BATCH):
            tokens = self.tokenizer(list(chunk)).numpy().astype(np.int64)
            feats.append(self.text_session.run(None, {"tokens": tokens})[0])
        if not feats:
            return np.zeros((0, self.dim), np.float32)
        return unit_rows(np.concatenate(feats))



def export_clip_onnx(arch: str, weights: str | Path, out_dir: str | Path, opset: int | None = None) -> Path:
    """Export the image and text towers of ``arch`` (weights loaded from the local
    ``weights`` as the ``openclip`` backend loads them) to ``out_dir``; returns the folder."""
    import torch

    from shared.perception.encoders.openclip import embed_dim, load_openclip

    model, _, tokenizer, path = load_openclip(arch, weights, "cpu")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pp = model.visual.preprocess_cfg
    size = pp["size"] if isinstance(pp["size"], (tuple, list)) else (pp["size"], pp["size"])
    context_length = int(getattr(model, "context_length", 77))
    resize_mode = str(pp.get("resize_mode", "shortest"))
    if resize_mode not in ("shortest", "squash") or (resize_mode == "shortest" and size[0] != size[1]):
        raise ValueError(f"{arch}: resize mode {resize_mode!r} at size {size} has no numpy preprocessing here")

    class Tower(torch.nn.Module):
        """One of the model's towers (its ``encode_image`` or ``encode_text``) as the module
        the exporter traces; its one input is the batch (``dynamic_shapes`` names it by position)."""

        def __init__(self, m: torch.nn.Module, encode: str) -> None:
            super().__init__()
            self.m = m
            self.encode = encode

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return getattr(self.m, self.encode)(x)

    batch = torch.export.Dim("batch", min=1, max=4096)
    pixels = torch.zeros(2, 3, int(size[0]), int(size[1]))
    tokens = tokenizer(["a photo of a chair", "a lamp"]).to(torch.int64)
    t0 = time.perf_counter()
    with torch.no_grad():
        torch.onnx.export(
            Tower(model, "encode_image").eval(), (pixels,), str(out / ONNX_IMAGE), input_names=["pixels"],
            output_names=["features"], dynamic_shapes=({0: batch},), opset_version=opset,
            dynamo=True, verbose=False,
        )  # fmt: skip
        torch.onnx.export(
            Tower(model, "encode_text").eval(), (tokens,), str(out / ONNX_TEXT), input_names=["tokens"],
            output_names=["features"], dynamic_shapes=({0: batch},), opset_version=opset,
            dynamo=True, verbose=False,
        )  # fmt: skip
    meta = {
        "format": META_FORMAT,
        "arch": arch,
        "image_size": [int(size[0]), int(size[1])],
        "mean": [float(v) for v in pp["mean"]],
        "std": [float(v) for v in pp["std"]],
        "interpolation": str(pp.get("interpolation", "bicubic")),
        "resize_mode": resize_mode,
        "dim": embed_dim(arch),
        "context_length": context_length,
        "source": path.name,
    }
    (out / ONNX_META).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    log.info("exported CLIP %s towers to %s in %.1f s", arch, out, time.perf_counter() - t0)
    return out
