"""Counting what a service does, and turning it into a :class:`ServiceStatus`.

A session owns one :class:`StatusBook`. Inputs, outputs, work-item latencies and the
service's own figures go in as they happen (from any thread); :meth:`StatusBook.report`
makes the message a node publishes once a second and writes as ``status.json`` at stop.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from shared.io import atomic_write_text
from shared.messages.status import InputCounters, ServiceState, ServiceStatus

log = logging.getLogger(__name__)

RATE_WINDOW_S = 5.0
"""Rates are counted over the last this many seconds: long enough to smooth a keyframe's
pause, short enough that the launcher's table shows a stall within seconds."""
LATENCY_WINDOW = 512
"""Latency percentiles are over the last this many work items."""


class _Rate:
    """Events per second over the last ``RATE_WINDOW_S``."""

    def __init__(self) -> None:
        self._times: collections.deque[float] = collections.deque()

    def tick(self, now: float, n: int = 1) -> None:
        for _ in range(n):
            self._times.append(now)
        self._trim(now)

    def _trim(self, now: float) -> None:
        while self._times and now - self._times[0] > RATE_WINDOW_S:
            self._times.popleft()

    def hz(self, now: float, started: float) -> float:
        self._trim(now)
        span = min(RATE_WINDOW_S, max(now - started, 1e-3))
        return len(self._times) / span


class _Input:
    def __init__(self) -> None:
        self.counts = {"received": 0, "processed": 0, "rejected": 0, "dropped": 0}
        self.rate = _Rate()
        self.depth: Callable[[], int] | None = None


