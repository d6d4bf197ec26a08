"""What fusion keeps of every fused frame to re-fuse the map after pose corrections
(``fusion.refuse``; docs/architecture.md, "Pose corrections").

A correction moves the map at once (:mod:`services.fusion.volume.move`), but a surface fused from
frames that had drifted apart stays blurred by their disagreement. Re-fusing the frames at
their corrected poses removes it; for that fusion keeps each tracked frame as it fused it
(depth, colour, track labels and confidences, the track list), compressed with the journal's
lossless record format (:mod:`services.fusion.durability.journal`): delta-coded depth and run-coded
labels, then zstd.

The log lives in memory, or, for the fusion service with a map store, in one append-only file
beside the snapshots (``<map>/graph/observations.wal``) that a resumed fusion reopens: every
record reaches the operating system before :meth:`ObservationLog.append` returns. A torn last
record (a crash mid-write) is cut off when the file is reopened; a log that lacks frames the
map fused (a resume from before it was kept) is not used, and says so.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from services.fusion.durability.journal import (
    FILE_MAGIC,
    HEADER,
    ReplayStats,
    decode_payload,
    encode_record,
    read_file,
)
from shared.messages.frames import TrackedFrame

if TYPE_CHECKING:
    from shared.config.root import TrackGraphConfig

log = logging.getLogger(__name__)

FILE_NAME = "observations.wal"


def refuse_wanted(cfg: TrackGraphConfig) -> bool:
    """``fusion.refuse``: ``on``, or ``auto`` with corrections configured for this run."""
    mode = cfg.fusion.refuse
    return mode == "on" or (mode == "auto" and (bool(cfg.source.corrections) or cfg.ros2.input.corrections != "none"))


class ObservationLog:
    """Tracked frames in fusion order, compressed; in memory (``path`` None) or in a file."""

    def __init__(self, path: Path | None = None, zstd_level: int = 1, *, fresh: bool = True) -> None:
        """``fresh``: start empty (a file there is truncated); else reopen what the file holds."""
        self.path = None if path is None else Path(path)
        self.level = zstd_level
        self.frames: list[int] = []
        """Frame indices held, in the order they were appended."""
        self._held: set[int] = set()
        self._fresh = fresh
        self.nbytes = 0
        self._records: list[bytes] = []
        self._fd: int | None = None
        if self.path is not None:
            self._open()

    def _open(self) -> None:
        assert self.path is not None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self._fresh and self.path.exists() and self.path.stat().st_size > 0:
            stats = ReplayStats()
            for rec in read_file(self.path, stats, repair=True):
                if rec.kind == "frame":
                    self.frames.append(int(rec.body.frame.frame_index))
            self._held = set(self.frames)
            if stats.torn:
                log.warning("observations: %d torn or damaged records dropped from %s", stats.torn, self.path)
            self.nbytes = self.path.stat().st_size
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        else:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.write(self._fd, FILE_MAGIC)
            self.nbytes = len(FILE_MAGIC)

    def append(self, tf: TrackedFrame) -> None:
        """Keep one fused frame (after the ones before it). A frame already held is skipped:
        a resumed fusion replays its journal's frames, which the log kept before the stop."""
        if int(tf.frame.frame_index) in self._held:
            return
        rec = encode_record("frame", tf, self.level)
        if self._fd is not None:
            os.write(self._fd, rec)
        else:
            self._records.append(rec)
        self.frames.append(int(tf.frame.frame_index))
        self._held.add(int(tf.frame.frame_index))
        self.nbytes += len(rec)

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[TrackedFrame]:
        """The frames, decoded one at a time, in the order they were fused."""
        if self._fd is None:
            for rec in self._records:
                yield decode_payload(rec[HEADER.size :]).body
            return
        for rec in read_file(self.path, ReplayStats()):
            if rec.kind == "frame":
                yield rec.body

    def covers(self, frames: list[int]) -> bool:
        """True if the log holds exactly these frames, in this order (the map's fused frames)."""
        return self.frames == list(frames)

    def clear(self) -> None:
        """Forget everything (a fresh map)."""
        self._records.clear()
        self.frames.clear()
        self._held.clear()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            self._fresh = True
            self._open()
        else:
            self.nbytes = 0

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
