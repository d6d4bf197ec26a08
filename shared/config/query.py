"""The query service (paper section III-F, eq. 10)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.config.base import StrictModel


class QueryConfig(StrictModel):
    """Retrieval over the live graph."""

    gallery: Literal["max", "mean"] = "max"
    """Segment score over its CLIP gallery: max cosine (eq. 10) or the mean feature
    (the gallery ablation)."""
    default_top_k: int = Field(10, ge=1)
    """Results returned when the request gives no top_k."""
    max_top_k: int = Field(100, ge=1)
    """Largest top_k a client may ask for."""
    max_text_chars: int = Field(512, ge=1)
    """Longest text query."""
    max_image_pixels: int = Field(4096 * 4096, ge=1)
    """Largest image query."""
    embed: Literal["remote", "local"] = "remote"
    """Embed queries through keyframe_vl's ``vl/embed``, or with a local encoder built
    from ``keyframe_vl.vl``."""
    workers: int = Field(4, ge=1)
    """Threads answering queries concurrently."""
