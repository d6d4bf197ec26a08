"""The source's coordination, without Zenoh: a sequence's frames out on ``frames`` when they
are due, an EndOfSequence after them on ``frames/end``; ``frames/ack`` in.

Which frame goes next and when is the :class:`~services.source.core.ReplayCursor`'s; in
lossless mode a frame also waits for the pipeline (:class:`~services.source.core.Pacer`: at
most ``source.window_frames`` ahead of the slowest of ``source.ack_from`` that is alive).
:meth:`SourceSession.tick` sends the next frame when it may go and says how long until it is
worth calling again; it never sleeps.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from services.source.core import Pacer, ReplayCursor, ReplayStats
from shared.config.source import SourceConfig
from shared.datasets.base import SequenceReader
from shared.messages.frames import EndOfSequence, Frame, FrameAck
from shared.messages.poses import PoseCorrection, read_corrections
from shared.runtime.bus import Bus
from shared.runtime.session import Session

log = logging.getLogger(__name__)

POLL_S = 0.1
"""While the pipeline holds the next frame, how often to look again (an ack wakes the node sooner)."""


class SourceSession(Session):
    """Replays ``reader`` per ``cfg`` on a bus.

    ``alive`` says which services are running now (their liveliness), for the pacer: a stage
    that is not running does not hold the source. ``on_ack`` is told of each ack (a node
    wakes its loop with it); ``on_progress`` of each planned frame sent, dropped or refused.
    """

    service = "source"
    serialized = False  # acks go to the pacer, which has its own lock; tick runs on one thread

    def __init__(
        self, bus: Bus, reader: SequenceReader, cfg: SourceConfig, *, alive: Callable[[], set[str]] = set,
        on_ack: Callable[[], None] | None = None, on_progress: Callable[[ReplayStats], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:  # fmt: skip
        super().__init__(bus, clock=clock)
        self.cfg = cfg
        self.cursor = ReplayCursor(reader, cfg)
        self.pacer = Pacer([n for _, n in self.cursor.plan], cfg.window_frames, cfg.ack_from, hold_gone_s=cfg.hold_gone_s, clock=clock)
        self.alive = alive
        self.on_ack, self.on_progress = on_ack, on_progress
        self.ended = False
        """The EndOfSequence is out."""
        self._held_at: float | None = None
        self._warned_k = -1
        self.frames_out = self.output("frames", Frame)
        self.end_out = self.output("end_of_sequence", EndOfSequence)
        self.corrections_out = self.output("poses_correction", PoseCorrection)
        self.corrections = _due_order(read_corrections(cfg.corrections)) if cfg.corrections else []
        """Pose corrections still to send (``source.corrections``), by the frame they follow."""
        self.corrections_sent = 0
        self.subscribe("frame_ack", FrameAck, self._on_ack, capacity=256)
        self._refresh(clock())

    @property
    def stats(self) -> ReplayStats:
        return self.cursor.stats

    def _on_ack(self, msg: FrameAck) -> None:
        self.pacer.ack(msg.service, msg.frame_index)
        if self.on_ack is not None:
            self.on_ack()

    def tick(self, now: float) -> float | None:
        """Send the next frame if it may go at ``now``. Returns the seconds until the next
        call is useful (0: at once), or None once the replay is over and its end is out."""
        if self.ended:
            return None
        cursor = self.cursor
        delay = cursor.wait(now)  # live: drops the frames whose slot has passed
        if cursor.done:
            self.finish(now)
            return None
        if delay > 0:
            self._refresh(now)
            return delay
        if self.cfg.mode == "lossless":
            held = self._held(cursor.k, now)
            if held:
                return POLL_S
        t0 = self.clock()
        sent = cursor.send(self.frames_out.put)
        if sent is not None:
            self.book.work_done(max(self.clock() - t0, 0.0))
            self._send_corrections(sent.frame_index)
        self._refresh(now)
        if self.on_progress is not None:
            self.on_progress(cursor.stats)
        return 0.0

    def _held(self, k: int, now: float) -> bool:
        """Whether the pacer holds frame ``k``; the time held for vanished stages is counted."""
        alive = self.alive()
        holding = self.pacer.holding(k, alive)
        gone = sorted(holding - alive)
        if gone:
            if self._warned_k != k:
                log.warning("frame %d waits for %s to come back (up to %.0f s)", k, ", ".join(gone), self.pacer.hold_gone_s)
                self._warned_k = k
            if self._held_at is not None:
                self.pacer.held_s += max(now - self._held_at, 0.0)
            self._held_at = now
        else:
            self._held_at = None
        return bool(holding)

    def finish(self, now: float) -> ReplayStats:
        """The replay is over (done, or stopped early): the EndOfSequence out, once."""
        if not self.ended:
            self.ended = True
            self._send_corrections(None)
            stats = self.cursor.close(now)
            self.end_out.put(EndOfSequence(frames_published=stats.published, frames_dropped=stats.dropped, last_frame_index=stats.last_frame_index))
            self._refresh(now)
        return self.cursor.stats

    def _send_corrections(self, frame_index: int | None) -> None:
        """The corrections due once frame ``frame_index`` is out (None: all that are left, at
        the end), each told to wait in fusion for the frame it follows."""
        while self.corrections and (frame_index is None or _after(self.corrections[0]) <= frame_index):
            c = self.corrections.pop(0)
            self.corrections_out.put(c.model_copy(update={"apply_after_frame": _after(c)}))
            self.corrections_sent += 1
            log.info("pose correction %d (frames up to %d) sent after frame %s", c.correction_id, c.frame_index, frame_index)

    def _refresh(self, now: float) -> None:
        s, book = self.cursor.stats, self.book
        seconds = s.seconds if self.ended else (0.0 if self.cursor.t0 is None else max(now - self.cursor.t0, 0.0))
        book.progress(done=s.published + s.dropped, expected=s.planned)
        book.figure("published", s.published)
        book.figure("dropped", s.dropped)
        book.figure("rejected", s.rejected)
        book.figure("seconds", round(seconds, 3))
        book.figure("hz", round(s.published / seconds, 3) if seconds > 0 else None)
        book.figure("held_s", round(self.pacer.held_s, 3))
        book.figure("corrections_sent", self.corrections_sent)


def _after(c: PoseCorrection) -> int:
    """The frame a replayed correction follows: its own ``apply_after_frame``, else the frame
    it is valid up to."""
    return c.frame_index if c.apply_after_frame is None else c.apply_after_frame


def _due_order(corrections: list[PoseCorrection]) -> list[PoseCorrection]:
    """By the frame each follows; file order among those that follow the same frame."""
    return sorted(corrections, key=_after)
