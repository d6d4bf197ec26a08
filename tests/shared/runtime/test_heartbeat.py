"""The status heartbeat: its decision without I/O, and the process keeping reports coming
while the service's interpreter is held."""

from __future__ import annotations

import ctypes
import itertools
import socket
import threading
import time

import pytest

from shared.config import TransportConfig
from shared.messages.status import ServiceStatus
from shared.runtime.heartbeat import Heartbeat, heartbeat_transport
from shared.runtime.status import StatusBook, StatusReporter


def report(uptime: float = 1.0, state: str = "running", **kw) -> ServiceStatus:
    return ServiceStatus(service="fusion", pid=123, state=state, uptime_s=uptime, frames_done=7, **kw)


def test_fresh_reports_go_at_once_and_the_last_is_resent_aged_after_a_period():
    beat = Heartbeat(0.5)
    assert beat.tick(0.0) is None  # nothing to resend before the first report
    first = report(uptime=2.0)
    assert beat.received(first, 10.0) is first
    assert beat.tick(10.4) is None  # a period has not passed
    again = beat.tick(10.6)
    assert again is not None and again.stale_s == pytest.approx(0.6) and again.uptime_s == pytest.approx(2.6)
    assert again.frames_done == 7 and again.pid == 123 and again.state == "running"
    assert beat.tick(10.9) is None  # one resend a period
    assert beat.tick(11.2).stale_s == pytest.approx(1.2)
    assert beat.received(report(uptime=3.3), 11.3).stale_s == 0.0
    assert beat.tick(11.5) is None
    assert beat.resent == 2


def test_a_stopped_service_is_not_reported_again():
    beat = Heartbeat(0.5)
    beat.received(report(state="stopped"), 0.0)
    assert beat.tick(5.0) is None


def test_the_heartbeat_connects_where_the_service_connects_and_to_where_it_listens():
    client = TransportConfig(mode="client", connect=["tcp/10.0.0.2:7447"])
    assert heartbeat_transport(client)["connect"] == ["tcp/10.0.0.2:7447"]
    peer = TransportConfig(mode="peer", connect=[], listen=["tcp/0.0.0.0:7450"])
    doc = heartbeat_transport(peer)
    assert doc["connect"] == ["tcp/127.0.0.1:7450"] and doc["listen"] == [] and doc["mode"] == "peer"
    assert TransportConfig.model_validate(doc).listen == []
    with pytest.raises(ValueError):
        Heartbeat(0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _hold_the_interpreter(seconds: float) -> None:
    """A native call that keeps the GIL, as Open3D's grid does when it doubles: libc's usleep
    through ``ctypes.PyDLL``, which does not release it."""
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


def _gaps_while_held(heartbeat: bool) -> tuple[float, list[ServiceStatus]]:
    from shared.transport import ZenohBus

    transport = TransportConfig(mode="peer", connect=[], listen=[f"tcp/127.0.0.1:{_free_port()}"], shared_memory=False)
    bus = ZenohBus.open(transport, "robot0")
    got: list[tuple[float, ServiceStatus]] = []
    lock = threading.Lock()

    def on(env) -> None:
        with lock:
            got.append((env.stamp, env.body))  # the sender's clock: when it was sent, not when this thread got the GIL

    reporter = None
    try:
        bus.subscribe("trackgraph/robot0/status/fusion", ServiceStatus, on, capacity=256)
        book = StatusBook("fusion")
        book.set_state("running")
        reporter = StatusReporter(book, bus, "trackgraph/robot0/status/fusion", period_s=0.25, heartbeat=transport if heartbeat else None)
        if heartbeat:
            assert reporter.sidecar.wait_ready(60), "the heartbeat process did not start"
        time.sleep(1.0)
        _hold_the_interpreter(1.6)
        time.sleep(1.0)
    finally:
        if reporter is not None:
            final = reporter.stop()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not any(b.state == "stopped" for _, b in got):
            time.sleep(0.05)
        bus.close()
    assert final.state == "stopped"
    with lock:
        stamps = sorted(t for t, _ in got)
        bodies = [b for _, b in got]
    assert bodies and bodies[-1].state == "stopped", [b.state for b in bodies]
    return max(b - a for a, b in itertools.pairwise(stamps)), bodies


@pytest.mark.zenoh
@pytest.mark.slow
def test_reports_keep_coming_while_a_native_call_holds_the_interpreter():
    gap, bodies = _gaps_while_held(heartbeat=True)
    assert gap < 0.7, gap
    stale = [b.stale_s for b in bodies if b.stale_s > 0]
    assert stale and max(stale) >= 1.0, stale  # the resent reports say how old their figures are
    assert all(b.pid == bodies[0].pid for b in bodies)  # the service's pid, not the heartbeat's


@pytest.mark.zenoh
@pytest.mark.slow
def test_without_the_heartbeat_the_same_hold_silences_the_reports():
    gap, bodies = _gaps_while_held(heartbeat=False)
    assert gap >= 1.4, gap
    assert all(b.stale_s == 0 for b in bodies)
