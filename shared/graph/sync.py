"""Keeping a graph replica in step with fusion, without Zenoh (the query node wires it).

Deltas come in order with consecutive ``graph_seq``. A receiver that joins late, or misses a
delta, cannot apply what follows: it asks fusion for a snapshot and, until the snapshot is
in, holds the deltas that keep arriving (bounded) so none is lost in between. While it waits
it reports itself out of sync, and the query service refuses to answer from a graph it knows
to be behind rather than serve a stale one.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from shared.graph.scene import ApplyResult, GraphReplica
from shared.messages.graph import GraphDelta, GraphSnapshot

log = logging.getLogger(__name__)

MAX_HELD = 512
"""Deltas held while a snapshot is on its way; beyond this the oldest go, which only means
the snapshot must be newer than them (a later request fixes it)."""


class ReplicaSync:
    """A :class:`GraphReplica` fed deltas and snapshots from any thread.

    ``on_change(replica)`` is called, under the lock, after every change that leaves the
    replica consistent, so the caller can rebuild what it derives from it.
    """

    def __init__(self, on_change: Callable[[GraphReplica], None] | None = None) -> None:
        self.replica = GraphReplica()
        self._held: list[GraphDelta] = []
        self._lock = threading.Lock()
        self._synced = threading.Event()
        self._on_change = on_change
        self.deltas = 0
        self.snapshots = 0
        self.gaps = 0

    @property
    def synced(self) -> bool:
        return self._synced.is_set()

    @property
    def graph_seq(self) -> int:
        return self.replica.graph_seq

    def wait_synced(self, timeout: float) -> bool:
        return self._synced.wait(timeout)

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
                self._hold(delta)
                log.info("graph delta %d after %d: resynchronising", delta.graph_seq, self.replica.graph_seq)
                return True
            if result is ApplyResult.APPLIED:
                self.deltas += 1
                self._changed()
            return False

    def on_snapshot(self, snap: GraphSnapshot) -> bool:
        """Install a snapshot and the held deltas after it; True if now in sync."""
        with self._lock:
            if self._synced.is_set() and snap.graph_seq <= self.replica.graph_seq:
                return True  # a late answer to an old request: the deltas are ahead of it
            self.replica.apply_snapshot(snap)
            self.snapshots += 1
            held, self._held = sorted(self._held, key=lambda d: d.graph_seq), []
            ok = True
            for d in held:
                if d.graph_seq <= self.replica.graph_seq:
                    continue
                if self.replica.apply_delta(d) is ApplyResult.NEED_SNAPSHOT:
                    ok = False  # the snapshot is older than a missing delta: ask again
                    self._held = [x for x in held if x.graph_seq >= d.graph_seq]
                    break
                self.deltas += 1
            if ok:
                self._synced.set()
                log.info("graph replica in sync at version %d (%d segments)", self.replica.graph_seq, len(self.replica.segments))
            self._changed()
            return ok

    def _hold(self, delta: GraphDelta) -> None:
        self._held.append(delta)
        if len(self._held) > MAX_HELD:
            del self._held[: len(self._held) - MAX_HELD]

    def _changed(self) -> None:
        if self._on_change is not None:
            self._on_change(self.replica)
