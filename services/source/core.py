"""Replay logic of the source, without Zenoh: which frames to send, and when.

``lossless`` sends every planned frame as fast as the consumer takes them (the publish
callback blocks when the network is full). ``live`` holds a wall-clock schedule at
``rate_hz``; a frame whose slot has already passed when its turn comes, because
publishing the previous one blocked on a lagging subscriber, is dropped and counted rather
than sent late, so the stream stays real-time.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from shared.config.source import SourceConfig
from shared.datasets.base import DatasetError, SequenceReader
from shared.messages.frames import Frame

log = logging.getLogger(__name__)


MAX_REJECTED_KEPT = 100
"""Reasons kept of the frames a reader refused (``trackgraph map`` reports the first 20)."""


@dataclass
class ReplayStats:
    """What a replay did; published in the EndOfSequence message."""

    planned: int = 0
    published: int = 0
    dropped: int = 0
    last_frame_index: int = -1
    dropped_indices: list[int] = field(default_factory=list)
    rejected: int = 0
    """Frames the reader refused (a corrupt image, a NaN pose): logged, counted, skipped."""
    rejected_errors: list[str] = field(default_factory=list)
    """Why, for the first ``MAX_REJECTED_KEPT`` of them."""
    seconds: float = 0.0


def planned_indices(n_frames: int, stride: int = 1, max_frames: int | None = None) -> list[int]:
    """Frame indices to replay: every ``stride``-th, at most ``max_frames`` of them."""
    idx = list(range(0, n_frames, stride))
    return idx[:max_frames] if max_frames is not None else idx


def replay_plan(n_frames: int, cfg: SourceConfig) -> list[tuple[int, int]]:
    """(reader index, published frame index) of every frame to send, ``cfg.loops`` laps."""
    plan = planned_indices(n_frames, cfg.stride, cfg.max_frames)
    return [(i, lap * n_frames + i) for lap in range(cfg.loops) for i in plan]


class ReplayCursor:
    """The replay plan and where it stands: which frame goes next, when it is due, and what
    became of every frame so far (:class:`ReplayStats`). No clock of its own: callers say
    what time it is, so a blocking loop (:func:`replay`) and the source's session drive it
    alike."""

    def __init__(self, reader: SequenceReader, cfg: SourceConfig) -> None:
        self.reader, self.cfg = reader, cfg
        self.n = len(reader)
        self.plan = replay_plan(self.n, cfg)
        self.stats = ReplayStats(planned=len(self.plan))
        self.period = 1.0 / cfg.rate_hz
        self.k = 0
        """Plan position of the next frame."""
        self.t0: float | None = None

    @property
    def done(self) -> bool:
        return self.k >= len(self.plan)

    def start(self, now: float) -> None:
        """The replay's clock starts: live frame k is due ``k / rate_hz`` after this."""
        if self.t0 is None:
            self.t0 = now

    def wait(self, now: float) -> float:
        """Seconds until the next frame is due (0: now). Live, a frame whose slot has passed
        is dropped and counted first, never loaded; lossless, every frame is due at once."""
        self.start(now)
        if self.cfg.mode != "live":
            return 0.0
        while not self.done:
            due = self.t0 + self.k * self.period
            if now > due + self.period:
                self.stats.dropped += 1
                self.stats.dropped_indices.append(self.plan[self.k][1])
                self.k += 1
                continue
            return max(due - now, 0.0)
        return 0.0

    def send(self, publish: Callable[[Frame], None]) -> Frame | None:
        """Read the next frame and publish it; None if the reader refused it (logged, counted)."""
        i, number = self.plan[self.k]
        self.k += 1
        try:
            frame = self.reader.frame(i)
        except DatasetError as exc:
            self.stats.rejected += 1
            if len(self.stats.rejected_errors) < MAX_REJECTED_KEPT:
                self.stats.rejected_errors.append(str(exc))
            log.warning("frame %d refused: %s", i, exc)
            return None
        if number != i:
            lap = number // self.n
            frame = frame.model_copy(update={"frame_index": number, "time_s": frame.time_s + lap * self.n / self.cfg.rate_hz})
        publish(frame)
        self.stats.published += 1
        self.stats.last_frame_index = number
        return frame

    def close(self, now: float) -> ReplayStats:
        """The replay is over (done or stopped): its duration, and a warning for drops."""
        self.stats.seconds = now - (now if self.t0 is None else self.t0)
        if self.stats.dropped:
            log.warning("live replay dropped %d of %d frames (subscriber lagging)", self.stats.dropped, self.stats.planned)
        return self.stats


