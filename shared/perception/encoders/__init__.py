"""Vision-language encoder backends, behind one factory (docs/architecture.md, "Perception
backends"). Each backend's config is registered in ``VL_ENCODERS`` (:mod:`.config`) from a
module beside its code (:mod:`.clip_config`, :mod:`.simulated_config`):

- ``openclip``: OpenCLIP from a local checkpoint (:mod:`.openclip`);
- ``clip_onnx``: the same towers exported to ONNX, run by onnxruntime (:mod:`.clip_onnx`);
- ``simulated``: ground-truth label mixtures in MiniLM text space (:mod:`.simulated`).

Importing this package imports no torch, open_clip, onnxruntime or sentence-transformers;
each backend imports what it needs when it is made.
"""

from __future__ import annotations

from shared.datasets.ground_truth import InstanceSource
from shared.perception import VLEncoder
from shared.perception.encoders.config import VL_ENCODERS, VLEncoderBackend, vl_config

__all__ = ["VL_ENCODERS", "VLEncoderBackend", "make_vl_encoder", "vl_config"]


def make_vl_encoder(
    cfg: VLEncoderBackend, device: str = "cpu", fp16: bool = True, ground_truth: InstanceSource | None = None
) -> VLEncoder:
    """The encoder ``cfg`` describes (``cfg.build``, registered in ``VL_ENCODERS``).

    ``device`` is ``cpu``, ``cuda`` (or ``cuda:N``) or ``auto``. The ``openclip`` backend runs
    in ``cfg.precision``; ``fp16`` says whether its ``auto`` may be half precision on CUDA
    (shared/devices.py). Missing weights raise
    FileNotFoundError naming the path and where to get them; ``simulated`` without usable
    ground truth raises FileNotFoundError or ValueError naming the file or the config field.
    ``ground_truth`` gives the ``simulated`` backend its instance ids instead of the sequence
    folder of ``cfg.ground_truth`` (tests); the other backends need none.
    """
    return cfg.build(device=device, fp16=fp16, ground_truth=ground_truth)
