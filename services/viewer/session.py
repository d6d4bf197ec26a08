"""The viewer as a session: ``graph/delta`` and ``tracks/frame`` in, a Rerun recording
(.rrd) out. No Zenoh: it talks through the :class:`~shared.runtime.bus.Bus` it is given.

The graph is kept by the same :class:`~shared.graph.sync.ReplicaFollower` as the query
service's: a gap in ``graph_seq``, or joining a running map late, is repaired from the
``graph/snapshot`` queryable in :meth:`ViewerSession.tick` (retried with backoff while
fusion is not there), the deltas meanwhile held, so the viewer converges without ever
blocking the mapper. Tracked frames arrive through a "latest" queue of one: the viewer shows
the newest frame and never slows the tracker.

Handlers may run on different threads (one per subscription over Zenoh); one lock
serialises the recording, and each log call sets its own timeline first (Rerun's time is
per thread).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
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
from shared.graph.scene import GraphReplica
from shared.graph.sync import ReplicaFollower
from shared.messages.base import Envelope
from shared.messages.frames import TrackedFrame
from shared.runtime.bus import Bus
from shared.runtime.status import StatusBook
from shared.topics import Topics

log = logging.getLogger(__name__)


class ViewerSession:
    """Records the live map to ``out_rrd``; open it with ``rerun out.rrd``. Every
    ``frame_every``-th tracked frame is logged (the trajectory gets them all)."""

    def __init__(
        self,
        cfg: TrackGraphConfig,
        bus: Bus,
        out_rrd: Path,
        *,
        frame_every: int = 10,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if frame_every < 1:
            raise ValueError("frame_every must be at least 1")
        self.cfg = cfg
        self.bus = bus
        self.out_rrd = Path(out_rrd)
        self.frame_every = int(frame_every)
        self.topics = Topics(cfg.robot_id)
        self.book = StatusBook("viewer", clock=clock)
        self._clock = clock
        self._lock = threading.Lock()
        self.frames_received = 0
        self.frames_logged = 0
        self._trajectory: list[np.ndarray] = []
        self._closed = False
        self._endpoints: list = []
        self.token = None

        self.out_rrd.parent.mkdir(parents=True, exist_ok=True)
        self.rec = new_recording(recording_id=None)
        self.rec.save(self.out_rrd)
        log_world_frame(self.rec)

        book = self.book
        book.figure("frames_logged", lambda: self.frames_logged)
        book.figure("frames_received", lambda: self.frames_received)
        try:
            self.graph = ReplicaFollower(
                bus, self.topics, book, with_mesh=True, timeout_s=cfg.transport.query_timeout_s, on_change=self._log_graph,
                capacity=64, name="viewer:delta", work=True,
            )  # fmt: skip
            self._endpoints.append(self.graph)
            self.sync = self.graph.sync
            self.deltas = self.graph.deltas
            self.frames = bus.subscribe(
                self.topics.tracks_frame, TrackedFrame, self.on_frame, policy="latest", capacity=1, name="viewer:frame",
                on_drop=lambda: book.count("tracks_frame", "dropped"), on_reject=lambda _why: book.count("tracks_frame", "rejected"),
            )  # fmt: skip
            self._endpoints.append(self.frames)
            book.declare_input("tracks_frame", self.frames.pending)
            self.token = bus.declare_alive(self.topics.alive("viewer"))
        except BaseException:
            self.close()
            raise
        book.set_state("running")
        log.info("viewer recording to %s", self.out_rrd)

    # ------------------------------------------------------------ graph

    def tick(self, now: float) -> bool | None:
        """Ask fusion for a snapshot (with the mesh) if the replica needs one and the backoff
        allows it (:meth:`ReplicaFollower.tick`)."""
        return self.graph.tick(now)

    def _log_graph(self, replica: GraphReplica, mesh_changed: bool) -> None:
        # The mesh only when it changed: it is most of a recording's size.
        try:
            with self._lock:
                if self._closed:
                    return
                self.rec.reset_time()
                log_snapshot(self.rec, replica.snapshot(with_mesh=mesh_changed), time_seq=replica.graph_seq)
        except Exception:  # noqa: BLE001 - a graph the recording cannot take must not stop the viewer
            self.book.error()
            log.exception("viewer: graph version %d not recorded", replica.graph_seq)

    # ------------------------------------------------------------ frames

    def on_frame(self, env: Envelope[TrackedFrame]) -> None:
        t0 = self._clock()
        self.book.count("tracks_frame", "received")
        try:
            with self._lock:
                if self._closed:
                    return
                tf = env.body
                self.frames_received += 1
                self._trajectory.append(np.asarray(tf.frame.T_world_cam[:3, 3], np.float64))
                if (self.frames_received - 1) % self.frame_every == 0:
                    self.rec.reset_time()
                    log_tracked_frame(self.rec, tf)
                    log_trajectory(self.rec, np.array(self._trajectory), time_frame=tf.frame.frame_index)
                    self.frames_logged += 1
        except Exception:  # noqa: BLE001 - a bad frame must not stop the viewer
            self.book.count("tracks_frame", "rejected")
            self.book.error()
            log.exception("viewer: failed on a tracked frame")
            return
        self.book.count("tracks_frame", "processed")
        self.book.work_done(self._clock() - t0)

    # ------------------------------------------------------------ lifecycle

    def stats(self) -> dict:
        return self.book.report().figures

    def close(self) -> None:
        """Stop receiving and finish the recording; the bus stays open (its owner closes it)."""
        for ep in self._endpoints:
            try:
                ep.close()
            except Exception:  # noqa: BLE001 - keep closing the rest
                log.exception("viewer: closing an endpoint")
        self._endpoints.clear()
        if self.token is not None:
            self.token.undeclare()
            self.token = None
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self.rec.flush()
            self.rec.disconnect()
        log.info("viewer closed: %s", self.stats())
