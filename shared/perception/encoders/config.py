"""What every VL encoder backend's config shares, and the registry that names them.

Each backend's config lives beside its code (``clip_config.py`` for ``openclip`` and
``clip_onnx``, ``simulated_config.py``) and registers itself in ``VL_ENCODERS`` when imported;
the registry imports those modules by name the first time a backend is looked up. None of them
imports torch, open_clip or onnxruntime: ``build`` does, when the encoder is made.
"""

from __future__ import annotations

from abc import abstractmethod

from shared.config.backends import BackendConfig, backend_config, backend_section
from shared.registry import Registry

VL_ENCODERS: Registry[type[VLEncoderBackend]] = Registry(
    "VL encoder backend",
    modules=("shared.perception.encoders.clip_config", "shared.perception.encoders.simulated_config"),
)
"""Vision-language encoder backends (``keyframe_vl.vl.backend``)."""


class VLEncoderBackend(BackendConfig):
    """What every vision-language encoder (CLIP in the paper) is asked for."""

    @abstractmethod
    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        """The :class:`~shared.perception.VLEncoder` this config describes. ``device`` is
        ``cpu``, ``cuda`` (or ``cuda:N``) or ``auto``; ``fp16`` says whether a ``precision:
        auto`` may be half precision on CUDA (shared/devices.py); ``ground_truth`` (an
        :class:`~shared.datasets.ground_truth.InstanceSource`) stands in for a simulated
        backend's sequence folder (tests)."""


VLSection, vl_default = backend_section(VL_ENCODERS, VLEncoderBackend, "openclip")
"""``keyframe_vl.vl``: the fields of the backend its ``backend`` key names."""


def vl_config(**fields) -> VLEncoderBackend:
    """A ``keyframe_vl.vl`` section from keyword fields (``backend`` default ``openclip``)."""
    return backend_config(VL_ENCODERS, "openclip", **fields)
