"""``trackgraph map``: the whole pipeline in one process, source -> tracker <-> keyframe_vl
-> fusion.

It composes the same session classes as the distributed services, over an
:class:`~shared.runtime.bus.InProcessBus` instead of Zenoh: after each frame the source
publishes, the bus delivers everything that frame sets off (the keyframe request, its masks and
CLIP features, the tracked frame, the graph delta) before the next one. The tracker waits for a
keyframe's masks, which keyframe_vl answers in that same round, so every keyframe is corrected
before the next frame, as in a lossless distributed run with ``tracker.wait_for_masks``.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

from services.fusion.export import (
    SEGMENT_IDS_FILE,
    export_map,
    ply_bytes,
    run_summary,
    segment_embedding,
)
from shared.config.base import save_resolved
from shared.config.root import TrackGraphConfig
from shared.datasets import open_sequence
from shared.datasets.base import DatasetError
from shared.io import atomic_write_text

log = logging.getLogger(__name__)

OBSERVATIONS_SCRATCH = ".observations.wal"
"""The frames ``fusion.refuse`` keeps while a map is made, deleted when it is done."""

__all__ = ["SEGMENT_IDS_FILE", "export_map", "ply_bytes", "prepare_config", "run_map", "run_summary", "segment_embedding"]

FINISH_MARGIN_S = 5.0
"""Past the tracker's keyframe time-out and fusion's end grace, how long the in-process run
waits for the map to finish before it calls the pipeline stuck."""


def prepare_config(cfg: TrackGraphConfig, seq_dir: Path) -> TrackGraphConfig:
    """Point every simulated backend whose ground truth is unset at the sequence, when it is
    synthetic (no message carries ground truth; see ``TrackGraphConfig.with_ground_truth``).
    A ROS 2 bag written from a synthetic sequence (``trackgraph synth --rosbag``) names that
    sequence in its metadata; its ground truth is used."""
    seq = Path(seq_dir)
    if not (seq / "instances").is_dir() and _is_bag(seq):
        from shared.ros2.bagio import bag_source_sequence

        seq = bag_source_sequence(seq) or seq
    return cfg.with_ground_truth(seq)


def _is_bag(path: Path) -> bool:
    """A ROS 2 bag folder (``metadata.yaml``) or one bag file."""
    return (path / "metadata.yaml").is_file() or (path.is_file() and path.suffix in (".mcap", ".db3"))


def run_map(
    seq_dir: Path,
    cfg: TrackGraphConfig,
    out: Path,
    *,
    dataset: str | None = None,
    save_tracks: bool = False,
    stride: int | None = None,
    max_frames: int | None = None,
    progress: bool = True,
    corrections: Path | None = None,
) -> dict[str, Any]:
    """Map a recorded sequence; writes the map folder and returns the ``run.json`` summary.
    ``corrections``: a JSON-lines file of pose corrections, each applied once the map has
    fused the frame it is valid up to (or its ``apply_after_frame``); default the config's
    ``source.corrections``."""
    from services.fusion.core import FusionCore
    from services.fusion.session import FusionSession
    from services.keyframe_vl.build import build_keyframe_vl
    from services.keyframe_vl.session import KeyframeVLSession
    from services.source.session import SourceSession
    from services.tracker.build import asks_for_keyframes, build_tracker
    from services.tracker.session import TrackerSession
    from shared.eval.track_io import TrackWriter
    from shared.graph.store import MapStore
    from shared.messages.frames import TrackedFrame
    from shared.runtime.bus import InProcessBus

    seq_dir, out = Path(seq_dir), Path(out)
    cfg = prepare_config(cfg, seq_dir)
    reader = open_sequence(seq_dir, dataset or cfg.source.dataset, cfg.source)
    # Every planned frame once, as fast as the pipeline takes it (a live rate, laps and
    # dropping are for a camera's stream, not for a batch map).
    replay = cfg.source.model_copy(update={
        "mode": "lossless", "loops": 1, "stride": stride or cfg.source.stride, "max_frames": max_frames or cfg.source.max_frames,
        "corrections": str(corrections) if corrections is not None else cfg.source.corrections,
    })  # fmt: skip
    pipeline_cfg = cfg.model_copy(update={"source": replay})
    out.mkdir(parents=True, exist_ok=True)
    save_resolved(cfg, out / "config.yaml")

    t0 = time.perf_counter()
    bus = InProcessBus(cfg.robot_id)
    sessions: list = []
    writer = None
    bar = None
    try:
        tracker_core = build_tracker(cfg)
        if asks_for_keyframes(cfg):
            sessions.append(KeyframeVLSession(bus, build_keyframe_vl(cfg)))
        elif getattr(tracker_core, "encoder", None) is not None:
            # A tracker that embeds its own crops (the oracle) answers vl/embed here, so the
            # rooms are named in the space of its galleries.
            _serve_embed(bus, tracker_core.encoder, cfg.keyframe_vl.embed_cache_size)
        tracker = TrackerSession(bus, pipeline_cfg, tracker_core, wait_for_masks=True)
        # Frames kept for a re-fusion after corrections (fusion.refuse) go to a file, not to memory.
        fusion = FusionSession(bus, pipeline_cfg, FusionCore(cfg.fusion, device=cfg.tracker.device), observations=out / OBSERVATIONS_SCRATCH)
        # Before the first frame, so every update names its rooms (in one process vl/embed
        # answers at once; without keyframe_vl the rooms keep features and no names).
        fusion.fetch_room_labels()
        source = SourceSession(bus, reader, replay)
        sessions += [tracker, fusion, source]
        if save_tracks:
            writer = TrackWriter(out)
            bus.subscribe(tracker.topics.tracks_frame, TrackedFrame, lambda env: writer.write(env.body.frame.frame_index, env.body.track_ids, keyframe=env.body.keyframe))
        bar = _bar(progress, len(source.cursor.plan))
        if bar is not None:
            source.on_progress = lambda _stats: bar.update(1)
        t_start = time.perf_counter()
        while source.tick(time.monotonic()) is not None:
            bus.drain()
        bus.drain()
        _wait_finished(bus, tracker, fusion, cfg.tracker.keyframe_timeout_s + cfg.fusion.end_grace_s)
        seconds = time.perf_counter() - t_start
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
        for s in reversed(sessions):
            s.close()
        bus.close()
        (out / OBSERVATIONS_SCRATCH).unlink(missing_ok=True)
    stats = source.stats
    if stats.planned and stats.rejected == stats.planned:
        raise DatasetError(f"{seq_dir}: no frame could be read; the first error: {stats.rejected_errors[0]}")

    core = fusion.core
    snapshot = core.snapshot(whole_map=True)
    MapStore(out / "graph", robot_id=cfg.robot_id).save(snapshot, extra_state=core.state_dict(), metadata={"sequence": str(seq_dir)})
    export_map(out, core)
    summary = run_summary(cfg, core, snapshot, frames=stats.planned - stats.rejected, seconds=seconds, sequence=seq_dir)
    summary["setup_seconds"] = round(t_start - t0, 3)
    summary["frames_rejected"] = stats.rejected
    summary["rejected"] = stats.rejected_errors[:20]
    atomic_write_text(out / "run.json", json.dumps(summary, indent=2))
    log.info("mapped %d frames in %.1f s (%.2f Hz): %d segments", stats.planned, seconds, summary["hz"] or 0, summary["segments"])
    return summary


def _serve_embed(bus, encoder, cache_size: int) -> None:
    from services.keyframe_vl.embedder import Embedder
    from shared.messages.rpc import EmbedReply, EmbedRequest
    from shared.topics import Topics

    embedder = Embedder(encoder, cache_size)
    bus.serve(Topics(bus.robot_id).vl_embed, EmbedRequest, EmbedReply, lambda env: embedder.embed(env.body))


def _wait_finished(bus, tracker, fusion, timeouts_s: float) -> None:
    """Everything the last frame set off is delivered; the map is finished unless a stage
    still waits on a time-out (a frame that failed in the tracker or in fusion): tick them
    until it is, within their time-outs (``timeouts_s``: ``tracker.keyframe_timeout_s`` plus
    ``fusion.end_grace_s``)."""
    deadline = time.monotonic() + timeouts_s + FINISH_MARGIN_S
    while not fusion.finished.is_set():
        now = time.monotonic()
        if now > deadline:
            raise RuntimeError(
                f"the in-process pipeline did not finish: tracker {tracker.book.report().model_dump(include={'state', 'frames_done', 'figures'})}, "
                f"fusion {fusion.book.report().model_dump(include={'state', 'frames_done', 'frames_expected', 'figures'})}"
            )
        tracker.tick(now)
        fusion.tick(now)
        if not bus.drain():
            time.sleep(0.05)


def _bar(enabled: bool, total: int):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="map")
