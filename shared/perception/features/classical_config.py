"""The ``classical`` dense features' settings: per-patch colour, gradient and depth
descriptors with no weights. Torch-free: ``build`` imports the backend."""

from __future__ import annotations

from typing import Literal

from shared.perception.features.config import DENSE_FEATURES, DenseFeaturesBackend


@DENSE_FEATURES.register("classical")
class ClassicalFeaturesConfig(DenseFeaturesBackend):
    """Per-patch colour, gradient and depth descriptors: no weights."""

    backend: Literal["classical"] = "classical"
    """Classical descriptors (shared/perception/features/classical.py)."""

    def build(self, device: str = "cpu", fp16: bool = True):
        from shared.perception.features.classical import ClassicalFeatures

        return ClassicalFeatures(self.short_side, self.patch_size, device)
