"""fusion's map path (``fusion.map_path``): graph updates beside the frame path.

The frame path (decode, journal, vote, integrate, acknowledge) runs on the session's thread.
With ``sync`` the core also updates the graph there, every ``mesh_every_n_frames`` frames:
updates happen at fixed frames, so a replay's map equals the in-process one, and a frame
that triggers an update waits for it. With ``async`` the frame path only captures what an
update reads (:meth:`FusionCore.capture_update <services.fusion.core.FusionCore.capture_update>`:
the active window's mesh and copies of tracks, trajectory and keyframe views), and a map
thread builds segments, re-identification, places, rooms and the delta from that capture
(:meth:`~services.fusion.core.FusionCore.build_update`) while later frames are fused. One
update runs at a time; the next is captured when it is done and ``mesh_every_n_frames``
frames came since, so a loaded fusion updates less often instead of holding frames back.

The map thread touches only map-path state (segments, surface sample, places, rooms, the
graph) and never the bus: finished deltas wait in order until the session's thread takes
them (:meth:`MapPath.take`, after every frame and tick). Whatever else reads or moves
map-path state (pose corrections, snapshots, the end of the map) waits for the running
update first (:meth:`MapPath.join`).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Literal, Protocol

if TYPE_CHECKING:
    from services.fusion.core import UpdateInput
    from shared.config.root import TrackGraphConfig
    from shared.messages.graph import GraphDelta

log = logging.getLogger(__name__)


def resolve_map_path(cfg: TrackGraphConfig) -> Literal["sync", "async"]:
    """``fusion.map_path`` for this config: ``auto`` is ``async`` for a live source."""
    mode = cfg.fusion.map_path
    if mode == "auto":
        return "async" if cfg.source.mode == "live" else "sync"
    return mode


class UpdatingCore(Protocol):
    """What the map path drives (:class:`~services.fusion.core.FusionCore`)."""

    frames: int
    sync_updates: bool

    def capture_update(self) -> UpdateInput: ...

    def build_update(self, inp: UpdateInput) -> GraphDelta: ...


class MapPath:
    """Graph updates of ``core``: on the frame path (``sync``) or on a map thread (``async``)."""

    def __init__(self, core: UpdatingCore, mode: Literal["sync", "async"], every_n_frames: int) -> None:
        if mode not in ("sync", "async"):
            raise ValueError(f"fusion.map_path: expected 'sync' or 'async', got {mode!r}")
        self.core, self.mode, self.every_n = core, mode, int(every_n_frames)
        self.updates = 0
        """Updates the map thread built."""
        self.failed = 0
        """Updates whose build raised (logged; the next capture tries again)."""
        self.capture_s = 0.0
        """Frame-path time of the newest capture."""
        self.build_s = 0.0
        """Map-thread time of the newest build."""
        self._reported_failures = 0
        self._done: collections.deque[GraphDelta] = collections.deque()
        self._job: UpdateInput | None = None
        self._busy = False
        self._closing = False
        self._captured_at = core.frames
        """``core.frames`` at the newest capture."""
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        if mode == "async":
            core.sync_updates = False
            self._thread = threading.Thread(target=self._run, name="fusion-map-path", daemon=True)
            self._thread.start()

    @property
    def busy(self) -> bool:
        """An update is being built."""
        return self._busy

    def after_frame(self) -> None:
        """Frame path, after each fused frame: capture and hand over an update when one is due
        and none is running (``async``; ``sync`` updates inside ``add_frame``)."""
        if self._thread is None or self._busy or self.core.frames - self._captured_at < self.every_n:
            return
        t0 = time.perf_counter()
        self._captured_at = self.core.frames
        try:
            inp = self.core.capture_update()
        except Exception:  # noqa: BLE001 - the frame is fused; the next capture tries again
            log.exception("fusion: capturing the graph update at frame %d failed", self.core.frames)
            with self._cond:
                self.failed += 1
            return
        self.capture_s = time.perf_counter() - t0
        with self._cond:
            self._job, self._busy = inp, True
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._job is None and not self._closing:
                    self._cond.wait()
                if self._job is None:
                    return
                inp, self._job = self._job, None
            t0 = time.perf_counter()
            try:
                delta = self.core.build_update(inp)
            except Exception:  # noqa: BLE001 - one failed update must not stop the map path
                log.exception("fusion: the graph update at frame %d failed", inp.frame_index)
                with self._cond:
                    self.failed += 1
            else:
                with self._cond:
                    self._done.append(delta)
                    self.updates += 1
            finally:
                with self._cond:
                    self.build_s = time.perf_counter() - t0
                    self._busy = False
                    self._cond.notify_all()

    def join(self) -> None:
        """Wait for the running update: before a correction moves the map, a snapshot reads
        it or the map ends."""
        with self._cond:
            while self._busy:
                self._cond.wait()

    def take(self) -> tuple[list[GraphDelta], int]:
        """The deltas finished since the last call, oldest first, and how many updates failed
        since then (the session publishes the one and counts the other)."""
        with self._cond:
            out = list(self._done)
            self._done.clear()
            failed, self._reported_failures = self.failed - self._reported_failures, self.failed
        return out, failed

    def figure(self) -> dict[str, Any]:
        """The ``map_path`` status figure."""
        return {"mode": self.mode, "busy": self._busy, "updates": self.updates, "failed": self.failed,
                "capture_ms": round(1e3 * self.capture_s, 1), "build_ms": round(1e3 * self.build_s, 1)}  # fmt: skip

    def close(self) -> None:
        """Let the running update finish, then stop the map thread (its delta stays to take)."""
        if self._thread is None:
            return
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join()
        self._thread = None
