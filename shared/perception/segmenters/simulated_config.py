"""The ``simulated`` segmenter's settings: ground-truth masks of a synthetic scene with
FastSAM-like errors. Torch-free: ``build`` imports the segmenter."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.config.base import StrictModel
from shared.perception.segmenters.config import SEGMENTERS, SegmenterBackend


class SimulatedSegmenterNoise(StrictModel):
    """Noise model applied to ground-truth masks by the ``simulated`` segmenter."""

    boundary_jitter_px: float = Field(1.5, ge=0)
    """Std of the random morphological boundary shift (pixels)."""
    split_prob: float = Field(0.05, ge=0, le=1)
    """Chance a mask is split in two along its principal axis."""
    merge_prob: float = Field(0.03, ge=0, le=1)
    """Chance a mask is merged with a touching neighbour."""
    miss_below_frac: float = Field(150 / (640 * 480), ge=0, le=1)
    """Objects covering less than this share of the image are dropped, as FastSAM misses small
    objects. A share, not a pixel count, because FastSAM resizes every image to its own input
    size (1024 on the long side) before it detects anything, so what it misses depends on the
    object's size relative to the frame. The default is 150 pixels at 640x480 (about a
    12 x 12 pixel object), 38 at the 320x240 presets."""
    miss_below_px: int | None = Field(None, ge=0)
    """An absolute threshold in pixels instead of ``miss_below_frac``, when set (0 misses
    nothing)."""
    spurious_per_frame: float = Field(0.5, ge=0)
    """Mean number of spurious blob masks added per keyframe."""


@SEGMENTERS.register("simulated")
class SimulatedSegmenterConfig(SegmenterBackend):
    """Noisy ground-truth masks of a synthetic scene: measures the mapping, not FastSAM."""

    backend: Literal["simulated"] = "simulated"
    """Ground truth with FastSAM-like errors; synthetic scenes only
    (shared/perception/segmenters/simulated.py)."""
    noise: SimulatedSegmenterNoise = Field(default_factory=SimulatedSegmenterNoise)
    """The errors; all zeros reproduces the ground truth."""
    seed: int = 0
    """Seed of the noise, combined with the frame index."""
    ground_truth: str | None = None
    """The synthetic sequence folder (``SEQ_DIR`` with ``instances/``) whose instance images
    it reads by keyframe index. ``trackgraph map``, ``launch`` and ``serve --sequence`` set it
    to the sequence when unset."""

    def build(self, device: str = "cpu", fp16: bool = False):
        from shared.perception.segmenters.simulated import SimulatedSegmenter

        return SimulatedSegmenter(self)
