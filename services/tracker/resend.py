"""What the tracker sent fusion and fusion has not acknowledged yet, to send again.

fusion acknowledges a tracked frame once it is in its journal (``frames/ack`` with
``service: fusion``), and the feature messages below ``features_through``. Everything after
that is kept here, in the order it went out, and sent again, in that order:

- when an ack carries an ``epoch`` other than the last one seen: fusion restarted and lost
  what it had not journaled;
- when the oldest kept message has waited ``tracker.resend_after_s`` (lossless replay only:
  a message lost on the link, a fusion that restarted before it ever acknowledged).

fusion drops what it already has (frame indices at or below its last, feature serials below
``features_through``), so sending too much costs time, never correctness. An ack for frame
``k`` lets every frame up to ``k`` go: fusion fuses frames in order and would skip an older
one sent again. The store holds at most ``tracker.resend_frames`` frames; past that the
oldest frame and the feature messages before it are let go and counted.
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass

from pydantic import BaseModel

from shared.messages.frames import FrameAck, TrackedFrame
from shared.messages.keyframes import TrackFeatures

log = logging.getLogger(__name__)


@dataclass
class Sent:
    """One message kept: ``kind`` is ``frame`` (``key`` its frame index) or ``features`` (``key`` its serial)."""

    kind: str
    key: int
    body: BaseModel
    sent_at: float


class Unacked:
    """The tracker's messages to fusion that fusion has not acknowledged, oldest first."""

    def __init__(self, capacity_frames: int, resend_after_s: float, *, on_timeout: bool = True) -> None:
        self.capacity = capacity_frames
        self.resend_after_s = resend_after_s
        self.on_timeout = on_timeout
        self._kept: collections.OrderedDict[tuple[str, int], Sent] = collections.OrderedDict()
        self._frames = 0
        self.epoch: int | None = None
        """fusion's epoch from its newest ack (None: fusion not heard from yet)."""
        self.let_go = 0
        """Messages let go unacknowledged because the store was full."""
        self.resent = 0
        """Messages sent again."""
        self.restarts = 0
        """New fusion epochs seen after the first."""

    def __len__(self) -> int:
        return len(self._kept)

    @property
    def frames(self) -> int:
        return self._frames

    def sent(self, body: TrackedFrame | TrackFeatures, now: float) -> None:
        """Keep a message just sent (a feature message without a serial cannot be told apart: not kept)."""
        if self.capacity == 0:
            return
        if isinstance(body, TrackedFrame):
            key = ("frame", body.frame.frame_index)
            self._frames += key not in self._kept
        elif body.serial is not None:
            key = ("features", body.serial)
        else:
            return
        self._kept[key] = Sent(key[0], key[1], body, now)
        while self._frames > self.capacity:
            self._pop_oldest_frame()

    def _pop_oldest_frame(self) -> None:
        while self._kept:
            (kind, key), _ = self._kept.popitem(last=False)
            self.let_go += 1
            if kind == "frame":
                self._frames -= 1
                if self.epoch is not None:
                    log.warning("frame %d let go before fusion acknowledged it: %d frames wait (tracker.resend_frames)", key, self.capacity)
                return

    def ack(self, msg: FrameAck) -> bool:
        """Take fusion's ack; True if it comes from a new fusion epoch (a restart): the caller
        sends :meth:`pending` again."""
        restarted = msg.epoch is not None and self.epoch is not None and msg.epoch != self.epoch
        if msg.epoch is not None:
            self.epoch = msg.epoch
        through = msg.features_through
        for (kind, key) in list(self._kept):
            if (kind == "frame" and key <= msg.frame_index) or (kind == "features" and through is not None and key < through):
                del self._kept[(kind, key)]
                self._frames -= kind == "frame"
        if restarted:
            self.restarts += 1
        return restarted

    def due(self, now: float) -> bool:
        """Whether the oldest kept message has waited past ``resend_after_s`` (once fusion was heard from)."""
        if not self.on_timeout or not self._kept or self.epoch is None:
            return False  # (a pipeline without fusion: nobody to send it to)
        oldest = next(iter(self._kept.values()))
        return now - oldest.sent_at > self.resend_after_s

    def pending(self, now: float) -> list[BaseModel]:
        """Everything kept, oldest first, marked as sent ``now`` (the caller sends it)."""
        out = []
        for s in self._kept.values():
            s.sent_at = now
            out.append(s.body)
        self.resent += len(out)
        return out

    def as_dict(self) -> dict:
        return {"kept": len(self._kept), "frames": self._frames, "resent": self.resent, "let_go": self.let_go, "fusion_restarts": self.restarts}
