"""Counters and warnings of the live input.

Why a message was dropped (:data:`REASONS`), the status book's :class:`LiveInputStats`, the
problem that currently stops frames, and warning lines limited to one per reason per
:data:`WARN_PERIOD_S`, all kept by one :class:`Ledger`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

# One logger for the whole assembler: its lines are the live input's, whichever part wrote them.
log = logging.getLogger("services.ros2.live")

REASONS = (
    "bad_payload",
    "unknown_encoding",
    "unsupported_type",
    "no_camera_info",
    "size_mismatch",
    "out_of_order",
    "no_depth",
    "no_pose",
    "tf_missing",
    "tf_backwards",
    "superseded",
    "bad_pose",
)
"""Why a message (or a colour image's frame) was dropped: the status counters."""

WARN_PERIOD_S = 5.0
"""At most one warning line per reason in this many seconds (of ``now``)."""

ERROR_ORDER = ("camera_info", "tf", "size", "input", "sync")
"""Which current problem :attr:`Ledger.error` names first, when there are several."""


@dataclass
class LiveInputStats:
    """Counters of the live input, for the status book (:meth:`as_dict`).

    ``received[topic] == accepted[topic] + (rejections of its messages)``, and for the colour
    topic ``accepted`` is the frames emitted; ``pending`` colour images are still waiting."""

    received: dict[str, int] = field(default_factory=dict)
    """Messages handed in, by topic."""
    accepted: dict[str, int] = field(default_factory=dict)
    """Messages taken in, by topic (colour topic: emitted in a frame)."""
    emitted: int = 0
    """Frames returned by ``poll``."""
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REASONS, 0))
    """Messages (colour images: frames) dropped, by reason (:data:`REASONS`)."""
    pending: int = 0
    """Colour images waiting for their depth or pose."""
    last_stamp_s: float | None = None
    """Colour stamp of the last frame emitted (s), None before the first."""
    resets: int = 0
    """Times the stamps went back for good and the buffers were cleared."""

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able copy."""
        return {
            "received": dict(self.received),
            "accepted": dict(self.accepted),
            "emitted": self.emitted,
            "rejected": dict(self.rejected),
            "pending": self.pending,
            "last_stamp_s": self.last_stamp_s,
            "resets": self.resets,
        }


class Ledger:
    """The counters, the current problems and the warning lines of one assembler.

    ``roles`` maps each configured topic to its role (``rgb``, ``depth``, ``camera_info``,
    ``tf``, ``tf_static``, ``pose``). Not locked: the assembler's lock covers it."""

    def __init__(self, roles: dict[str, str]) -> None:
        self.roles = roles
        self.stats = LiveInputStats(received=dict.fromkeys(roles, 0), accepted=dict.fromkeys(roles, 0))
        self.errors: dict[str, str] = {}
        """Current problems by kind (:data:`ERROR_ORDER`), each until what clears it."""
        self.t0: float | None = None
        """``now`` of the first call, None before it."""
        self.now = 0.0
        """The latest ``now`` seen: the warning lines' clock."""
        self._warned: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def tick(self, now: float) -> None:
        if self.t0 is None:
            self.t0 = now
        self.now = max(self.now, now)

    @property
    def error(self) -> str | None:
        """The problem that currently stops frames, as one line; None when there is none."""
        return next((self.errors[k] for k in ERROR_ORDER if k in self.errors), None)

    def accept(self, topic: str) -> None:
        self.stats.accepted[topic] += 1

    def emitted(self, topic: str) -> None:
        """A frame of the colour image on ``topic`` went out: whatever stood in the way is gone."""
        self.stats.emitted += 1
        self.accept(topic)
        for key in ("size", "input", "sync", "tf"):
            self.errors.pop(key, None)

    def reject(self, reason: str, topic: str, text: str) -> None:
        """Count a message refused at intake, with a rate-limited warning."""
        self.stats.rejected[reason] += 1
        if reason in ("unknown_encoding", "unsupported_type", "bad_payload") and self.roles[topic] in ("rgb", "depth", "pose"):
            self.errors["input"] = text  # until the next frame: a camera stuck on yuv422 shows here
        self.warn(reason, text)

    def drop(self, reason: str, text: str) -> None:
        """Count a pending colour image given up."""
        self.stats.rejected[reason] += 1
        if reason in ("no_depth", "no_pose", "tf_missing", "tf_backwards"):
            self.errors["sync"] = text  # until the next frame: depth or poses on another clock show here
        self.warn(reason, text)

    def count(self, reason: str, text: str, key: str | None = None, exc_info: bool = False) -> None:
        """Count a frame that could not be built, warning under ``key`` (default: the reason)."""
        self.stats.rejected[reason] += 1
        self.warn(key or reason, text, exc_info=exc_info)

    def size_error(self, text: str) -> None:
        self.errors["size"] = text
        self.count("size_mismatch", text)

    def warn(self, key: str, text: str, exc_info: bool = False) -> None:
        """One warning line per ``key`` per WARN_PERIOD_S of ``now``, saying how many were held back."""
        last = self._warned.get(key)
        if last is not None and self.now - last < WARN_PERIOD_S:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        held = self._suppressed.pop(key, 0)
        self._warned[key] = self.now
        more = f" (+{held} more in the last {WARN_PERIOD_S:.0f} s)" if held else ""
        log.warning("ROS input [%s]: %s%s", key, text, more, exc_info=exc_info)
