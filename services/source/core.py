"""Replay logic of the source, without Zenoh: which frames to send, and when.

``lossless`` sends every planned frame as fast as the consumer takes them (the publish
callback blocks when the network is full). ``live`` holds a wall-clock schedule at
``rate_hz``; a frame whose slot has already passed when its turn comes, because
publishing the previous one blocked on a lagging subscriber, is dropped and counted rather
than sent late, so the stream stays real-time.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from shared.config.source import SourceConfig
from shared.datasets.base import SequenceReader
from shared.messages.frames import Frame

log = logging.getLogger(__name__)


@dataclass
class ReplayStats:
    """What a replay did; published in the EndOfSequence message."""

    planned: int = 0
    published: int = 0
    dropped: int = 0
    last_frame_index: int = -1
    dropped_indices: list[int] = field(default_factory=list)
    seconds: float = 0.0


def planned_indices(n_frames: int, stride: int = 1, max_frames: int | None = None) -> list[int]:
    """Frame indices to replay: every ``stride``-th, at most ``max_frames`` of them."""
    idx = list(range(0, n_frames, stride))
    return idx[:max_frames] if max_frames is not None else idx


def replay(
    reader: SequenceReader,
    cfg: SourceConfig,
    publish: Callable[[Frame], None],
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    should_stop: Callable[[], bool] = lambda: False,
    on_progress: Callable[[ReplayStats], None] | None = None,
) -> ReplayStats:
    """Send the planned frames of ``reader`` through ``publish`` under ``cfg.mode``."""
    plan = planned_indices(len(reader), cfg.stride, cfg.max_frames)
    stats = ReplayStats(planned=len(plan))
    period = 1.0 / cfg.rate_hz
    t0 = clock()
    for k, i in enumerate(plan):
        if should_stop():
            break
        if cfg.mode == "live":
            due = t0 + k * period
            now = clock()
            if now > due + period:
                stats.dropped += 1
                stats.dropped_indices.append(i)
                continue
            if now < due:
                sleep(due - now)
        frame = reader.frame(i)
        publish(frame)
        stats.published += 1
        stats.last_frame_index = i
        if on_progress is not None:
            on_progress(stats)
    stats.seconds = clock() - t0
    if stats.dropped:
        log.warning("live replay dropped %d of %d frames (subscriber lagging)", stats.dropped, stats.planned)
    return stats
