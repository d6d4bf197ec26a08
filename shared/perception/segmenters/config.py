"""What every segmenter backend's config shares, and the registry that names them.

Each backend's config lives beside its code (``fastsam_config.py``, ``classical_config.py``,
``simulated_config.py``) and registers itself in ``SEGMENTERS`` when imported; the registry
imports those modules by name the first time a backend is looked up. None of them imports
torch, ultralytics or onnxruntime: ``build`` does, when the segmenter is made.
"""

from __future__ import annotations

from abc import abstractmethod

from pydantic import Field

from shared.config.backends import BackendConfig, backend_config, backend_section
from shared.registry import Registry

SEGMENTERS: Registry[type[SegmenterBackend]] = Registry(
    "segmenter backend",
    modules=(
        "shared.perception.segmenters.fastsam_config",
        "shared.perception.segmenters.classical_config",
        "shared.perception.segmenters.simulated_config",
    ),
)
"""Keyframe segmenter backends (``keyframe_vl.segmenter.backend``)."""


class SegmenterBackend(BackendConfig):
    """What every class-agnostic keyframe segmenter (FastSAM in the paper) shares: the filter
    its masks pass (shared/perception/segmenters/base.py)."""

    max_masks: int = Field(100, ge=1)
    """Keep at most this many masks per keyframe, highest score first."""
    min_area_px: int = Field(100, ge=0)
    """Drop masks smaller than this (pixels)."""
    max_area_frac: float = Field(0.95, gt=0, le=1)
    """Drop masks covering more than this fraction of the image."""

    @abstractmethod
    def build(self, device: str = "cpu", fp16: bool = False):
        """The :class:`~shared.perception.Segmenter` this config describes. ``device`` and
        ``fp16`` matter to the backends that run a network; missing weights raise
        FileNotFoundError naming the path (nothing is ever downloaded)."""


SegmenterSection, segmenter_default = backend_section(SEGMENTERS, SegmenterBackend, "fastsam")
"""``keyframe_vl.segmenter``: the fields of the backend its ``backend`` key names."""


def segmenter_config(**fields) -> SegmenterBackend:
    """A ``keyframe_vl.segmenter`` section from keyword fields (``backend`` default ``fastsam``)."""
    return backend_config(SEGMENTERS, "fastsam", **fields)
