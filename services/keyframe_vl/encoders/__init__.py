"""Vision-language encoder backends of keyframe_vl, behind one factory
(docs/architecture.md, "Perception backends").

- ``openclip``: OpenCLIP from a local checkpoint (:mod:`.openclip`);
- ``clip_onnx``: the same towers exported to ONNX, run by onnxruntime (:mod:`.clip_onnx`);
- ``simulated``: ground-truth label mixtures in MiniLM text space (:mod:`.simulated`).

Importing this package imports no torch, open_clip, onnxruntime or sentence-transformers;
each backend imports what it needs when it is made.
"""

from __future__ import annotations

import logging

from shared.config.keyframe_vl import VLEncoderConfig
from shared.datasets.ground_truth import InstanceSource
from shared.perception import VLEncoder

log = logging.getLogger(__name__)

BACKENDS = ("openclip", "clip_onnx", "simulated")

__all__ = ["BACKENDS", "make_vl_encoder"]


def make_vl_encoder(
    cfg: VLEncoderConfig, device: str = "cpu", fp16: bool = True, ground_truth: InstanceSource | None = None
) -> VLEncoder:
    """The encoder ``cfg.backend`` names.

    ``device`` is ``cpu``, ``cuda`` (or ``cuda:N``) or ``auto``. The ``openclip`` backend runs
    in ``cfg.precision``; ``fp16`` says whether its ``auto`` may be half precision on CUDA
    (shared/devices.py). Missing weights raise
    FileNotFoundError naming the path and where to get them; ``simulated`` without usable
    ground truth raises FileNotFoundError or ValueError naming the file or the config field.
    ``ground_truth`` gives the ``simulated`` backend its instance ids instead of the sequence
    folder of ``cfg.ground_truth`` (tests); the other backends need none.
    """
    if cfg.backend in ("openclip", "clip_onnx"):
        from shared.devices import resolve_device

        device = resolve_device(device)
    if cfg.backend == "openclip":
        from services.keyframe_vl.encoders.openclip import OpenClipEncoder
        from shared.devices import resolve_precision

        return OpenClipEncoder(
            cfg.model, cfg.weights, device=device, precision=resolve_precision(cfg.precision, device, fp16),
            crop_padding=cfg.crop_padding, batch_size=cfg.batch_size, crop_mode=cfg.crop_mode,
        )  # fmt: skip
    if cfg.backend == "clip_onnx":
        from services.keyframe_vl.encoders.clip_onnx import ClipOnnxEncoder

        return ClipOnnxEncoder(
            cfg.weights, arch=cfg.model, device=device,
            crop_padding=cfg.crop_padding, batch_size=cfg.batch_size, crop_mode=cfg.crop_mode,
        )  # fmt: skip
    if cfg.backend == "simulated":
        from services.keyframe_vl.encoders.simulated import SimulatedVLEncoder

        # The text encoder stays on the CPU: its embeddings are cached on disk by text, and
        # a crop costs no network pass at all.
        return SimulatedVLEncoder(cfg.ground_truth, noise_std=cfg.noise_std, source=ground_truth)
    raise ValueError(f"unknown VL encoder backend {cfg.backend!r}; choose one of: {', '.join(BACKENDS)}")
