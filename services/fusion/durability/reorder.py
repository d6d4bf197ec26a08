"""The tracker's messages to fusion put back in the order they were sent.

Tracked frames and feature messages travel on two topics, and after a fusion restart the
tracker sends again what fusion had not acknowledged while new messages keep coming. Applied
as they arrive, a new frame would overtake the resent ones (which fusion then drops as older
than its last frame) and a new feature message would move ``features_through`` past resent
ones: the map would lose them, or fuse them in another order than the uninterrupted run.

The tracker numbers both kinds together (``order``, from 0, within its ``stream``: an epoch
drawn at its start). Here a message whose turn it is goes through, with every held one that
follows it; a later one is held; an earlier one is a duplicate. A gap that does not fill
within ``wait_s`` (a message let go by the tracker, or lost in live mode), or more than
``capacity`` held messages, is given up: the held ones go on in order and the missing ones
are counted.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)


@dataclass
class Held:
    kind: str
    body: Any
    since: float


class InOrder:
    """Puts messages numbered ``(stream, order)`` back in order; unnumbered ones pass."""

    def __init__(self, wait_s: float, capacity: int) -> None:
        self.wait_s = wait_s
        self.capacity = capacity
        self.stream: int | None = None
        """The tracker's epoch the numbering belongs to (None: none seen yet)."""
        self.next = 0
        """The ``order`` whose turn it is."""
        self.done = 0
        """One past the ``order`` of the last message applied (set by the caller): a snapshot
        taken while a released run is being applied keeps this, not ``next``."""
        self._held: dict[int, Held] = {}
        self.held_most = 0
        """The most messages held at once."""
        self.skipped = 0
        """Messages given up on: their turn passed without them."""
        self.dropped = 0
        """Held messages of a tracker stream that ended (the tracker restarted)."""
        self.streams = 0
        """New tracker streams seen after the first (tracker restarts)."""

    def __len__(self) -> int:
        return len(self._held)

    def admit(self, kind: str, body: Any, stream: int | None, order: int | None, now: float) -> tuple[list[tuple[str, Any]], bool]:
        """What to apply now, in order, and whether ``body`` is a duplicate (already applied)."""
        if order is None:
            return [(kind, body)], False
        if stream is not None and stream != self.stream:
            if self.stream is not None:
                self.streams += 1
                self.dropped += len(self._held)
                log.warning("a new tracker stream (%d after %d): its numbering starts again; %d held messages of the old one dropped", stream, self.stream, len(self._held))
                self._held.clear()
                self.next = self.done = 0
            self.stream = stream
        if order < self.next:
            return [], True
        if order > self.next:
            self._held[order] = Held(kind, body, now)
            self.held_most = max(self.held_most, len(self._held))
            out = self._give_up() if len(self._held) > self.capacity else []
            return out, False
        self.next += 1
        return [(kind, body), *self._release()], False

    def expire(self, now: float) -> list[tuple[str, Any]]:
        """Held messages whose gap waited past ``wait_s``: the gap given up, they go on."""
        if not self._held:
            return []
        oldest = min(h.since for h in self._held.values())
        return self._give_up() if now - oldest > self.wait_s else []

    def _give_up(self) -> list[tuple[str, Any]]:
        first = min(self._held)
        missing = first - self.next
        self.skipped += missing
        log.warning("tracker messages %d to %d never came (%d held behind them): going on without them", self.next, first - 1, len(self._held))
        self.next = first
        return self._release()

    def _release(self) -> list[tuple[str, Any]]:
        out = []
        while self.next in self._held:
            h = self._held.pop(self.next)
            out.append((h.kind, h.body))
            self.next += 1
        return out

    def applied(self, order: int | None) -> None:
        """The message numbered ``order`` is in the map."""
        if order is not None:
            self.done = order + 1

    def state(self) -> list[int]:
        """What a snapshot keeps: ``[stream or -1, done]`` (held and released-not-applied
        messages are not acknowledged: the tracker still has them)."""
        return [-1 if self.stream is None else self.stream, self.done]

    def load(self, state: list[int]) -> None:
        stream, done = (int(x) for x in state)
        self.stream = None if stream < 0 else stream
        self.next = self.done = done
        self._held.clear()

    def as_dict(self) -> dict:
        return {"held": len(self._held), "held_most": self.held_most, "skipped": self.skipped, "dropped": self.dropped, "tracker_restarts": self.streams}