class StatusBook:
    """Thread-safe counters of one service; ``clock`` is injectable for tests."""

    def __init__(self, service: str, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.service = service
        self.clock = clock
        self.started = clock()
        self.state: ServiceState = "starting"
        self.frames_done: int | None = None
        self.frames_expected: int | None = None
        self.errors = 0
        self._inputs: dict[str, _Input] = {}
        self._published: dict[str, int] = {}
        self._work = _Rate()
        self._latency: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)
        self._figures: dict[str, Callable[[], Any] | Any] = {}
        self._lock = threading.Lock()

    # ---------------------------------------------------------------- counting

    def _input(self, name: str) -> _Input:
        inp = self._inputs.get(name)
        if inp is None:
            inp = self._inputs[name] = _Input()
        return inp

    def declare_input(self, name: str, depth: Callable[[], int] | None = None) -> None:
        """Make an input known (reported with zero counts) and how to read its queue depth."""
        with self._lock:
            self._input(name).depth = depth

    def count(self, name: str, what: str, n: int = 1) -> None:
        """Add ``n`` to input ``name``'s ``what``: received, processed, rejected or dropped."""
        with self._lock:
            inp = self._input(name)
            if what not in inp.counts:
                raise ValueError(f"unknown counter {what!r}; expected one of {', '.join(inp.counts)}")
            inp.counts[what] += n
            if what == "received":
                inp.rate.tick(self.clock(), n)

    def published(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._published[name] = self._published.get(name, 0) + n

    def work_done(self, seconds: float) -> None:
        """One work item (a frame, a keyframe, a query) finished after ``seconds``."""
        with self._lock:
            self._latency.append(float(seconds))
            self._work.tick(self.clock())

    def error(self) -> None:
        with self._lock:
            self.errors += 1

    def figure(self, name: str, value: Callable[[], Any] | Any) -> None:
        """A service-specific figure: a JSON-compatible value, or a callable read at report time."""
        with self._lock:
            self._figures[name] = value

    def set_state(self, state: ServiceState) -> None:
        with self._lock:
            self.state = state

    def progress(self, done: int | None = None, expected: int | None = None) -> None:
        with self._lock:
            if done is not None:
                self.frames_done = int(done)
            if expected is not None:
                self.frames_expected = int(expected)

    def counts(self, name: str) -> dict[str, int]:
        with self._lock:
            return dict(self._input(name).counts)

    # ---------------------------------------------------------------- reporting

    def report(self, state: ServiceState | None = None) -> ServiceStatus:
        now = self.clock()
        with self._lock:
            lat = np.asarray(self._latency, np.float64) * 1000.0
            inputs = [
                InputCounters(
                    name=name, **inp.counts, rate_hz=round(inp.rate.hz(now, self.started), 3),
                    queue_depth=max(int(inp.depth()), 0) if inp.depth is not None else 0,
                )
                for name, inp in sorted(self._inputs.items())
            ]  # fmt: skip
            figures = {k: (v() if callable(v) else v) for k, v in self._figures.items()}
            return ServiceStatus(
                service=self.service,
                pid=os.getpid(),
                state=state or self.state,
                uptime_s=round(max(now - self.started, 0.0), 3),
                inputs=inputs,
                published=dict(self._published),
                rate_hz=round(self._work.hz(now, self.started), 3),
                latency_p50_ms=round(float(np.percentile(lat, 50)), 3) if lat.size else None,
                latency_p99_ms=round(float(np.percentile(lat, 99)), 3) if lat.size else None,
                frames_done=self.frames_done,
                frames_expected=self.frames_expected,
                errors=self.errors,
                figures=_jsonable(figures),
            )


def _jsonable(value: Any) -> Any:
    """Figures as plain JSON values (numpy scalars and tuples included)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"status figure of type {type(value).__name__} is not JSON-compatible")


STATUS_FILE_SUFFIX = ".status.json"
"""A service's last report is written as ``<log dir>/<service>.status.json`` at stop."""


def status_path(log_dir: Path, service: str) -> Path:
    return Path(log_dir) / f"{service}{STATUS_FILE_SUFFIX}"


def write_status(path: Path, status: ServiceStatus) -> None:
    """``status.json``: the report as JSON, written atomically."""
    atomic_write_text(Path(path), json.dumps(status.model_dump(mode="json"), indent=2))


def read_status(path: Path) -> ServiceStatus:
    """A ``status.json`` back as a :class:`ServiceStatus`; ValueError naming the file if it is not one."""
    path = Path(path)
    try:
        return ServiceStatus.model_validate(json.loads(path.read_text()))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a ServiceStatus report ({exc})") from None


REPORT_PERIOD_S = 0.5
"""Seconds between two status reports. Consumers are promised one at least every second; a
busy fusion process on two cores was measured holding a report back by up to 0.65 s, so
reports go out twice as often as promised."""


class StatusReporter:
    """Publishes a book's report on ``key`` every ``period_s`` from a thread of its own, and a
    last one at :meth:`stop` (also written to ``status_file`` when given).

    With ``heartbeat`` (the service's transport settings) the reports go out through a
    heartbeat process of the service's own (:mod:`shared.runtime.heartbeat`), which keeps
    them coming while a native call holds this process's interpreter. Until that process is
    up, and if it goes, this thread publishes them itself."""

    def __init__(self, book: StatusBook, bus: Any, key: str, *, period_s: float = REPORT_PERIOD_S, heartbeat: Any = None) -> None:
        self.book, self.key, self.period_s = book, key, period_s
        self._pub = bus.publisher(key, ServiceStatus)
        self.sidecar = None
        if heartbeat is not None:
            from shared.runtime.heartbeat import StatusSidecar

            try:
                self.sidecar = StatusSidecar(heartbeat, bus.robot_id, key, period_s=period_s)
            except OSError as exc:
                log.warning("%s: no status heartbeat (%s); reports go out from the service", book.service, exc)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"status:{book.service}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.publish()

    def _put(self, report: ServiceStatus) -> None:
        if self.sidecar is None or not self.sidecar.send(report):
            self._pub.put(report)

    def publish(self, state: ServiceState | None = None) -> ServiceStatus | None:
        try:
            report = self.book.report(state)
            self._put(report)
            return report
        except Exception:  # noqa: BLE001 - a status report must never take the service down
            log.warning("%s: status report not sent", self.book.service, exc_info=True)
            return None

    def stop(self, status_file: Path | None = None) -> ServiceStatus:
        """The final report, state ``stopped``: published, and written to ``status_file``."""
        self._stop.set()
        self._thread.join(timeout=5)
        report = self.book.report("stopped")
        took = self.sidecar is not None and self.sidecar.close(report)
        if not took:
            try:
                self._pub.put(report)
            except Exception:  # noqa: BLE001 - the session may be going; the file still gets it
                pass
        if status_file is not None:
            write_status(status_file, report)
        self._pub.close()
        return report
