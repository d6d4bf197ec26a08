"""The ``classical`` segmenter's settings: graph-based RGB-D segmentation with no weights.
Torch-free: ``build`` imports the segmenter."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.perception.segmenters.config import SEGMENTERS, SegmenterBackend


@SEGMENTERS.register("classical")
class ClassicalSegmenterConfig(SegmenterBackend):
    """Graph-based RGB-D segmentation (no learned weights)."""

    backend: Literal["classical"] = "classical"
    """Graph-based RGB-D segmentation, no weights (shared/perception/segmenters/classical.py)."""

    graph_width: int = Field(320, ge=16, le=4096)
    """Least width (pixels) of the pixel graph: the image is reduced by the largest integer
    factor that keeps this many pixels across (640 -> 320, 320 -> 320, 1280 -> 320), and the
    region labels are copied back to full resolution. 160 is about four times faster and a
    little coarser."""
    connectivity: Literal[4, 8] = 8
    """Pixel neighbourhood of the graph."""
    smooth_sigma: float = Field(0.8, ge=0)
    """Gaussian blur (graph pixels) of the colour image before edge weights are taken."""
    colour_weight: float = Field(1.0, ge=0)
    """Weight of the CIE Lab colour distance (per 100 Lab units) in an edge."""
    lightness_weight: float = Field(0.75, ge=0, le=1)
    """Scale of L* against a* and b* in the colour distance: below 1 forgives shading."""
    depth_weight: float = Field(16.0, ge=0)
    """Weight of the depth step not explained by the neighbouring steps, relative to depth."""
    normal_weight: float = Field(0.5, ge=0)
    """Weight of the angle (radians) between the normals of two pixels at a concave crease
    (where an object meets the floor or a wall)."""
    convex_factor: float = Field(0.2, ge=0, le=1)
    """Scale of the normal term at convex creases (the edges of one box-like object)."""
    k: float = Field(1.2, gt=0)
    """Felzenszwalb scale: a region covering a thousandth of the image accepts an edge this much
    heavier than the heaviest one inside it; larger values give larger regions."""
    min_region_frac: float = Field(0.0005, ge=0, le=0.5)
    """Regions smaller than this share of the image merge into their most similar neighbour."""
    min_region_width: float = Field(2.5, ge=0)
    """Regions thinner than this (graph pixels) merge into their most similar neighbour: the
    slivers of mixed pixels along silhouettes."""

    def build(self, device: str = "cpu", fp16: bool = False):
        from shared.perception.segmenters.classical import ClassicalSegmenter

        return ClassicalSegmenter(self)