def replay(
    reader: SequenceReader,
    cfg: SourceConfig,
    publish: Callable[[Frame], None],
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    should_stop: Callable[[], bool] = lambda: False,
    on_progress: Callable[[ReplayStats], None] | None = None,
    pace: Callable[[int], None] | None = None,
) -> ReplayStats:
    """Send the planned frames of ``reader`` through ``publish`` under ``cfg.mode``, blocking
    (scripts and tests; the source service runs :class:`services.source.session.SourceSession`);
    in lossless mode ``pace(k)`` is called before the k-th frame and returns when the
    pipeline is ready for it (see :class:`Pacer`)."""
    cursor = ReplayCursor(reader, cfg)
    cursor.start(clock())
    while not cursor.done:
        if should_stop():
            break
        if cfg.mode == "live":
            delay = cursor.wait(clock())
            if cursor.done:
                break
            if delay > 0:
                sleep(delay)
        elif pace is not None:
            pace(cursor.k)
            if should_stop():
                break
        if cursor.send(publish) is not None and on_progress is not None:
            on_progress(cursor.stats)
    return cursor.close(clock())


class Pacer:
    """Lossless replay's end-to-end flow control, without Zenoh: frame k may go out once
    every pacing stage that is alive has acknowledged frame k - ``window`` (or, before it
    acknowledged anything, while k < ``window``). Stages that are not running do not count,
    so a source replaying to a plain subscriber is not held up; a stage that was running and
    vanished (a crash being restarted, a router restart) still counts for ``hold_gone_s``, so
    the source waits for it instead of replaying into the void."""

    def __init__(
        self, plan: list[int], window: int, stages: list[str], hold_gone_s: float = 0.0, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.position = {int(f): k for k, f in enumerate(plan)}
        self.window = window
        self.stages = list(stages)
        self.hold_gone_s = float(hold_gone_s)
        self.clock = clock
        self.done: dict[str, int] = {}
        """Stage -> highest plan position it has acknowledged."""
        self.last_seen: dict[str, float] = {}
        """Stage -> when it was last seen alive."""
        self.held_s = 0.0
        """Total time spent waiting for vanished stages."""
        self.rejoins: dict[str, int] = {}
        """Stage -> times it came back after vanishing."""
        self._gone: set[str] = set()
        self._cv = threading.Condition()

    def ack(self, stage: str, frame_index: int) -> None:
        k = self.position.get(int(frame_index))
        if k is None or stage not in self.stages:
            return
        with self._cv:
            if k > self.done.get(stage, -1):
                self.done[stage] = k
                self._cv.notify_all()

    def counted(self, alive: set[str], k: int) -> set[str]:
        """The stages that hold frame ``k`` now: those alive, and those gone for less than
        ``hold_gone_s``. A stage that comes back (restarted) never acknowledges what it lost
        while away, so it starts afresh from ``k``: what it lost is its to count."""
        now = self.clock()
        for s in self.stages:
            if s in alive:
                if s in self._gone:
                    self._gone.discard(s)
                    self.rejoins[s] = self.rejoins.get(s, 0) + 1
                    self.done[s] = max(self.done.get(s, -1), k - 1)
                    log.info("%s is back; pacing on from frame position %d", s, k)
                self.last_seen[s] = now
            elif s in self.last_seen:
                self._gone.add(s)
        return {s for s in self.stages if s in alive or now - self.last_seen.get(s, -math.inf) < self.hold_gone_s}

    def _holding(self, k: int, alive: set[str]) -> set[str]:
        """The counted stages that have not yet acknowledged frame k - ``window``."""
        return {s for s in self.counted(alive, k) if self.done.get(s, -1) < k - self.window}

    def holding(self, k: int, alive: set[str]) -> set[str]:
        """The stages frame ``k`` waits for now; empty when it may go."""
        with self._cv:
            return self._holding(k, alive)

    def ready(self, k: int, alive: set[str]) -> bool:
        return not self.holding(k, alive)

    def wait(self, k: int, alive: Callable[[], set[str]], should_stop: Callable[[], bool], poll_s: float = 0.1) -> None:
        """Block until frame ``k`` may go, or ``should_stop``; ``alive`` is re-read while
        waiting, so a stage that dies stops holding the source (after ``hold_gone_s``)."""
        warned = False
        with self._cv:
            while not should_stop():
                now_alive = alive()
                holding = self._holding(k, now_alive)
                if not holding:
                    return
                gone = sorted(holding - now_alive)
                if gone:
                    if not warned:
                        log.warning("frame %d waits for %s to come back (up to %.0f s)", k, ", ".join(gone), self.hold_gone_s)
                        warned = True
                    self.held_s += poll_s
                self._cv.wait(poll_s)
