"""Clock checks of the live input: header stamps in ns, and the streams stamped back in time.

One message stamped back is refused (``out_of_order``); a stream that keeps going back for
more than :data:`RESET_AFTER_S` of arrivals is a new timeline (a bag played in a loop, a
simulator reset), and :class:`Timeline` hands it to the assembler to clear its buffers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

NS = 1_000_000_000
"""Nanoseconds in a second."""
RESET_AFTER_S = 1.0
"""A stream whose stamps keep going back for this long (of arrivals) means a new timeline."""
RESET_MIN_MESSAGES = 3
"""... and at least this many messages in a row went back (one stray message is no reset)."""


def header_stamp_ns(header: Any) -> int:
    """Header stamp in ns; ValueError for one no ROS clock can produce."""
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec < 0 or not 0 <= nsec < NS:
        raise ValueError(f"invalid header stamp sec={sec} nanosec={nsec}")
    return sec * NS + nsec


@dataclass
class Streak:
    """A stream whose stamps went back: since when (arrival time) and how many in a row."""

    since: float
    count: int = 0


class Timeline:
    """The streams (``"colour"``, ``"pose"``, ``"tf:<child>"``) whose stamps currently go back.

    ``on_reset(what)`` is called when one has gone back long enough to be a new timeline;
    it clears the buffers (and, through :meth:`clear`, the streaks)."""

    def __init__(self, on_reset: Callable[[str], None]) -> None:
        self._on_reset = on_reset
        self._streaks: dict[str, Streak] = {}

    def went_back(self, stream: str, now: float, what: str) -> bool:
        """Count one message of ``stream`` stamped back in time; True (after the reset) when
        the stream has kept going back long enough to be a new timeline."""
        s = self._streaks.setdefault(stream, Streak(now))
        s.count += 1
        if now - s.since <= RESET_AFTER_S or s.count < RESET_MIN_MESSAGES:
            return False
        self._on_reset(what)
        return True

    def forward(self, stream: str) -> None:
        """``stream`` went forward again (or is gone): its streak ends."""
        self._streaks.pop(stream, None)

    def clear(self) -> None:
        self._streaks.clear()
