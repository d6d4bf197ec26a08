"""``status/<service>``: what each running service reports about itself, once a second and
once at stop. Consumers (the launcher's table, ``trackgraph status``, the bench) read these,
never log text."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.messages.base import Message, register

ServiceState = Literal["starting", "running", "finished", "stopped"]


class InputCounters(Message):
    """Counters of one input of a service (a subscribed key or an answered queryable)."""

    name: str = Field(min_length=1, max_length=64)
    """The input's topic name, as in ``docs/wire.md`` (``frames``, ``keyframe_masks``, ...)."""
    received: int = Field(0, ge=0)
    """Messages that arrived and decoded."""
    processed: int = Field(0, ge=0)
    """Messages the service finished handling (successfully or with an answered error)."""
    rejected: int = Field(0, ge=0)
    """Messages refused: undecodable, invalid, from another robot, or failed in the handler."""
    dropped: int = Field(0, ge=0)
    """Messages lost to a full queue (fifo) or replaced by newer ones (latest)."""
    rate_hz: float = Field(0.0, ge=0)
    """Messages received per second over the last few seconds."""
    queue_depth: int = Field(0, ge=0)
    """Messages waiting to be handled now."""


@register
class ServiceStatus(Message):
    """One service's health and progress (``trackgraph/<robot>/status/<service>``)."""

    service: str = Field(min_length=1, max_length=32)
    """The service's name (``source``, ``tracker``, ``keyframe_vl``, ``fusion``, ``query``, ``viewer``)."""
    pid: int = Field(ge=0)
    """Operating-system process id of the reporting process."""
    state: ServiceState
    """``starting`` until ready, ``running``, ``finished`` (its sequence is done), ``stopped`` (last report)."""
    uptime_s: float = Field(ge=0)
    """Seconds since the service started."""
    inputs: list[InputCounters] = Field(default_factory=list)
    """One entry per input key."""
    published: dict[str, int] = Field(default_factory=dict)
    """Messages sent, per output topic name."""
    rate_hz: float = Field(0.0, ge=0)
    """Work items (frames, keyframes, queries) processed per second over the last few seconds."""
    latency_p50_ms: float | None = Field(None, ge=0)
    """Median processing time of one work item over the recent window (ms); None before the first."""
    latency_p99_ms: float | None = Field(None, ge=0)
    """99th percentile of the same (ms)."""
    frames_done: int | None = Field(None, ge=0)
    """Frames this service has finished, where it handles frames."""
    frames_expected: int | None = Field(None, ge=0)
    """Frames it will get in all, where known (the source knows its sequence's length)."""
    errors: int = Field(0, ge=0)
    """Work items that failed inside the service (logged with their traceback)."""
    figures: dict[str, int | float | str | bool | None | dict | list] = Field(default_factory=dict)
    """The service's own figures, e.g. the tracker's keyframe ledger under ``keyframes``
    (JSON-compatible values only)."""
    stale_s: float = Field(0.0, ge=0)
    """0 when the service made this report just now. Above 0, its heartbeat process sent the
    service's last report again because the service has not had its interpreter for this many
    seconds (a long native call): the process is alive, and its figures are this old."""
