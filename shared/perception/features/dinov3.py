"""DINOv3 ViT-S+/16 dense features from local weights (paper III-B, IV-A).

Three weight layouts load into the same features:

* ``transformers``: a folder written by ``save_pretrained`` (``config.json`` plus
  ``model.safetensors``), e.g. https://huggingface.co/facebook/dinov3-vits16plus-pretrain-lvd1689m
  downloaded by the user; loaded with ``DINOv3ViTModel.from_pretrained(folder,
  local_files_only=True)``.
* ``timm``: a state dict with timm's key names (``.safetensors``, ``.pth`` or ``.bin``, or a folder
  holding ``model.safetensors``), e.g. https://huggingface.co/timm/vit_small_plus_patch16_dinov3.lvd1689m;
  built as ``timm.create_model("vit_small_plus_patch16_dinov3", pretrained=False)``.
* ``hub``: the official checkpoint ``dinov3_vits16plus_pretrain_lvd1689m-*.pth`` that
  ``torch.hub.load("facebookresearch/dinov3", "dinov3_vits16plus", weights=...)`` reads (from
  https://github.com/facebookresearch/dinov3, after accepting its license). Its keys are mapped
  onto the timm model by timm's own ``eva.checkpoint_filter_fn``: ``storage_tokens`` ->
  ``reg_token``, ``blocks.i.ls{1,2}.gamma`` -> ``gamma_{1,2}``, ``mlp.w1/w2/w3`` ->
  ``mlp.fc1_g/fc1_x/fc2``, ``attn.qkv.bias`` -> ``attn.q_bias``/``attn.v_bias`` (the key bias is
  masked to zero upstream, so it is dropped), and ``rope_embed.periods``, ``mask_token`` and
  ``*.bias_mask`` are discarded (recomputed or training-only). No DINOv3 source code is needed.

All three give the same patch tokens for the same weights (tests check it to 1e-4): taken
after the final LayerNorm, without the CLS token and the 4 register tokens, reshaped to the
patch grid and L2-normalised per patch.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from shared.checkpoints import key_report
from shared.perception.features.base import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    PatchGridMixin,
)

log = logging.getLogger(__name__)

Loader = Literal["transformers", "timm", "hub"]

TIMM_VARIANT = "vit_small_plus_patch16_dinov3"
TIMM_VARIANT_QKV_BIAS = "vit_small_plus_patch16_dinov3_qkvb"

WHERE = {
    "transformers": "a folder with config.json and model.safetensors, e.g. "
    "https://huggingface.co/facebook/dinov3-vits16plus-pretrain-lvd1689m (gated: accept the "
    "DINOv3 license, then download the folder)",
    "timm": "model.safetensors from https://huggingface.co/timm/vit_small_plus_patch16_dinov3.lvd1689m",
    "hub": "dinov3_vits16plus_pretrain_lvd1689m-4057cbaa.pth, linked from "
    "https://github.com/facebookresearch/dinov3 after accepting its license",
}


def missing_weights(loader: str, path: Path, detail: str = "") -> FileNotFoundError:
    extra = f" ({detail})" if detail else ""
    return FileNotFoundError(
        f"DINOv3 ViT-S+/16 weights for loader '{loader}' not found at {path}{extra}. "
        f"Weights are never downloaded; put {WHERE[loader]} there, or set "
        f"tracker.features.weights, or use tracker.features.backend: classical."
    )


class PatchTokens(nn.Module):
    """Backbone wrapper: pixels (1, 3, H, W) -> final-norm patch tokens (1, H/16 * W/16, D).

    One interface over the transformers and timm models, used by the torch backend and by the
    ONNX export alike so the two cannot drift apart.
    """

    def __init__(self, backbone: nn.Module, kind: Literal["transformers", "timm"], num_prefix: int, dim: int, patch_size: int):
        super().__init__()
        self.backbone = backbone
        self.kind = kind
        self.num_prefix = num_prefix
        self.dim = dim
        self.patch_size = patch_size

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        if self.kind == "transformers":
            tokens = self.backbone(pixel_values=pixels).last_hidden_state
        else:
            tokens = self.backbone.forward_features(pixels)
        return tokens[:, self.num_prefix :]


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path), device="cpu")
    obj = torch.load(str(path), map_location="cpu", weights_only=True)
    # Training checkpoints nest the weights; the released files are flat.
    for key in ("model_ema", "teacher", "model", "state_dict"):
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
    if not isinstance(obj, dict):
        raise ValueError(f"{path} does not hold a state dict (got {type(obj).__name__})")
    return obj


def _resolve_file(loader: str, path: Path, names: tuple[str, ...], pattern: str) -> Path:
    if path.is_file():
        return path
    if path.is_dir():
        for name in names:
            if (path / name).is_file():
                return path / name
        found = sorted(path.glob(pattern))
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise ValueError(f"{path} holds several {pattern} files ({[p.name for p in found]}); point weights at one")
        raise missing_weights(loader, path, f"no {' / '.join(names)} or {pattern} inside")
    raise missing_weights(loader, path)


def foreign_weights(loader: str, source: str | Path, report: str) -> ValueError:
    return ValueError(
        f"{source} is not a DINOv3 ViT-S+/16 checkpoint ({loader} layout): {report}. "
        f"Put {WHERE[loader]} there, or point tracker.features.weights at it."
    )


def timm_from_state_dict(state_dict: dict[str, torch.Tensor], source: str, loader: str = "timm") -> nn.Module:
    """Builds timm's ViT-S+/16 DINOv3 and loads timm- or hub-format weights into it.

    Any missing, unexpected or wrongly shaped key refuses the file (ValueError naming
    ``source``): timm would otherwise leave those weights at their random init."""
    import timm
    from timm.models.eva import checkpoint_filter_fn

    # The released S+ has zero q/v biases and timm ships it without them; a checkpoint that
    # carries them (hub format, or timm's _qkvb export) gets the variant that has the slots.
    has_bias = any(k.endswith(("attn.qkv.bias", "attn.q_bias")) for k in state_dict)
    variant = TIMM_VARIANT_QKV_BIAS if has_bias else TIMM_VARIANT
    model = timm.create_model(variant, pretrained=False, num_classes=0)
    mapped = checkpoint_filter_fn(state_dict, model)
    mapped = {k: v for k, v in mapped.items() if not k.startswith(("head.", "fc_norm."))}
    shapes = {k: tuple(v.shape) for k, v in mapped.items()}
    # The filter resamples a patch embedding of another patch size to 16x16 without a word:
    # judge that key by the shape the file holds, so a ViT-*/14 is refused, not resized.
    raw_patch = state_dict.get("patch_embed.proj.weight")
    if raw_patch is not None and "patch_embed.proj.weight" in shapes:
        shapes["patch_embed.proj.weight"] = tuple(raw_patch.shape)
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    missing = [k for k in expected if k not in shapes]
    unexpected = [k for k in shapes if k not in expected]
    mismatched = [(k, shapes[k], expected[k]) for k in expected if k in shapes and shapes[k] != expected[k]]
    if missing or unexpected or mismatched:
        raise foreign_weights(loader, source, key_report(missing, unexpected, mismatched))
    try:
        model.load_state_dict(mapped)
    except RuntimeError as exc:  # keys and shapes agree, so only a dtype or storage problem is left
        raise ValueError(f"{source}: DINOv3 ViT-S+/16 weights that do not load: {exc}") from exc
    return model.eval()


HF_ARCH = {
    "hidden_size": 384,
    "patch_size": 16,
    "num_register_tokens": 4,
    "num_hidden_layers": 12,
    "num_attention_heads": 6,
    "intermediate_size": 1536,
    "use_gated_mlp": True,
}
"""The architecture in facebook/dinov3-vits16plus-pretrain-lvd1689m's config.json. The
SwiGLU MLP is what tells S+ from ViT-S/16, which has the same width."""

HF_WEIGHT_FILES = ("model.safetensors", "model.safetensors.index.json", "pytorch_model.bin", "pytorch_model.bin.index.json")


def _load_transformers(path: Path) -> PatchTokens:
    """A ``save_pretrained`` folder of exactly ViT-S+/16: its config is checked before the
    weights are read, and transformers' loading report afterwards."""
    import json

    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    config_file = path / "config.json"
    if not config_file.is_file():
        raise missing_weights("transformers", path, "no config.json")
    if not any((path / name).is_file() for name in HF_WEIGHT_FILES):
        raise missing_weights("transformers", path, f"no {' / '.join(HF_WEIGHT_FILES[::2])}")
    try:
        model_type = json.loads(config_file.read_text()).get("model_type")
    except (OSError, ValueError, AttributeError) as exc:
        raise ValueError(f"{config_file} is not a transformers config (a JSON object): {exc}") from exc
    if model_type != "dinov3_vit":
        raise ValueError(
            f"{config_file} describes a {model_type!r} model, not DINOv3 ViT-S+/16 (model_type 'dinov3_vit'). "
            f"Put {WHERE['transformers']} there."
        )
    cfg = DINOv3ViTConfig.from_pretrained(str(path), local_files_only=True)
    found = {key: getattr(cfg, key, None) for key in HF_ARCH}
    if isinstance(found["patch_size"], (list, tuple)):
        found["patch_size"] = int(found["patch_size"][0])
    wrong = [f"{key} {found[key]!r} (expected {want!r})" for key, want in HF_ARCH.items() if found[key] != want]
    if wrong:
        raise ValueError(
            f"{config_file} describes a DINOv3 ViT other than ViT-S+/16: {', '.join(wrong)}. "
            f"Put {WHERE['transformers']} there."
        )
    # from_pretrained gives every key the file lacks a random init and only logs it, so a
    # folder holding another model's weights would "load". Its report is checked instead;
    # ignore_mismatched_sizes puts wrong shapes into that report too, where transformers
    # would otherwise raise a RuntimeError that only points at its logged table.
    model, info = DINOv3ViTModel.from_pretrained(
        str(path), config=cfg, local_files_only=True, output_loading_info=True, ignore_mismatched_sizes=True
    )
    errors = list(info.get("error_msgs") or [])
    report = key_report(info.get("missing_keys") or set(), info.get("unexpected_keys") or set(), info.get("mismatched_keys") or set())
    if errors:
        report = "; ".join(filter(None, [report, f"errors: {' | '.join(errors[:3])}"]))
    if report:
        raise foreign_weights("transformers", path, report)
    return PatchTokens(model.eval(), "transformers", 1 + cfg.num_register_tokens, cfg.hidden_size, HF_ARCH["patch_size"])


