"""OpenCLIP crop, image and text features from a local checkpoint (paper III-B, IV-A).

Any built-in OpenCLIP architecture works (ViT-H-14 in the paper, ViT-B-32 onboard). The
model is built by ``open_clip.create_model_and_transforms(arch, pretrained=<file>)``, so a
checkpoint is loaded, converted and checked exactly as OpenCLIP itself does; a tag name is
never passed, so nothing is downloaded. OpenAI checkpoints need the ``-quickgelu`` variant of
the architecture name (e.g. ``ViT-B-32-quickgelu``), as in OpenCLIP.
"""

from __future__ import annotations

import logging
import os
import pickle
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch
from PIL import Image

from shared.checkpoints import key_report
from shared.perception import KeyframeImage, Masks
from shared.perception.encoders.common import ImageTowerMixin, check_rgb, unit_rows
from shared.perception.encoders.crops import (
    CROP_MODES,
    CropMode,
    batched,
    fill_colour,
    padded_boxes,
    padded_crops,
    shape_crops,
    square_offsets,
)
from shared.perception.encoders.weights import (
    is_transformers_clip,
    resolve_checkpoint,
    transformers_clip_hint,
    weights_hint,
)

log = logging.getLogger(__name__)

OPENAI_MEAN = (0.48145466, 0.4578275, 0.40821073)
OPENAI_STD = (0.26862954, 0.26130258, 0.27577711)
"""OpenCLIP's normalisation when a model carries no preprocess config of its own."""

TEXT_BATCH = 256
"""Texts per forward pass: text is cheap next to images, and query lists are short."""


def _import_open_clip():
    # huggingface_hub reads its offline switch when first imported: set it before open_clip
    # imports it, so a tokenizer or config that would need the hub fails at once instead of
    # waiting on a network that is not there.
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    import open_clip

    return open_clip


def check_arch(arch: str) -> dict[str, Any]:
    """The built-in OpenCLIP config of ``arch``; hub and folder schemas are refused because
    they resolve weights and configs by themselves (``hf-hub:`` downloads)."""
    open_clip = _import_open_clip()
    if ":" in arch:
        raise ValueError(
            f"OpenCLIP architecture {arch!r}: give a built-in name (e.g. ViT-H-14) and the weights file separately"
        )
    cfg = open_clip.get_model_config(arch)
    if cfg is None:
        known = ", ".join(open_clip.list_models())
        raise ValueError(f"unknown OpenCLIP architecture {arch!r}; built-in ones: {known}")
    return cfg


def load_openclip(arch: str, weights: str | Path, device: str = "cpu"):
    """``(model, preprocess, tokenizer, checkpoint path)`` for ``arch`` from a local checkpoint
    file (or a downloaded repository folder holding one), the model in eval mode.

    A checkpoint that is not ``arch``'s (another architecture, transformers-format CLIP
    weights, a file that is no checkpoint) raises ValueError naming the file, the
    architecture and the first keys that do not fit."""
    path = resolve_checkpoint(weights, arch)
    check_arch(arch)
    open_clip = _import_open_clip()
    from safetensors import SafetensorError

    t0 = time.perf_counter()
    try:
        model, _, preprocess = open_clip.create_model_and_transforms(arch, pretrained=str(path), device=device)
    except RuntimeError as exc:
        # open_clip loads strictly, so foreign weights end here, as torch's list of every
        # key and shape at fault (thousands of lines for ViT-H): replaced by a short report.
        if "Error(s) in loading state_dict" in str(exc):
            raise foreign_checkpoint(arch, path) or unreadable_checkpoint(arch, path, exc) from exc
        if "PytorchStreamReader" not in str(exc):  # a truncated or non-zip .bin/.pt; else a real failure
            raise
        raise unreadable_checkpoint(arch, path, exc) from exc
    except AssertionError as exc:
        # open_clip asserts while resampling position embeddings of another width ("text
        # pos_embed width changed!"): a foreign checkpoint too, if its keys say so.
        refusal = foreign_checkpoint(arch, path)
        if refusal is None:
            raise
        raise refusal from exc
    except (pickle.UnpicklingError, EOFError, SafetensorError) as exc:
        raise unreadable_checkpoint(arch, path, exc) from exc
    model.eval()
    tokenizer = open_clip.get_tokenizer(arch)
    log.info("OpenCLIP %s loaded from %s on %s in %.1f s", arch, path, device, time.perf_counter() - t0)
    return model, preprocess, tokenizer, path


