"""viewer node: ``graph/delta`` and ``tracks/frame`` in; a Rerun recording (.rrd) out.

A thin shell around :mod:`services.viewer.recording`. The graph is kept in a
:class:`GraphReplica`; a gap in ``graph_seq`` (or joining a running map late) is repaired by
asking the ``graph/snapshot`` queryable, and a failed request is retried on the next delta,
so the viewer converges without ever blocking the mapper. Tracked frames arrive through a
"latest" queue of one: the viewer shows the newest frame and never slows the tracker.

Both handlers run on the subscribers' worker threads; one lock serialises the replica and
the recording, and each log call sets its own timeline first (Rerun's time is per thread).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from services.viewer.recording import (
    log_snapshot,
    log_tracked_frame,
    log_trajectory,
    log_world_frame,
    new_recording,
)
from shared.config.root import TrackGraphConfig
from shared.graph.scene import ApplyResult, GraphReplica
from shared.messages.base import Envelope
from shared.messages.frames import TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, SnapshotRequest
from shared.topics import Topics
from shared.transport import TransportError, TypedSubscriber, declare_alive, open_session, request

log = logging.getLogger(__name__)


class ViewerNode:
    """Records the live map to ``out_rrd``; open it with ``rerun out.rrd``."""

    def __init__(self, cfg: TrackGraphConfig, out_rrd: Path, *, session=None, frame_every: int = 10) -> None:
        if frame_every < 1:
            raise ValueError("frame_every must be at least 1")
        self.cfg = cfg
        self.out_rrd = Path(out_rrd)
        self.frame_every = int(frame_every)
        self.topics = Topics(cfg.robot_id)
        self.replica = GraphReplica()
        self._lock = threading.RLock()
        self._need_snapshot = False
        self._counts = {"deltas": 0, "stale": 0, "snapshots": 0, "snapshot_requests": 0, "frames_received": 0, "frames_logged": 0, "errors": 0}
        self._trajectory: list[np.ndarray] = []
        self._closed = False

        self.out_rrd.parent.mkdir(parents=True, exist_ok=True)
        self.rec = new_recording(recording_id=None)
        self.rec.save(self.out_rrd)
        log_world_frame(self.rec)

        self.subs: list[TypedSubscriber] = []
        self.token = None
        self._own_session = session is None
        self.session = session
        codec = cfg.transport.codec
        try:
            if self.session is None:
                self.session = open_session(cfg.transport)
            self.subs = [
                TypedSubscriber(self.session, self.topics.graph_delta, GraphDelta, codec=codec, capacity=64, callback=self._on_delta, name="viewer:delta"),
                TypedSubscriber(
                    self.session, self.topics.tracks_frame, TrackedFrame, codec=codec, policy="latest", capacity=1,
                    callback=self._on_frame, name="viewer:frame",
                ),
            ]  # fmt: skip
            self.token = declare_alive(self.session, self.topics.alive("viewer"))
        except BaseException:
            self._teardown()
            raise
        log.info("viewer recording to %s", self.out_rrd)

    # ------------------------------------------------------------ graph

    def _on_delta(self, env: Envelope[GraphDelta]) -> None:
        try:
            with self._lock:
                self._delta(env.body)
        except Exception:  # noqa: BLE001 - a bad delta must not stop the viewer
            self._error()
            log.exception("viewer: failed on graph delta %d", env.body.graph_seq)

    def _delta(self, delta: GraphDelta) -> None:
        if self._need_snapshot and not self._resync():
            return
        result = self.replica.apply_delta(delta)
        if result is ApplyResult.NEED_SNAPSHOT:
            self._need_snapshot = True
            if not self._resync():
                return
            # The snapshot may predate this delta; apply it if it is the next version.
            result = self.replica.apply_delta(delta)
        if result is ApplyResult.APPLIED:
            self._counts["deltas"] += 1
            self._log_graph(with_mesh=delta.mesh is not None)
        elif result is ApplyResult.STALE:
            self._counts["stale"] += 1

    def _resync(self) -> bool:
        """Fetch and apply a snapshot; False (and retry on the next delta) if none came."""
        self._counts["snapshot_requests"] += 1
        try:
            env = request(
                self.session, self.topics.graph_snapshot, SnapshotRequest(with_mesh=True), GraphSnapshot,
                robot_id=self.cfg.robot_id, timeout=self.cfg.transport.query_timeout_s, codec=self.cfg.transport.codec,
            )  # fmt: skip
        except TransportError as exc:
            self._error()
            log.warning("viewer: graph snapshot unavailable (%s); retrying on the next delta", exc)
            return False
        self.replica.apply_snapshot(env.body)
        self._need_snapshot = False
        self._counts["snapshots"] += 1
        log.info("viewer: resynchronised from snapshot at graph %d", env.body.graph_seq)
        self._log_graph(with_mesh=True)
        return True

    def _log_graph(self, with_mesh: bool) -> None:
        # The mesh only when it changed: it is most of a recording's size.
        self.rec.reset_time()
        log_snapshot(self.rec, self.replica.snapshot(with_mesh=with_mesh), time_seq=self.replica.graph_seq)

    # ------------------------------------------------------------ frames

    def _on_frame(self, env: Envelope[TrackedFrame]) -> None:
        try:
            with self._lock:
                tf = env.body
                self._counts["frames_received"] += 1
                self._trajectory.append(np.asarray(tf.frame.T_world_cam[:3, 3], np.float64))
                if (self._counts["frames_received"] - 1) % self.frame_every:
                    return
                self.rec.reset_time()
                log_tracked_frame(self.rec, tf)
                log_trajectory(self.rec, np.array(self._trajectory), time_frame=tf.frame.frame_index)
                self._counts["frames_logged"] += 1
        except Exception:  # noqa: BLE001 - a bad frame must not stop the viewer
            self._error()
            log.exception("viewer: failed on a tracked frame")

    # ------------------------------------------------------------ lifecycle

    def _error(self) -> None:
        with self._lock:
            self._counts["errors"] += 1

    def stats(self) -> dict:
        with self._lock:
            out = dict(self._counts)
            out["graph_seq"] = self.replica.graph_seq
            out["need_snapshot"] = self._need_snapshot
        out["links"] = {s.key: s.stats.as_dict() for s in self.subs}
        return out

    def close(self) -> None:
        """Stop receiving, finish the recording and (if it was ours) close the session."""
        if self._closed:
            return
        self._closed = True
        self._teardown()
        log.info("viewer closed: %s", {k: v for k, v in self.stats().items() if k != "links"})

    def _teardown(self) -> None:
        for s in self.subs:
            try:
                s.close()
            except Exception:  # noqa: BLE001 - keep closing the rest
                log.exception("viewer: closing %s", s.key)
        if self.token is not None:
            self.token.undeclare()
            self.token = None
        with self._lock:
            self.rec.flush()
            self.rec.disconnect()
        if self._own_session and self.session is not None:
            self.session.close()

    def __enter__(self) -> ViewerNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