def load_patch_tokens(loader: Loader, weights: str | Path) -> PatchTokens:
    """The ViT-S+/16 backbone from local files, on CPU in float32, in eval mode."""
    path = Path(weights).expanduser().resolve()  # errors name the absolute path that was read
    if loader == "transformers":
        wrapped = _load_transformers(path)
    elif loader in ("timm", "hub"):
        if loader == "timm":
            file = _resolve_file(loader, path, ("model.safetensors", "pytorch_model.bin"), "*.safetensors")
        else:
            file = _resolve_file(loader, path, (), "dinov3_vits16plus*.pth")
        state = _read_state_dict(file)
        if loader == "hub" and "storage_tokens" not in state:
            raise ValueError(f"{file} is not an official DINOv3 checkpoint (no storage_tokens); use loader: timm")
        model = timm_from_state_dict(state, str(file), loader)
        wrapped = PatchTokens(model, "timm", model.num_prefix_tokens, model.embed_dim, model.patch_embed.patch_size[0])
    else:
        raise ValueError(f"unknown DINOv3 loader {loader!r}")
    log.info("DINOv3 %s backbone loaded from %s (%d prefix tokens, dim %d)", loader, path, wrapped.num_prefix, wrapped.dim)
    return wrapped


def preprocess(
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"],
    size: tuple[int, int],
    device: torch.device | str = "cpu",
) -> Annotated[torch.Tensor, "(1, 3, H', W') float32, ImageNet-normalised"]:
    """Resize (bilinear, antialiased when shrinking) and normalise one frame for the ViT."""
    return preprocess_tensor(torch.from_numpy(np.ascontiguousarray(rgb)).to(device), size)