def unreadable_checkpoint(arch: str, path: Path, exc: Exception) -> ValueError:
    text = str(exc).strip()
    reason = (text.splitlines() or [""])[0]
    if "Weights only load failed" in text:
        # torch's refusal opens with advice to set weights_only=False, which is no advice for
        # a file that is not a checkpoint; its reason comes after "WeightsUnpickler error:".
        detail = text.partition("WeightsUnpickler error:")[2].strip().splitlines()
        reason = "torch's weights-only loader refused it" + (f": {detail[0]}" if detail else "")
    return ValueError(
        f"{path} is not a readable checkpoint for OpenCLIP {arch} ({type(exc).__name__}: {reason}); {weights_hint(arch)}"
    )


def foreign_checkpoint(arch: str, path: Path, first: int = 5) -> ValueError | None:
    """The refusal of a checkpoint that open_clip could not load into ``arch``: which keys
    are missing, unexpected or of the wrong shape, compared the way open_clip loads it; None
    when they all fit (the failure was something else)."""
    import open_clip.factory as factory
    from open_clip.model import convert_to_custom_text_state_dict

    state = factory.load_state_dict(str(path))
    if is_transformers_clip(state):
        return ValueError(f"{path} is not an OpenCLIP checkpoint for {arch}: {transformers_clip_hint(arch)}")
    # The expected shapes, from a model on the meta device: no memory, no init time even for
    # ViT-H. open_clip logs that this one has no weights, which would only mislead here.
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        model = _import_open_clip().create_model(arch, pretrained=None, device="meta")
    finally:
        logging.disable(previous)
    state = factory.convert_state_dict(model, state)
    if "positional_embedding" in state and not hasattr(model, "positional_embedding"):
        state = convert_to_custom_text_state_dict(state)
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in state.items() if hasattr(v, "shape")}
    # What open_clip adapts by itself is no fault: it resamples position embeddings to the
    # model's length, reshapes logit_scale / logit_bias, and adds a missing logit_bias.
    resized = ("visual.positional_embedding", "positional_embedding", "text.positional_embedding")
    adapted = ("logit_scale", "logit_bias")

    def fits(key: str) -> bool:
        a, b = found[key], expected[key]
        if key in resized:
            return a[1:] == b[1:]
        if key in adapted:
            return int(np.prod(a)) == int(np.prod(b))
        return a == b

    missing = [k for k in expected if k not in found and k != "logit_bias"]
    unexpected = [k for k in found if k not in expected]
    mismatched = [(k, found[k], expected[k]) for k in expected if k in found and not fits(k)]
    report = key_report(missing, unexpected, mismatched, first)
    if not report:
        return None
    return ValueError(
        f"{path} is not an OpenCLIP {arch} checkpoint: {report}. "
        f"Give keyframe_vl.vl.model the architecture the file was trained as, or {weights_hint(arch)}"
    )


def embed_dim(arch: str) -> int:
    return int(check_arch(arch)["embed_dim"])


