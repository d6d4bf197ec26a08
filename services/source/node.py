"""Source node: publishes a sequence's frames on ``frames`` and an EndOfSequence after them.

In lossless mode it is paced by the pipeline's ``frames/ack`` (``core.Pacer``): at most
``source.window_frames`` ahead of the slowest of ``source.ack_from`` that is alive."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from services.source.core import Pacer, ReplayStats, replay, replay_plan
from shared.config.root import TrackGraphConfig
from shared.datasets import open_sequence
from shared.messages.frames import EndOfSequence, Frame, FrameAck
from shared.topics import Topics, service_of_alive_key
from shared.transport import (
    LivelinessWatcher,
    TransportError,
    TypedPublisher,
    TypedSubscriber,
    declare_alive,
    open_session,
)

log = logging.getLogger(__name__)


def run_source(
    cfg: TrackGraphConfig,
    sequence: Path,
    *,
    stop: threading.Event | None = None,
    wait_subscribers_s: float = 30.0,
    progress: bool = True,
) -> ReplayStats:
    """Replay ``sequence`` over Zenoh per ``cfg.source``; returns what was sent and dropped."""
    stop = stop or threading.Event()
    reader = open_sequence(sequence, cfg.source.dataset, cfg.source)
    topics = Topics(cfg.robot_id)
    session = open_session(cfg.transport)
    try:
        token = declare_alive(session, topics.alive("source"))
        pub = TypedPublisher(session, topics.frames, Frame, robot_id=cfg.robot_id, codec=cfg.transport.codec)
        end = TypedPublisher(session, topics.end_of_sequence, EndOfSequence, robot_id=cfg.robot_id, codec=cfg.transport.codec)
        if cfg.source.mode == "lossless" and not pub.wait_for_subscribers(wait_subscribers_s):
            raise TransportError(f"{topics.frames}: no subscriber after {wait_subscribers_s:.1f} s; lossless replay would lose frames")
        log.info("replaying %s (%d frames, %s mode) on %s", sequence, len(reader), cfg.source.mode, topics.frames)
        plan = [number for _, number in replay_plan(len(reader), cfg.source)]
        bar = _progress_bar(progress, total=len(plan))
        pacer = Pacer(plan, cfg.source.window_frames, cfg.source.ack_from, hold_gone_s=cfg.source.hold_gone_s)
        acks = TypedSubscriber(session, topics.frame_ack, FrameAck, codec=cfg.transport.codec, capacity=256,
                               callback=lambda env: pacer.ack(env.body.service, env.body.frame_index))  # fmt: skip
        alive = LivelinessWatcher(session, topics.alive_all)

        def stages() -> set[str]:
            return {service_of_alive_key(k) for k in alive.alive()}

        try:
            stats = replay(
                reader,
                cfg.source,
                pub.put,
                should_stop=stop.is_set,
                on_progress=(lambda s: bar.update(1)) if bar is not None else None,
                pace=lambda k: pacer.wait(k, stages, stop.is_set),
            )
        finally:
            acks.close()
            alive.close()
        if bar is not None:
            bar.close()
        end.put(EndOfSequence(frames_published=stats.published, frames_dropped=stats.dropped, last_frame_index=stats.last_frame_index))
        log.info(
            "published %d frames in %.1f s (%.1f Hz), dropped %d, refused by the reader %d, held %.1f s for restarting stages",
            stats.published, stats.seconds, stats.published / max(stats.seconds, 1e-9), stats.dropped, stats.rejected, pacer.held_s,
        )  # fmt: skip
        pub.close()
        end.close()
        token.undeclare()
        return stats
    finally:
        session.close()


def _progress_bar(enabled: bool, total: int | None):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="source", leave=False)
