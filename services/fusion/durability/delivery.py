"""What fusion has taken of the tracker's stream, across restarts: feature messages applied
once per ``serial`` (a tracker resends what a killed fusion did not acknowledge), and the
end of the sequence, complete once every frame and feature message it announces is in (or
its grace is over)."""

from __future__ import annotations

import logging

from shared.messages.frames import EndOfSequence
from shared.messages.keyframes import TrackFeatures

log = logging.getLogger(__name__)


class FeatureSerials:
    """Feature messages in the map, each ``serial`` once."""

    def __init__(self) -> None:
        self.in_map = 0
        """Feature messages in the map (across restarts: saved with each snapshot)."""
        self.next = 0
        """One past the highest ``serial`` applied: lower ones are duplicates."""
        self.duplicate = 0

    def seen(self, msg: TrackFeatures) -> bool:
        """Whether ``msg`` is in the map already (sent again after a restart); counted."""
        if msg.serial is not None and msg.serial < self.next:
            self.duplicate += 1
            return True
        return False

    def took(self, msg: TrackFeatures) -> None:
        """``msg`` is in the map."""
        self.in_map += 1
        if msg.serial is not None:
            self.next = msg.serial + 1


class EndWatch:
    """The tracker's ``tracks/end`` and when it came; the map may finish once everything it
    announced is in, or ``grace_s`` after it came (with a warning)."""

    def __init__(self, grace_s: float) -> None:
        self.grace_s = grace_s
        self.end: EndOfSequence | None = None
        self.at = 0.0

    def arrive(self, msg: EndOfSequence, now: float) -> None:
        self.end, self.at = msg, now

    def complete(self, now: float, last_frame_index: int, features_in: int) -> bool:
        """Whether the sequence is over: the end came, and its frames and feature messages are
        in or its grace is over."""
        end = self.end
        if end is None:
            return False
        frames_in = last_frame_index >= end.last_frame_index
        feats_in = end.track_features_published is None or features_in >= end.track_features_published
        if not (frames_in and feats_in):
            if now - self.at < self.grace_s:
                return False
            log.warning(
                "finishing without everything the tracker announced: frames up to %d (have %d), %s feature messages (have %d)",
                end.last_frame_index, last_frame_index, end.track_features_published, features_in,
            )  # fmt: skip
        return True

    def lost(self, frames_in_map: int) -> tuple[int | None, int | None]:
        """Frames the source announced, and how many of them are not in the map (None before
        the end came); a loss is logged."""
        announced = None if self.end is None else self.end.frames_published
        lost = None if announced is None else max(announced - frames_in_map, 0)
        if lost:
            log.warning("%d of %d announced frames are not in the map (lost in a crash or on the link)", lost, announced)
        return announced, lost
