"""Where the CLIP weights live, and what to tell a user whose file is missing.

Light on purpose (no torch): ``trackgraph models check`` can call it to report what is
present without loading a model.
"""

from __future__ import annotations

from pathlib import Path

CHECKPOINT_NAMES = (
    "open_clip_model.safetensors",
    "open_clip_pytorch_model.safetensors",
    "open_clip_pytorch_model.bin",
    "open_clip_pytorch_model.pth",
    "model.safetensors",
    "pytorch_model.bin",
)
"""File names a Hugging Face OpenCLIP repository folder holds its weights under, preferred first
(open_clip's own order). In the LAION repositories the last two hold the transformers
``CLIPModel`` conversion, which open_clip cannot load; they stay as fallbacks because some
repositories keep open_clip weights under them, and ``load_openclip`` tells the two apart by
their keys (``is_transformers_clip``)."""

TRANSFORMERS_CLIP_PREFIXES = ("vision_model.", "text_model.")
"""Key prefixes of a transformers ``CLIPModel`` state dict; open_clip's are ``visual.``,
``transformer.``, ``token_embedding.`` and the like."""

ONNX_META = "clip_onnx.json"
ONNX_IMAGE = "image.onnx"
ONNX_TEXT = "text.onnx"

SOURCES = {
    "ViT-H-14": "laion/CLIP-ViT-H-14-laion2B-s32B-b79K",
    "ViT-B-32": "laion/CLIP-ViT-B-32-laion2B-s34B-b79K",
    "ViT-B-16": "laion/CLIP-ViT-B-16-laion2B-s34B-b88K",
    "ViT-L-14": "laion/CLIP-ViT-L-14-laion2B-s32B-b82K",
}
"""Hugging Face repositories of the LAION weights of the usual architectures."""


def weights_hint(arch: str) -> str:
    """Where to get a local checkpoint of ``arch``, for error messages."""
    repo = SOURCES.get(arch)
    where = (
        f"download open_clip_pytorch_model.bin (or open_clip_model.safetensors) from the Hugging Face "
        f"repository {repo}"
        if repo
        else f"download an OpenCLIP checkpoint for {arch} (open_clip.list_pretrained() names them; "
        "each lives on the Hugging Face hub)"
    )
    return f"{where} on a machine with internet, copy it here and set keyframe_vl.vl.weights to its path"


def is_transformers_clip(keys) -> bool:
    """Whether state-dict ``keys`` are a transformers ``CLIPModel``'s (``vision_model.*``,
    ``text_model.*``), not OpenCLIP's."""
    return any(str(k).startswith(TRANSFORMERS_CLIP_PREFIXES) for k in keys)


def transformers_clip_hint(arch: str) -> str:
    """What to fetch instead of a transformers-format CLIP checkpoint."""
    repo = SOURCES.get(arch)
    where = f"the same Hugging Face repository ({repo})" if repo else "the same Hugging Face repository"
    return (
        "these are Hugging Face transformers CLIPModel weights (keys vision_model.*, text_model.*), "
        "which open_clip cannot load: it needs open_clip_pytorch_model.bin or "
        f"open_clip_model.safetensors from {where}; set keyframe_vl.vl.weights to that file"
    )


def resolve_checkpoint(weights: str | Path, arch: str) -> Path:
    """The checkpoint file ``weights`` names: the file itself, or the preferred checkpoint
    inside a downloaded repository folder. Raises FileNotFoundError naming the path."""
    path = Path(weights).expanduser()
    if path.is_file():
        return path.resolve()
    if path.is_dir():
        for name in CHECKPOINT_NAMES:
            if (path / name).is_file():
                return (path / name).resolve()
        raise FileNotFoundError(
            f"OpenCLIP weights for {arch}: the folder {path} holds none of {', '.join(CHECKPOINT_NAMES)}; "
            + weights_hint(arch)
        )
    raise FileNotFoundError(f"OpenCLIP weights for {arch} not found: {path}; " + weights_hint(arch))


def resolve_onnx_dir(folder: str | Path) -> Path:
    """The folder ``export_clip_onnx`` wrote. Raises FileNotFoundError naming what is missing."""
    path = Path(folder).expanduser()
    missing = [path / n for n in (ONNX_META, ONNX_IMAGE, ONNX_TEXT) if not (path / n).is_file()]
    if missing:
        raise FileNotFoundError(
            f"CLIP ONNX export not found: {', '.join(str(p) for p in missing)} missing; write it with "
            "shared.perception.encoders.clip_onnx.export_clip_onnx(arch, weights, out_dir) "
            "and set keyframe_vl.vl.weights to that folder"
        )
    return path.resolve()