def preprocess_tensor(
    rgb: Annotated[torch.Tensor, "(H, W, 3) uint8"], size: tuple[int, int]
) -> Annotated[torch.Tensor, "(1, 3, H', W') float32, ImageNet-normalised"]:
    """``preprocess`` of a frame already on its device."""
    x = rgb.permute(2, 0, 1)[None].float().div_(255.0)
    if tuple(x.shape[-2:]) != tuple(size):
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
    mean = torch.tensor(IMAGENET_MEAN, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std


def tokens_to_grid(tokens: torch.Tensor, h: int, w: int) -> Annotated[torch.Tensor, "(h, w, D) float32 unit"]:
    if tokens.shape[0] != h * w:
        raise RuntimeError(f"backbone returned {tokens.shape[0]} patch tokens for a {h}x{w} grid")
    return F.normalize(tokens.float().reshape(h, w, -1), dim=-1)


class Dinov3Features(PatchGridMixin):
    """DINOv3 ViT-S+/16 patch features (torch) in fp32, or fp16 / bf16 under autocast."""

    name = "dinov3"

    def __init__(self, model: PatchTokens, short_side: int, device: str | torch.device = "cpu", precision: str = "fp32"):
        from shared.devices import PRECISIONS

        if precision not in PRECISIONS:
            raise ValueError(f"DINOv3 precision {precision!r}: expected one of {', '.join(PRECISIONS)}")
        self.device = torch.device(device)
        self.patch_size = model.patch_size
        self.dim = model.dim
        self.appearance_dims = model.dim
        self.short_side = short_side
        self.precision = precision
        # fp32 weights under autocast, not a half model: the final LayerNorm and the per-patch
        # normalisation keep full precision, and the matmuls take the fast path.
        self.model = model.to(self.device).eval()
        self._pinned: torch.Tensor | None = None
        self._copied: torch.cuda.Event | None = None

    def _upload(self, rgb: np.ndarray) -> torch.Tensor:
        """The frame on the device, through one reused pinned buffer on CUDA (one
        asynchronous copy a frame, no pageable staging)."""
        if self.device.type != "cuda":
            return torch.from_numpy(np.ascontiguousarray(rgb))
        if self._pinned is None or tuple(self._pinned.shape) != rgb.shape:
            self._pinned = torch.empty(rgb.shape, dtype=torch.uint8, pin_memory=True)
            self._copied = None
        if self._copied is not None:
            self._copied.synchronize()  # the previous frame's copy has left the buffer
        self._pinned.numpy()[...] = rgb
        on_device = self._pinned.to(self.device, non_blocking=True)
        self._copied = torch.cuda.Event()
        self._copied.record()
        return on_device

    @torch.no_grad()
    def features(self, rgb: np.ndarray, depth_m: np.ndarray | None, size: tuple[int, int]) -> torch.Tensor:
        from shared.devices import autocast

        x = preprocess_tensor(self._upload(rgb), size)
        with autocast(str(self.device), self.precision):  # type: ignore[arg-type]
            tokens = self.model(x)[0]
        return tokens_to_grid(tokens, size[0] // self.patch_size, size[1] // self.patch_size)
