"""The query service (paper section III-F, eq. 10)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.config.base import Device, StrictModel


class QueryConfig(StrictModel):
    """Retrieval over the live graph."""

    gallery: Literal["max", "mean"] = "max"
    """Segment score over its CLIP gallery: max cosine (eq. 10) or the mean feature
    (the gallery ablation)."""
    default_top_k: int = Field(10, ge=1)
    """Results returned when the request gives no top_k."""
    min_view_share: float = Field(0.02, ge=0, lt=1)
    """Not in the paper: eq. 10 takes its maximum over the gallery rows whose track holds at
    least this share of the segment's hypothesis weight (``SegmentNode.gallery_weights``),
    so a small object's track that a larger segment absorbed (a clock on a wall, a book in a
    shelf) cannot make that segment the answer for it. On the synthetic ``demo`` preset with
    simulated perception this took the top-1 hit rate of synonym queries for objects over
    20 cm from 0.785 to 0.861. 0 is the paper's plain maximum (docs/method.md, Q1)."""
    max_top_k: int = Field(100, ge=1)
    """Largest top_k a client may ask for."""
    max_text_chars: int = Field(512, ge=1)
    """Longest text query."""
    max_image_pixels: int = Field(4096 * 4096, ge=1)
    """Largest image query."""
    embed: Literal["remote", "local"] = "remote"
    """Embed queries through keyframe_vl's ``vl/embed``, or with a local encoder built
    from ``keyframe_vl.vl``."""
    device: Device = "auto"
    """Torch device of the local encoder (``embed: local``, and offline queries): ``auto``
    (CUDA when present), ``cpu``, ``cuda`` or ``cuda:N``. ViT-H-14's text tower needs about
    4 GB; on a base station with a GPU it belongs there. Its precision is
    ``keyframe_vl.vl.precision``."""
    workers: int = Field(4, ge=1)
    """Threads answering queries concurrently."""
    queue_size: int = Field(16, ge=1)
    """Requests that may wait for a free worker; one more is answered "overloaded: ..." at
    once instead of queueing, so a client under load hears it in milliseconds rather than
    waiting out its timeout. 16 behind 4 workers, measured with benchmarks/query.py
    --while-mapping --novel on this 2-core machine: 16 clients asking novel texts while
    ``demo`` maps all fit (none overloaded, p99 545 ms against a 2 s time-out); 32 clients on
    ``small`` get half their requests answered "overloaded" within 28 ms and none times out."""
    embed_cache_size: int = Field(1024, ge=0)
    """Text query embeddings the service remembers, least recently used dropped first (0: ask
    ``vl/embed`` every time). Clients repeat prompts; a remembered one is answered without the
    ``vl/embed`` round trip. 1024 of 1024-d float32 is 4 MB."""
    warmup_retry_s: float = Field(0.5, gt=0)
    """The service declares itself alive (liveliness token, status ``running``) only once its
    text-embedding path has answered a warm-up request; until then it asks again this often
    (keyframe_vl declares ``vl/embed`` only when its models are loaded and warm)."""
    sync_wait_s: float = Field(1.0, ge=0)
    """A query arriving while the replica resynchronises waits this long for the snapshot,
    then is refused: the service never answers from a graph it knows is behind."""
