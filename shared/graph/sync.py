"""Keeping a graph replica in step with fusion, without Zenoh: the one implementation behind
the query service and the viewer.

Deltas come in order with consecutive ``graph_seq``. A receiver that joins late, or misses a
delta, cannot apply what follows: it asks fusion for a snapshot and, until the snapshot is
in, holds the deltas that keep arriving (bounded) so none is lost in between. While it waits
it reports itself out of sync, and the query service refuses to answer from a graph it knows
to be behind rather than serve a stale one.

A new :class:`ReplicaSync` wants a snapshot at once (fusion may have been mapping for a while;
a receiver there from the start is in sync by the first delta instead). The owner asks for
one by calling :meth:`ReplicaSync.resync` from its ``tick(now)``: it fetches only when one is
due, and backs off (``retry_min_s`` doubling up to ``retry_max_s``) while fusion does not
answer, so a missing fusion costs a request every few seconds, never a busy loop.

:class:`ReplicaFollower` wires one to a :class:`~shared.runtime.bus.Bus` (``graph/delta``
subscribed, ``graph/snapshot`` requested) and counts it all in the owner's
:class:`~shared.runtime.status.StatusBook`: the query service and the viewer each hold one.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

from shared.graph.scene import ApplyResult, GraphReplica
from shared.messages.base import Envelope
from shared.messages.graph import GraphDelta, GraphSnapshot, SnapshotRequest
from shared.runtime.bus import Bus, BusError
from shared.runtime.status import StatusBook
from shared.topics import Topics

log = logging.getLogger(__name__)

MAX_HELD = 512
"""Deltas held while a snapshot is on its way; beyond this the oldest go, which only means
the snapshot must be newer than them (a later request fixes it)."""
RETRY_MIN_S, RETRY_MAX_S = 0.2, 5.0
"""Backoff between snapshot requests while fusion does not answer."""

OnChange = Callable[[GraphReplica, bool], None]
"""``on_change(replica, mesh_changed)``."""


class ReplicaSync:
    """A :class:`GraphReplica` fed deltas and snapshots from any thread.

    ``on_change(replica, mesh_changed)`` is called, under the lock, after every change of the
    replica (``mesh_changed``: the change brought a mesh), so the owner can rebuild what it
    derives from it: the query's index, the viewer's recording.
    """

    def __init__(
        self,
        on_change: OnChange | None = None,
        *,
        max_held: int = MAX_HELD,
        retry_min_s: float = RETRY_MIN_S,
        retry_max_s: float = RETRY_MAX_S,
    ) -> None:
        if max_held < 1:
            raise ValueError("max_held must be at least 1")
        if not 0 < retry_min_s <= retry_max_s:
            raise ValueError("need 0 < retry_min_s <= retry_max_s")
        self.replica = GraphReplica()
        self.max_held = max_held
        self.retry_min_s, self.retry_max_s = retry_min_s, retry_max_s
        self._held: list[GraphDelta] = []
        self._lock = threading.Lock()
        self._fetching = threading.Lock()
        self._synced = threading.Event()
        self._on_change = on_change
        self._next_try = -math.inf
        self._wait = retry_min_s
        self.deltas = 0
        """Deltas applied (held ones included, once applied)."""
        self.stale = 0
        """Deltas the replica already had (a snapshot covered them)."""
        self.snapshots = 0
        self.gaps = 0
        """Times a missing delta put the replica out of sync."""
        self.requests = 0
        """Snapshot requests made."""
        self.failures = 0
        """Snapshot requests that got no answer."""

    # ---------------------------------------------------------------- state

    @property
    def synced(self) -> bool:
        return self._synced.is_set()

    @property
    def graph_seq(self) -> int:
        return self.replica.graph_seq

    @property
    def held(self) -> int:
        with self._lock:
            return len(self._held)

    def wait_synced(self, timeout: float) -> bool:
        return self._synced.wait(timeout) if timeout > 0 else self._synced.is_set()

    def due(self, now: float) -> bool:
        """True when a snapshot is wanted and the backoff allows asking at ``now``."""
        return not self._synced.is_set() and now >= self._next_try

    def figures(self) -> dict:
        """The counters, for a status report."""
        with self._lock:
            return {
                "graph_seq": self.replica.graph_seq, "synced": self._synced.is_set(), "deltas": self.deltas,
                "stale": self.stale, "snapshots": self.snapshots, "gaps": self.gaps, "held": len(self._held),
                "snapshot_requests": self.requests, "snapshot_failures": self.failures,
            }  # fmt: skip

    # ---------------------------------------------------------------- input

    def on_delta(self, delta: GraphDelta) -> bool:
        """Apply one delta; True if the replica now needs a snapshot."""
        with self._lock:
            if not self._synced.is_set() and self.replica.graph_seq == 0 and not self._held and delta.graph_seq == 1:
                self._synced.set()  # there from the start: deltas alone build the graph
            if not self._synced.is_set():
                self._hold(delta)
                return True
            result = self.replica.apply_delta(delta)
            if result is ApplyResult.NEED_SNAPSHOT:
                self.gaps += 1
                self._synced.clear()
                self._next_try, self._wait = -math.inf, self.retry_min_s  # a gap is news: ask at once
                self._hold(delta)
                log.info("graph delta %d after %d: resynchronising", delta.graph_seq, self.replica.graph_seq)
                return True
            if result is ApplyResult.STALE:
                self.stale += 1
            else:
                self.deltas += 1
                self._changed(delta.mesh is not None)
            return False

    def on_snapshot(self, snap: GraphSnapshot) -> bool:
        """Install a snapshot and the held deltas after it; True if now in sync."""
        with self._lock:
            if self._synced.is_set() and snap.graph_seq <= self.replica.graph_seq:
                return True  # a late answer to an old request: the deltas are ahead of it
            self.replica.apply_snapshot(snap)
            self.snapshots += 1
            mesh = snap.mesh is not None
            held, self._held = sorted(self._held, key=lambda d: d.graph_seq), []
            ok = True
            for d in held:
                if d.graph_seq <= self.replica.graph_seq:
                    self.stale += 1
                    continue
                if self.replica.apply_delta(d) is ApplyResult.NEED_SNAPSHOT:
                    ok = False  # the snapshot is older than a missing delta: ask again, at once
                    self._held = [x for x in held if x.graph_seq >= d.graph_seq]
                    self._next_try, self._wait = -math.inf, self.retry_min_s
                    break
                self.deltas += 1
                mesh = mesh or d.mesh is not None
            # What readers derive (the query index) is rebuilt before the replica says it is in
            # sync, so nobody waiting on ``synced`` is answered from the old derivation.
            self._changed(mesh)
            if ok:
                self._synced.set()
                log.info("graph replica in sync at version %d (%d segments)", self.replica.graph_seq, len(self.replica.segments))
            return ok

    def resync(self, now: float, fetch: Callable[[], GraphSnapshot]) -> bool | None:
        """If a snapshot is :meth:`due` at ``now``, ``fetch()`` one and install it.

        ``fetch`` raises :class:`~shared.runtime.bus.BusError` when fusion does not answer;
        the next request then waits out the backoff. Returns None when nothing was due (or
        another thread is fetching), else whether the replica is now in sync."""
        if not self.due(now) or not self._fetching.acquire(blocking=False):
            return None
        try:
            with self._lock:
                self.requests += 1
            try:
                snap = fetch()  # outside the lock: over a network it takes a round trip
            except BusError as exc:
                with self._lock:
                    self.failures += 1
                    self._next_try = now + self._wait
                    log.debug("no graph snapshot (%s); retrying in %.1f s", exc, self._wait)
                    self._wait = min(2 * self._wait, self.retry_max_s)
                return False
            with self._lock:
                self._next_try, self._wait = -math.inf, self.retry_min_s
            return self.on_snapshot(snap)
        finally:
            self._fetching.release()

    # ---------------------------------------------------------------- internals

    def _hold(self, delta: GraphDelta) -> None:
        self._held.append(delta)
        if len(self._held) > self.max_held:
            del self._held[: len(self._held) - self.max_held]

    def _changed(self, mesh_changed: bool) -> None:
        if self._on_change is not None:
            self._on_change(self.replica, mesh_changed)


class ReplicaFollower:
    """A :class:`ReplicaSync` fed from ``bus``: deltas from ``graph/delta`` (a fifo of
    ``capacity``), snapshots requested from ``graph/snapshot`` in :meth:`tick` (``with_mesh``:
    whether the owner wants the mesh in them), each within ``timeout_s``. With ``work``, each
    delta is one of the owner's work items (its rate and latency in the report).

    Counts go to ``book``: inputs ``graph_delta`` (received, processed, rejected, dropped,
    queue depth) and ``graph_snapshot`` (replies received); ``published["graph_snapshot"]``
    (requests sent); and the figures ``graph_seq``, ``synced``, ``deltas``, ``snapshots``,
    ``gaps``, ``stale``, ``snapshot_failures``.
    """

    def __init__(
        self,
        bus: Bus,
        topics: Topics,
        book: StatusBook,
        *,
        with_mesh: bool,
        timeout_s: float,
        on_change: OnChange | None = None,
        capacity: int = 64,
        name: str = "graph:delta",
        work: bool = False,
    ) -> None:
        self.bus, self.topics, self.book, self.work = bus, topics, book, work
        self.with_mesh, self.timeout_s = with_mesh, float(timeout_s)
        self.sync = ReplicaSync(on_change=on_change)
        sync = self.sync
        for fig, value in {
            "graph_seq": lambda: sync.graph_seq, "synced": lambda: sync.synced, "deltas": lambda: sync.deltas,
            "snapshots": lambda: sync.snapshots, "gaps": lambda: sync.gaps, "stale": lambda: sync.stale,
            "snapshot_failures": lambda: sync.failures,
        }.items():  # fmt: skip
            book.figure(fig, value)
        self.deltas = bus.subscribe(
            topics.graph_delta, GraphDelta, self.on_delta, capacity=capacity, name=name,
            on_drop=lambda: book.count("graph_delta", "dropped"), on_reject=lambda _why: book.count("graph_delta", "rejected"),
        )  # fmt: skip
        book.declare_input("graph_delta", self.deltas.pending)
        book.declare_input("graph_snapshot")

    def on_delta(self, env: Envelope[GraphDelta]) -> None:
        t0 = self.book.clock()
        self.book.count("graph_delta", "received")
        try:
            self.sync.on_delta(env.body)
        except Exception:  # noqa: BLE001 - one bad delta must not stop the service
            self.book.count("graph_delta", "rejected")
            self.book.error()
            log.exception("%s: failed on graph delta %d", self.book.service, env.body.graph_seq)
            return
        self.book.count("graph_delta", "processed")
        if self.work:
            self.book.work_done(self.book.clock() - t0)

    def tick(self, now: float) -> bool | None:
        """Ask fusion for a snapshot if the replica needs one and the backoff allows it;
        returns :meth:`ReplicaSync.resync`'s answer."""
        return self.sync.resync(now, self._fetch)

    def _fetch(self) -> GraphSnapshot:
        self.book.published("graph_snapshot")
        snap = self.bus.request(self.topics.graph_snapshot, SnapshotRequest(with_mesh=self.with_mesh), GraphSnapshot, timeout=self.timeout_s)
        self.book.count("graph_snapshot", "received")
        self.book.count("graph_snapshot", "processed")
        return snap

    def close(self) -> None:
        self.deltas.close()
