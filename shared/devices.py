"""Torch devices and numeric precisions of the learned models, resolved in one place.

A config names a device (``auto``, ``cpu``, ``cuda`` or ``cuda:N``) and, per model, a
precision (``auto``, ``fp32``, ``fp16`` or ``bf16``). This module turns them into what runs,
with an error naming the setting when the machine cannot honour it. torch is imported only
inside the functions that need it, so configs and light services can import this freely.
"""

from __future__ import annotations

import logging
import re
from typing import Literal

log = logging.getLogger(__name__)

DEVICE_PATTERN = r"^(auto|cpu|cuda(:[0-9]+)?)$"
"""What a ``device`` config field accepts."""

Resolved = Literal["fp32", "fp16", "bf16"]

PRECISIONS: tuple[Resolved, ...] = ("fp32", "fp16", "bf16")


def resolve_device(device: str, what: str = "device") -> str:
    """``auto`` -> ``cuda`` when torch sees a GPU, else ``cpu``; ``cuda``/``cuda:N`` are
    checked against the GPUs torch sees, and refused with the count when absent."""
    if not re.match(DEVICE_PATTERN, device):
        raise ValueError(f"{what} {device!r}: expected auto, cpu, cuda or cuda:N")
    if device == "cpu":
        return device
    try:
        import torch
    except ImportError:
        # A base-station install without torch (simulated or remote perception): auto is
        # the CPU, and a GPU cannot be asked for.
        if device == "auto":
            return "cpu"
        raise ValueError(f"{what} {device!r}: torch is not installed here; use cpu or auto") from None

    available = torch.cuda.is_available()
    if device == "auto":
        return "cuda" if available else "cpu"
    if not available:
        raise ValueError(
            f"{what} {device!r}: torch {torch.__version__} sees no CUDA GPU here "
            "(a CPU build of torch, or no driver); use cpu or auto"
        )
    index = int(device.split(":")[1]) if ":" in device else 0
    count = torch.cuda.device_count()
    if index >= count:
        raise ValueError(f"{what} {device!r}: torch sees {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return device


def device_type(device: str) -> str:
    """``cuda:1`` -> ``cuda``: what ``torch.autocast`` and provider choices take."""
    return device.split(":")[0]


def device_index(device: str) -> int:
    """The GPU index of ``cuda``/``cuda:N`` (0 for plain ``cuda``)."""
    return int(device.split(":")[1]) if ":" in device else 0


def resolve_precision(precision: str, device: str, half_default: bool = True) -> Resolved:
    """The precision a model runs in on the resolved ``device``.

    ``auto`` is fp16 on CUDA when ``half_default`` (tensor cores double the rate and CLIP,
    DINOv3 and FastSAM keep their rankings in half precision), else fp32: on a CPU half
    precision is emulated and slower than fp32. An explicit choice is kept as given.
    """
    if precision == "auto":
        return "fp16" if half_default and device_type(device) == "cuda" else "fp32"
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: expected auto, fp32, fp16 or bf16")
    return precision  # type: ignore[return-value]


def onnx_providers(device: str, what: str = "device") -> list:
    """onnxruntime execution providers for ``device``: CUDA on GPU ``N`` (``device_id``) with
    the CPU behind it when onnxruntime has CUDA, else the CPU with a warning."""
    import onnxruntime as ort

    if device_type(device) == "cpu":
        return ["CPUExecutionProvider"]
    available = ort.get_available_providers()
    if "CUDAExecutionProvider" in available:
        return [("CUDAExecutionProvider", {"device_id": device_index(device)}), "CPUExecutionProvider"]
    if device != "auto":
        log.warning("%s %s asked for, but onnxruntime has no CUDA provider (has %s): running on CPU", what, device, available)
    return ["CPUExecutionProvider"]


def torch_dtype(precision: Resolved):
    """The torch dtype of a resolved precision (imports torch)."""
    import torch

    return {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}[precision]


def autocast(device: str, precision: Resolved):
    """A ``torch.autocast`` context for ``precision`` on ``device``; a no-op one for fp32.

    Autocast rather than a model cast: the weights stay fp32, so layer norms and the final
    normalisation keep full precision and the same model object serves every precision."""
    import torch

    if precision == "fp32":
        return torch.autocast(device_type(device), enabled=False)
    if precision == "fp16" and device_type(device) == "cpu" and _older(torch.__version__, (2, 5)):
        # Older CPU autocast warns and runs fp32 instead: refuse rather than mislabel a run.
        raise ValueError(f"fp16 on the CPU needs torch 2.5 or newer (this is {torch.__version__}); use bf16 or fp32")
    return torch.autocast(device_type(device), dtype=torch_dtype(precision))


def _older(version: str, than: tuple[int, int]) -> bool:
    parts = re.findall(r"\d+", version)[:2]
    return tuple(int(p) for p in parts) < than