class OpenClipEncoder(ImageTowerMixin):
    """The ``openclip`` VL backend: L2-normalised float32 features of dimension ``dim``.

    Crops go through one of two equal paths: on a CPU, PIL and OpenCLIP's own transform; on a
    GPU (or with ``tensor_crops``), the frame is uploaded once and every crop is cut, squared,
    resized (antialiased bicubic, as PIL) and normalised on the device as one batch.
    """

    def __init__(
        self,
        arch: str,
        weights: str | Path,
        device: str = "cpu",
        precision: str = "fp32",
        crop_padding: float = 0.1,
        batch_size: int = 16,
        crop_mode: CropMode = "pad_square",
        tensor_crops: bool | None = None,
    ) -> None:
        from shared.devices import PRECISIONS

        if precision not in PRECISIONS:
            raise ValueError(f"OpenCLIP precision {precision!r}: expected one of {', '.join(PRECISIONS)}")
        if crop_mode not in CROP_MODES:
            raise ValueError(f"crop mode {crop_mode!r}: expected one of {', '.join(CROP_MODES)}")
        self.arch = arch
        self.name = f"openclip:{arch}"
        self.device = torch.device(device)
        self.precision = precision
        self.crop_padding = float(crop_padding)
        self.batch_size = int(batch_size)
        self.crop_mode: CropMode = crop_mode
        self.tensor_crops = self.device.type == "cuda" if tensor_crops is None else bool(tensor_crops)
        self.model, self.preprocess, self.tokenizer, self.weights = load_openclip(arch, weights, str(self.device))
        self.dim = embed_dim(arch)
        pp = getattr(self.model.visual, "preprocess_cfg", None) or {}
        size = pp.get("size", getattr(self.model.visual, "image_size", 224))
        self.size = (int(size), int(size)) if isinstance(size, int) else tuple(int(v) for v in size)
        self.mean = tuple(float(v) for v in pp.get("mean", OPENAI_MEAN))
        self.std = tuple(float(v) for v in pp.get("std", OPENAI_STD))
        self.interpolation = str(pp.get("interpolation", "bicubic"))
        self.fill = fill_colour(self.mean)

    def _autocast(self):
        from shared.devices import autocast

        return autocast(str(self.device), self.precision)  # type: ignore[arg-type]

    def _encode_pixels(self, x: torch.Tensor) -> np.ndarray:
        with torch.inference_mode(), self._autocast():
            f = self.model.encode_image(x.to(self.device, non_blocking=True))
        return f.float().cpu().numpy()

    def _forward_images(self, images: Sequence[np.ndarray]) -> Annotated[np.ndarray, "(N, D) float32"]:
        feats = []
        for chunk in batched(images, self.batch_size):
            feats.append(self._encode_pixels(torch.stack([self.preprocess(Image.fromarray(im)) for im in chunk])))
        if not feats:
            return np.zeros((0, self.dim), np.float32)
        return unit_rows(np.concatenate(feats))

    def crop_pixels(
        self, rgb: Annotated[np.ndarray, "(H, W, 3) uint8"], boxes: Annotated[np.ndarray, "(N, 4) int x0, y0, x1, y1"]
    ) -> Annotated[torch.Tensor, "(N, 3, S, S) float32, normalised, on the device"]:
        """The device path's CLIP input for each box of ``rgb``."""
        import torch.nn.functional as F

        frame = torch.from_numpy(np.ascontiguousarray(rgb))
        if self.device.type == "cuda":
            frame = frame.pin_memory()
        frame = frame.to(self.device, non_blocking=True).permute(2, 0, 1).float()
        mode = "bilinear" if self.interpolation == "bilinear" else "bicubic"
        size_h, size_w = self.size
        fill = torch.tensor(self.fill, dtype=torch.float32, device=self.device).view(3, 1, 1)
        out = []
        for x0, y0, x1, y1 in boxes.tolist():
            crop = frame[:, y0:y1, x0:x1]
            h, w = crop.shape[1:]
            if self.crop_mode == "pad_square" and h != w:
                side, top, left = square_offsets(h, w)
                square = fill.expand(3, side, side).clone()
                square[:, top : top + h, left : left + w] = crop
                crop, h, w = square, side, side
            # OpenCLIP's "shortest" resize, then its centre crop (a no-op on a square).
            new_h, new_w = (size_h, int(size_h * w / h)) if h <= w else (int(size_h * h / w), size_h)
            if (new_h, new_w) != (h, w):
                # antialias=True also when enlarging: torch's antialiased kernels are PIL's
                # (bicubic a = -0.5), its plain bicubic is not (a = -0.75).
                crop = F.interpolate(crop[None], size=(new_h, new_w), mode=mode, align_corners=False, antialias=True)[0]
            top, left = int(round((new_h - size_h) / 2.0)), int(round((new_w - size_w) / 2.0))
            out.append(crop[:, top : top + size_h, left : left + size_w])
        x = torch.stack(out).clamp_(0, 255).round_().div_(255.0)
        mean = torch.tensor(self.mean, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(self.std, device=self.device).view(1, 3, 1, 1)
        return (x - mean) / std

    def encode_crops(self, image: KeyframeImage, masks: Masks) -> Annotated[np.ndarray, "(N, D) float32"]:
        """One feature per mask, from its padded bounding-box crop, ``batch_size`` crops a pass."""
        rgb = check_rgb(image.rgb)
        if len(masks) == 0:
            return np.zeros((0, self.dim), np.float32)
        if not self.tensor_crops:
            crops = shape_crops(padded_crops(rgb, masks.masks, self.crop_padding, masks.boxes), self.crop_mode, self.fill)
            return self._forward_images(crops)
        boxes = padded_boxes(masks.masks, masks.boxes, self.crop_padding)
        feats = [self._encode_pixels(self.crop_pixels(rgb, chunk)) for chunk in batched(boxes, self.batch_size)]
        return unit_rows(np.concatenate(feats))

    def encode_text(self, texts: list[str]) -> Annotated[np.ndarray, "(N, D) float32"]:
        texts = [str(t) for t in texts]
        feats = []
        for chunk in batched(texts, TEXT_BATCH):
            tokens = self.tokenizer(list(chunk)).to(self.device)
            with torch.inference_mode(), self._autocast():
                f = self.model.encode_text(tokens)
            feats.append(f.float().cpu().numpy())
        if not feats:
            return np.zeros((0, self.dim), np.float32)
        return unit_rows(np.concatenate(feats))
