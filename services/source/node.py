"""Source node: a :class:`~services.source.session.SourceSession` on Zenoh, replaying a
sequence's frames on ``frames`` and an EndOfSequence after them.

In lossless mode it is paced by the pipeline's ``frames/ack``: at most
``source.window_frames`` ahead of the slowest of ``source.ack_from`` that is alive (their
liveliness tokens say which). Its ``ServiceStatus`` goes out every second on
``status/source``; the last one is also written to ``status_file``."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from services.source.core import ReplayStats
from services.source.session import SourceSession
from shared.config.root import TrackGraphConfig
from shared.datasets import open_sequence
from shared.runtime.adapter import SessionNode, open_bus
from shared.runtime.lifeline import install_stop_handlers, start_lifeline
from shared.runtime.status import StatusReporter
from shared.topics import Topics, service_of_alive_key
from shared.transport import LivelinessWatcher, TransportError

log = logging.getLogger(__name__)


def run_source(
    cfg: TrackGraphConfig,
    sequence: Path,
    *,
    stop: threading.Event | None = None,
    wait_subscribers_s: float = 30.0,
    progress: bool = True,
    status_file: Path | None = None,
) -> ReplayStats:
    """Replay ``sequence`` over Zenoh per ``cfg.source``; returns what was sent and dropped."""
    stop = stop or threading.Event()
    signalled = threading.Event()

    def stop_now() -> None:
        signalled.set()
        stop.set()

    install_stop_handlers(stop_now)
    lifeline = start_lifeline()  # launched: end with the launcher, however it ends
    reader = open_sequence(sequence, cfg.source.dataset, cfg.source)
    topics = Topics(cfg.robot_id)
    bus = open_bus(cfg)
    if lifeline is not None:
        lifeline.stop_with(stop_now)  # connected: from now on the launcher's death is an orderly stop
    wake = threading.Event()

    def make(b) -> SourceSession:
        alive = node.own(LivelinessWatcher(b.session, topics.alive_all))

        def stages() -> set[str]:
            return {service_of_alive_key(k) for k in alive.alive()}

        return SourceSession(b, reader, cfg.source, alive=stages, on_ack=wake.set)

    # Driven by the loop below, not ticked; "running" once a lossless replay has its consumer.
    node = reporter = bar = None
    try:
        node = SessionNode(bus, make, name="source", alive="source", running=False, start=False)
        node.start()
        session = node.session
        bar = _progress_bar(progress, total=len(session.cursor.plan))
        if bar is not None:
            session.on_progress = lambda _stats: bar.update(1)
        heartbeat = cfg.transport if "source" in cfg.transport.status_heartbeat else None
        reporter = StatusReporter(session.book, bus, topics.status("source"), heartbeat=heartbeat)
        if cfg.source.mode == "lossless" and not _wait_for(session.frames_out.has_subscribers, wait_subscribers_s, stop) and not stop.is_set():
            raise TransportError(f"{topics.frames}: no subscriber after {wait_subscribers_s:.1f} s; lossless replay would lose frames")
        log.info("replaying %s (%d frames, %s mode) on %s", sequence, len(reader), cfg.source.mode, topics.frames)
        session.book.set_state("running")
        while not stop.is_set():
            wake.clear()
            delay = session.tick(time.monotonic())
            if delay is None:
                break
            if delay > 0:
                wake.wait(delay)
        stats = session.finish(time.monotonic())  # stopped early: what was sent so far
        log.info(
            "published %d frames in %.1f s (%.1f Hz), dropped %d, refused by the reader %d, held %.1f s for restarting stages",
            stats.published, stats.seconds, stats.published / max(stats.seconds, 1e-9), stats.dropped, stats.rejected, session.pacer.held_s,
        )  # fmt: skip
    finally:
        if bar is not None:
            bar.close()
        if node is not None:
            node.close(keep_bus=True)
        if reporter is not None:
            reporter.stop(status_file)
        bus.close()
        if lifeline is not None:
            lifeline.close()
    if signalled.is_set():
        # Stopped by a signal before the end: not "finished" (exit 130, as Ctrl-C always was),
        # so a launcher never mistakes an interrupted replay for a complete one.
        raise KeyboardInterrupt
    return stats


def _wait_for(cond, timeout: float, stop: threading.Event) -> bool:
    """Wait until ``cond()`` (lossless replay must not publish into the void)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() >= deadline or stop.is_set():
            return False
        time.sleep(0.02)
    return True


def _progress_bar(enabled: bool, total: int | None):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="source", leave=False)
