"""Watching a running system through its ``ServiceStatus`` reports: the live figures of
``trackgraph launch``'s table and of ``trackgraph status``.

Every service publishes a report on ``trackgraph/<robot>/status/<service>`` once a second
(and a last one at stop). :class:`StatusWatch` keeps the newest report of each service, with
when it came; the functions below turn a report into the table's cells (rate, drops, queue
depth, progress with an ETA) and the whole set into a table or JSON. Nothing here reads log
text, and nothing imports Zenoh: the watch subscribes through any :class:`~shared.runtime.bus.Bus`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from shared.messages.base import Envelope
from shared.messages.status import ServiceStatus
from shared.topics import Topics, service_names

STALE_S = 3.0
"""A report older than this is shown dimmed: the service has stopped reporting (a report
comes once a second)."""
GATHER_S = 1.5
"""``trackgraph status --once`` listens this long after the first report, so every running
service (one report a second each) is in the table."""


class MonitorError(RuntimeError):
    """No service answered, or they stopped answering."""


class StatusWatch:
    """The newest :class:`ServiceStatus` of each service of ``robot_id``, subscribed on ``bus``."""

    def __init__(self, bus: Any, robot_id: str, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.robot_id = robot_id
        self.key = Topics(robot_id).status_all
        self._clock = clock
        self._latest: dict[str, tuple[ServiceStatus, float]] = {}
        self._cv = threading.Condition()
        self.received = 0
        self.rejected = 0
        self._sub = bus.subscribe(self.key, ServiceStatus, self._on_status, capacity=256, name="status:watch",
                                  on_reject=self._on_reject)  # fmt: skip

    def _on_status(self, env: Envelope[ServiceStatus]) -> None:
        with self._cv:
            self._latest[env.body.service] = (env.body, self._clock())
            self.received += 1
            self._cv.notify_all()

    def _on_reject(self, _why: str) -> None:
        with self._cv:
            self.rejected += 1

    def latest(self) -> dict[str, tuple[ServiceStatus, float]]:
        """Service -> (newest report, its age in seconds)."""
        now = self._clock()
        with self._cv:
            return {name: (st, max(now - t, 0.0)) for name, (st, t) in self._latest.items()}

    def get(self, service: str) -> tuple[ServiceStatus, float] | None:
        return self.latest().get(service)

    def wait(self, count: int = 1, timeout: float = 5.0) -> bool:
        """Wait until ``count`` reports in all have come; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while self.received < count:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
            return True

    def close(self) -> None:
        self._sub.close()


# ---------------------------------------------------------------------- figures


def drops(st: ServiceStatus) -> int:
    """Messages the service lost: every input's ``dropped``, plus the source's own ``dropped``
    figure (frames it was too late to send)."""
    own = st.figures.get("dropped")
    return sum(i.dropped for i in st.inputs) + (own if isinstance(own, int) and not isinstance(own, bool) else 0)


def queue_depth(st: ServiceStatus) -> int:
    return sum(i.queue_depth for i in st.inputs)


def frame_rate(st: ServiceStatus) -> float | None:
    """Frames (work items) a second: the recent rate, else the average since the start."""
    if st.rate_hz > 0:
        return st.rate_hz
    if st.frames_done and st.uptime_s > 0:
        return st.frames_done / st.uptime_s
    return None


def eta_s(st: ServiceStatus) -> float | None:
    """Seconds until ``frames_expected`` at the current rate; 0 when done, None when unknown."""
    if st.frames_done is None or st.frames_expected is None:
        return None
    left = st.frames_expected - st.frames_done
    if left <= 0:
        return 0.0
    rate = frame_rate(st)
    return left / rate if rate else None


def fmt_rate(hz: float) -> str:
    """Three significant digits at most: 12.3, 4.56, 0.0456."""
    if hz <= 0:
        return "0"
    return f"{hz:.0f}" if hz >= 100 else f"{hz:.3g}"


def fmt_duration(seconds: float) -> str:
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def progress_text(st: ServiceStatus) -> str:
    """``done/total (pct%), ETA ...``; ``done frames`` without a total; ``-`` where the service
    handles no frames."""
    done, total = st.frames_done, st.frames_expected
    if done is None:
        return "-"
    if total is None or total <= 0:
        return f"{done} frames"
    pct = 100.0 * min(done / total, 1.0)
    text = f"{done}/{total} ({pct:.0f}%)"
    if done >= total:
        return text + " done"
    eta = eta_s(st)
    return text + (f", ETA {fmt_duration(eta)}" if eta is not None else "")


def with_source_total(st: ServiceStatus, source: ServiceStatus | None) -> ServiceStatus:
    """A stage downstream of the source (tracker, fusion) learns how many frames it gets in
    all only at the end of the sequence; until then its total is the frames the source will
    send, less those the source has dropped."""
    if st.frames_done is None or st.frames_expected is not None or source is None or source is st or not source.frames_expected:
        return st
    return st.model_copy(update={"frames_expected": max(source.frames_expected - drops(source), 0)})


def report_cells(st: ServiceStatus | None) -> dict[str, str]:
    """The table's report columns for one service; dashes before its first report."""
    if st is None:
        return {"Hz": "-", "drops": "-", "queue": "-", "progress": "-"}
    return {"Hz": fmt_rate(st.rate_hz), "drops": str(drops(st)), "queue": str(queue_depth(st)), "progress": progress_text(st)}


