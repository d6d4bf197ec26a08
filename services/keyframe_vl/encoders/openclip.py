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
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch
from PIL import Image

from services.keyframe_vl.crops import batched, padded_crops
from services.keyframe_vl.encoders.common import check_rgb, unit_rows
from services.keyframe_vl.encoders.weights import resolve_checkpoint
from shared.perception import KeyframeImage, Masks

log = logging.getLogger(__name__)

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
    file (or a downloaded repository folder holding one), the model in eval mode."""
    path = resolve_checkpoint(weights, arch)
    check_arch(arch)
    open_clip = _import_open_clip()
    t0 = time.perf_counter()
    model, _, preprocess = open_clip.create_model_and_transforms(arch, pretrained=str(path), device=device)
    model.eval()
    tokenizer = open_clip.get_tokenizer(arch)
    log.info("OpenCLIP %s loaded from %s on %s in %.1f s", arch, path, device, time.perf_counter() - t0)
    return model, preprocess, tokenizer, path


def embed_dim(arch: str) -> int:
    return int(check_arch(arch)["embed_dim"])


class OpenClipEncoder:
    """The ``openclip`` VL backend: L2-normalised float32 features of dimension ``dim``."""

    def __init__(
        self,
        arch: str,
        weights: str | Path,
        device: str = "cpu",
        fp16: bool = False,
        crop_padding: float = 0.1,
        batch_size: int = 16,
    ) -> None:
        self.arch = arch
        self.name = f"openclip:{arch}"
        self.device = torch.device(device)
        self.crop_padding = float(crop_padding)
        self.batch_size = int(batch_size)
        # Autocast rather than a half model: the weights stay fp32, so the same encoder can
        # fall back to fp32 and the normalisation stays exact.
        self.autocast = bool(fp16) and self.device.type == "cuda"
        self.model, self.preprocess, self.tokenizer, self.weights = load_openclip(arch, weights, str(self.device))
        self.dim = embed_dim(arch)

    def _forward_images(self, images: Sequence[np.ndarray]) -> Annotated[np.ndarray, "(N, D) float32"]:
        feats = []
        for chunk in batched(images, self.batch_size):
            x = torch.stack([self.preprocess(Image.fromarray(im)) for im in chunk]).to(self.device)
            with torch.inference_mode(), torch.autocast("cuda", dtype=torch.float16, enabled=self.autocast):
                f = self.model.encode_image(x)
            feats.append(f.float().cpu().numpy())
        if not feats:
            return np.zeros((0, self.dim), np.float32)
        return unit_rows(np.concatenate(feats))

    def encode_crops(self, image: KeyframeImage, masks: Masks) -> Annotated[np.ndarray, "(N, D) float32"]:
        """One feature per mask, from its padded bounding-box crop, ``batch_size`` crops a pass."""
        rgb = check_rgb(image.rgb)
        if len(masks) == 0:
            return np.zeros((0, self.dim), np.float32)
        crops = padded_crops(rgb, masks.masks, self.crop_padding, masks.boxes)
        return self._forward_images(crops)

    def encode_text(self, texts: list[str]) -> Annotated[np.ndarray, "(N, D) float32"]:
        texts = [str(t) for t in texts]
        feats = []
        for chunk in batched(texts, TEXT_BATCH):
            tokens = self.tokenizer(list(chunk)).to(self.device)
            with torch.inference_mode(), torch.autocast("cuda", dtype=torch.float16, enabled=self.autocast):
                f = self.model.encode_text(tokens)
            feats.append(f.float().cpu().numpy())
        if not feats:
            return np.zeros((0, self.dim), np.float32)
        return unit_rows(np.concatenate(feats))

    def encode_image(self, rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]) -> Annotated[np.ndarray, "(D,) float32"]:
        """A whole image (an image query)."""
        return self._forward_images([check_rgb(rgb)])[0]
