"""Zenoh session and wire-encoding settings."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from shared.config.base import ServiceName, StrictModel

_LOCATOR_PREFIXES = ("tcp/", "udp/", "tls/", "quic/", "unixsock-stream/", "ws/")


class CodecConfig(StrictModel):
    """Size limits for decoding, and how images and masks travel on each link."""

    max_payload_bytes: int = Field(256 * 2**20, gt=0)
    """Largest payload accepted before msgpack parsing starts (bytes)."""
    max_array_bytes: int = Field(128 * 2**20, gt=0)
    """Largest single decoded array, raw or after decompression (bytes). Checked from the
    declared shape before anything is allocated."""
    max_total_array_bytes: int | None = Field(None, gt=0)
    """Most bytes all arrays of one payload may decode to together, so many small compressed
    arrays cannot add up to a huge allocation; default twice ``max_array_bytes``."""
    max_ndim: int = Field(4, ge=1, le=8)
    """Most dimensions an array may declare."""
    max_items: int = Field(1_000_000, gt=0)
    """Most entries in one msgpack list or map."""
    max_string_bytes: int = Field(1 * 2**20, gt=0)
    """Longest msgpack string (bytes)."""
    max_image_pixels: int = Field(4096 * 4096, gt=0)
    """Most pixels in one compressed image, checked from its header before decoding."""
    @property
    def total_array_limit(self) -> int:
        return self.max_total_array_bytes or 2 * self.max_array_bytes

    rgb: Literal["raw", "jpeg"] = "raw"
    """RGB encoding on this link: raw for loopback/shared memory, jpeg over Wi-Fi."""
    jpeg_quality: int = Field(90, ge=1, le=100)
    """JPEG quality when ``rgb: jpeg``."""
    depth: Literal["raw", "png", "zstd"] = "raw"
    """Depth encoding on this link: raw uint16; ``zstd`` (lossless: gradient-predicted,
    zigzagged, byte planes, zstd) for Wi-Fi, 3.7x smaller than raw in 2.6 ms a 1200x680
    frame; or lossless 16-bit PNG (2.9x in 33 ms, too slow for 30 Hz; kept for old configs).
    Receivers decode all three whatever their own setting."""
    zstd_level: int = Field(1, ge=1, le=19)
    """zstd level of ``depth: zstd``. 1: on sensor-noisy depth, higher levels were no smaller
    (3.61x at 3, 3.68x at 6) and 2.5-5x slower."""
    png_level: int = Field(1, ge=0, le=9)
    """zlib level for PNG depth; 1 trades a little size for a lot of speed."""
    masks: Literal["bits", "rle"] = "bits"
    """Mask encoding: bit-packed (fast, fixed size) or run-length (small for few big masks)."""
    labels: Literal["raw", "zlib"] = "raw"
    """Integer label maps (per-pixel track ids): raw, or zlib level 1. Raw by default, as
    colour and depth: label maps go tracker -> fusion on the robot, where a 1200x680
    ``TrackedFrame`` took 10.3 ms to encode and 4.0 ms to decode with zlib labels against
    2.5 and 0.9 ms raw (8.2 MB against 4.3 MB); zlib for a link where bytes cost more."""


class TransportConfig(StrictModel):
    """How a process joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = "client"
    """Zenoh mode. Services are clients of a router; ``trackgraph router`` is the router."""
    connect: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    """Endpoints to connect to, e.g. ``tcp/10.0.0.2:7447`` or ``tls/base:7447``."""
    listen: list[str] = Field(default_factory=list)
    """Endpoints to listen on (routers and peers), e.g. ``tcp/0.0.0.0:7447``."""
    multicast_scouting: bool = False
    """Multicast discovery. Off by default: explicit endpoints are predictable on robots."""
    gossip_scouting: bool = False
    """Gossip discovery through connected peers."""
    shared_memory: bool = True
    """Zero-copy shared memory between processes on one host; tests can turn it off."""
    connect_timeout_s: float = Field(-1.0)
    """How long a client waits for its router at start; -1 waits forever (the router may
    start later than the service)."""
    query_timeout_s: float = Field(2.0, gt=0)
    """Default timeout of request/reply calls (snapshot, embed, query)."""
    timestamping: bool = True
    """Zenoh stamps each sample with its hybrid logical clock. Zenoh's advanced publishers
    (ROS 2's transient-local topics: the scene-graph markers, ``/tf_static``) need it, and
    rmw_zenoh's own session config turns it on; the cost is 16 bytes a sample."""
    zenoh_config_file: str | None = None
    """Optional Zenoh JSON5 file (TLS, user/password, access control) applied before the
    fields above."""
    codec: CodecConfig = Field(default_factory=CodecConfig)
    """Encoding and decoding limits of this process's links."""
    status_heartbeat: list[ServiceName] = Field(
        default_factory=lambda: ["fusion"]
    )
    """Services whose status reports go out through a heartbeat process of their own, so that
    one arrives every second even while a native call holds the service's interpreter.
    Fusion is here by default: Open3D's grid, when it doubles, holds it 0.6-1.7 s. The cost is
    one small process (about 60 MB) per service named."""

    @field_validator("connect", "listen")
    @classmethod
    def _locators(cls, v: list[str]) -> list[str]:
        for loc in v:
            if not loc.startswith(_LOCATOR_PREFIXES):
                raise ValueError(
                    f"endpoint {loc!r} must start with one of {', '.join(_LOCATOR_PREFIXES)}"
                )
        return v