def report_summary(st: ServiceStatus) -> dict[str, Any]:
    """A report's headline figures (``--json`` outputs)."""
    eta = eta_s(st)
    return {
        "state": st.state, "rate_hz": st.rate_hz, "dropped": drops(st), "queue_depth": queue_depth(st),
        "frames_done": st.frames_done, "frames_expected": st.frames_expected,
        "eta_s": None if eta is None else round(eta, 1), "errors": st.errors, "stale_s": st.stale_s,
    }  # fmt: skip


def ordered(names: list[str] | set[str]) -> list[str]:
    """Services in pipeline order (source first), unknown names after them."""
    rank = {n: i for i, n in enumerate(service_names())}
    return sorted(names, key=lambda n: (rank.get(n, len(rank)), n))


def status_table(latest: dict[str, tuple[ServiceStatus, float]], *, title: str = "trackgraph status"):
    """A rich Table of every reporting service (``trackgraph status``)."""
    from rich.table import Table

    t = Table(title=title, header_style="bold")
    for col in ("service", "state", "pid", "up", "Hz", "drops", "queue", "p50 ms", "p99 ms", "errors", "progress", "report"):
        t.add_column(col, justify="right" if col in ("pid", "Hz", "drops", "queue", "p50 ms", "p99 ms", "errors") else "left")
    colours = {"running": "green", "finished": "cyan", "starting": "yellow", "stopped": "white"}
    source = latest["source"][0] if "source" in latest else None
    for name in ordered(set(latest)):
        st, age = latest[name]
        cells = report_cells(with_source_total(st, source))
        style = "dim" if age > STALE_S else None
        t.add_row(
            name, f"[{colours.get(st.state, 'white')}]{st.state}[/]", str(st.pid), fmt_duration(st.uptime_s),
            cells["Hz"], cells["drops"], cells["queue"],
            "-" if st.latency_p50_ms is None else f"{st.latency_p50_ms:.1f}", "-" if st.latency_p99_ms is None else f"{st.latency_p99_ms:.1f}",
            str(st.errors), cells["progress"], f"{age:.1f} s ago" + (f", busy {st.stale_s:.1f} s" if st.stale_s else ""), style=style,
        )  # fmt: skip
    return t


def status_json(latest: dict[str, tuple[ServiceStatus, float]], robot_id: str) -> dict[str, Any]:
    """``trackgraph status --json``: each service's whole report, its age and headline figures."""
    return {
        "robot": robot_id,
        "services": {
            name: {**latest[name][0].model_dump(mode="json"), "age_s": round(latest[name][1], 2), "summary": report_summary(latest[name][0])}
            for name in ordered(set(latest))
        },
    }


# ---------------------------------------------------------------------- trackgraph status


def run_status(
    transport: Any,
    robot_id: str,
    *,
    once: bool = False,
    as_json: bool = False,
    timeout: float = 5.0,
    stop: threading.Event | None = None,
    out: Any = None,
) -> int:
    """``trackgraph status``: the live table (or JSON) of every service of ``robot_id`` that
    reports on the network ``transport`` joins. MonitorError if none does within ``timeout``
    seconds, or (live) once none has for that long."""
    import json
    import sys

    from rich.console import Console

    from shared.transport import ZenohBus

    if timeout <= 0:
        raise MonitorError(f"--timeout must be positive, got {timeout}")
    out = out or sys.stdout
    stop = stop or threading.Event()
    # A client that cannot reach its router within the timeout fails, rather than wait forever.
    transport = transport.model_copy(update={"connect_timeout_s": float(timeout)})
    bus = ZenohBus.open(transport, robot_id)
    watch = None
    try:
        watch = StatusWatch(bus, robot_id)
        where = ", ".join(transport.connect or transport.listen) or "the network"
        if not watch.wait(1, timeout):
            raise MonitorError(f"no service of robot {robot_id!r} reported on {watch.key} within {timeout:g} s (is the system running? connected to {where})")
        tty = hasattr(out, "isatty") and out.isatty()
        console = Console(file=out, width=None if tty else 160)  # a pipe gets the whole table, unwrapped

        def show() -> None:
            latest = watch.latest()
            if as_json:
                print(json.dumps(status_json(latest, robot_id)), file=out, flush=True)
            else:
                console.print(status_table(latest, title=f"trackgraph status: robot {robot_id} ({where})"))

        if once:
            stop.wait(GATHER_S)
            show()
            return 0
        live = None
        if not as_json and tty:
            from rich.live import Live

            live = Live(status_table(watch.latest()), console=console, refresh_per_second=2)
            live.start()
        try:
            while not stop.wait(1.0):
                latest = watch.latest()
                newest = min((age for _, age in latest.values()), default=float("inf"))
                if newest > timeout:
                    raise MonitorError(f"no status report from robot {robot_id!r} for {timeout:g} s: the system has stopped or is unreachable")
                if live is not None:
                    live.update(status_table(latest, title=f"trackgraph status: robot {robot_id} ({where})"))
                else:
                    show()
        finally:
            if live is not None:
                live.stop()
        return 0
    finally:
        if watch is not None:
            watch.close()
        bus.close()
