"""What a node adds to its session: a bus that delivers on its own threads (Zenoh), and a
thread of its own driving the session's ``tick(now)``. In one process the caller drives the
session itself, over the in-process bus."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)


class Ticker:
    """Calls ``tick(time.monotonic())`` at once and then every ``period_s`` until
    :meth:`stop`; a failed tick is logged, reported to ``on_error`` and retried next time."""

    def __init__(self, tick: Callable[[float], object], period_s: float, *, name: str,
                 on_error: Callable[[], None] | None = None) -> None:  # fmt: skip
        if period_s <= 0:
            raise ValueError("period_s must be positive")
        self._tick, self.period_s, self._on_error = tick, period_s, on_error
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                self._tick(time.monotonic())
            except Exception:  # noqa: BLE001 - a failed tick is retried on the next one
                if self._on_error is not None:
                    self._on_error()
                log.exception("%s: tick failed", self._thread.name)
            if self._stop.wait(self.period_s):
                return

    def stop(self, timeout: float | None = None) -> None:
        """Stop ticking; waits up to ``timeout`` for a tick in progress (a request may be in flight)."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)


class SessionNode:
    """A session on ``bus`` (``make_session(bus)``, which has ``book``, ``tick(now)`` and
    ``close()``), ticked every ``tick_s`` seconds. What ``trackgraph serve`` needs of a node:
    ``book``, ``bus``, ``close(keep_bus=False)``. If the session cannot be made, the bus is
    closed and the error raised."""

    def __init__(self, bus: Any, make_session: Callable[[Any], Any], *, name: str, tick_s: float, stop_timeout_s: float) -> None:
        self.bus = bus
        try:
            self.session = make_session(bus)
        except BaseException:
            bus.close()
            raise
        self.book = self.session.book
        self._stop_timeout_s = stop_timeout_s
        self._ticker = Ticker(self.session.tick, tick_s, name=f"{name}:tick", on_error=self.book.error)
        self._closed = False

    def close(self, keep_bus: bool = False) -> None:
        """Stop ticking and close the session; with ``keep_bus`` the bus stays open (for the
        last status report; its owner closes it). Calling it again does nothing."""
        if self._closed:
            return
        self._closed = True
        self._ticker.stop(timeout=self._stop_timeout_s)  # a snapshot request may be in flight
        self.session.close()
        if not keep_bus:
            self.bus.close()
