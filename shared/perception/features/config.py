"""What every dense-feature backend's config shares, and the registry that names them.

Each backend's config lives beside its code (``dinov3_config.py`` for ``dinov3`` and
``dinov3_onnx``, ``classical_config.py``) and registers itself in ``DENSE_FEATURES`` when
imported; the registry imports those modules by name the first time a backend is looked up.
None of them imports torch, transformers or onnxruntime: ``build`` does, when the backend is made.
"""

from __future__ import annotations

from abc import abstractmethod

from pydantic import Field

from shared.config.backends import BackendConfig, backend_config, backend_section
from shared.registry import Registry

DENSE_FEATURES: Registry[type[DenseFeaturesBackend]] = Registry(
    "dense-feature backend",
    modules=("shared.perception.features.dinov3_config", "shared.perception.features.classical_config"),
)
"""Dense per-patch feature backends (``tracker.features.backend``)."""


class DenseFeaturesBackend(BackendConfig):
    """Dense per-patch features used to carry mask identity (DINOv3 in the paper): what every
    backend's grid is."""

    short_side: int = Field(720, ge=16)
    """Input resize: short side in pixels, rounded to a multiple of the patch size
    (IV-A: 720, 480 onboard)."""
    patch_size: int = Field(16, ge=1)
    """Patch size of the backbone, and the grid of the classical descriptors."""

    @abstractmethod
    def build(self, device: str = "cpu", fp16: bool = True):
        """The :class:`~shared.perception.features.base.DenseFeatures` this config describes,
        on ``device`` (``cpu``, ``cuda``, ``cuda:N``; resolved by the caller). ``fp16`` says
        whether a ``precision: auto`` may be half precision on CUDA."""


DenseFeaturesSection, features_default = backend_section(DENSE_FEATURES, DenseFeaturesBackend, "dinov3")
"""``tracker.features``: the fields of the backend its ``backend`` key names."""


def dense_features_config(**fields) -> DenseFeaturesBackend:
    """A ``tracker.features`` section from keyword fields (``backend`` default ``dinov3``)."""
    return backend_config(DENSE_FEATURES, "dinov3", **fields)
