"""A service's status reports sent by a small process of its own.

A thread of the service cannot publish while a native call holds the interpreter: Open3D's
voxel-block grid, when it doubles, keeps it 0.6 s on this machine's two cores and 1.7 s on a
busy CI runner, with more blocks longer. Consumers are promised a report at least once a
second, so a service can hand its reports to a heartbeat process
(``python -m shared.runtime.heartbeat``) over a pipe. The heartbeat forwards each report as
it comes, and when none has come for a period it sends the last one again with its uptime
advanced and ``stale_s`` saying how old its figures are. The process is alive (it holds the
pipe) but busy; a consumer that sees ``stale_s`` grow knows it is hung, not gone. When the
service's process ends, the pipe closes and the heartbeat exits.

:class:`Heartbeat` is the decision (no I/O); :class:`StatusSidecar` is the service's end of
the pipe; :func:`main` is the heartbeat process, the only part that opens a Zenoh session.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from shared.messages.status import ServiceStatus

log = logging.getLogger(__name__)

READY = "ready"
"""What the heartbeat prints on its stdout once it can publish."""
START_TIMEOUT_S = 30.0
"""How long the service publishes its reports itself while its heartbeat starts; after that
it gives up on the heartbeat and goes on publishing itself."""


class Heartbeat:
    """Which report goes out when: every report received is sent at once; with none for
    ``period_s``, the last one again, aged by the time since it came."""

    def __init__(self, period_s: float) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be positive")
        self.period_s = float(period_s)
        self._last: ServiceStatus | None = None
        self._last_at = 0.0
        self._sent_at = 0.0
        self.resent = 0

    def received(self, report: ServiceStatus, now: float) -> ServiceStatus:
        """A fresh report from the service: the one to send now."""
        self._last, self._last_at, self._sent_at = report, now, now
        return report

    def tick(self, now: float) -> ServiceStatus | None:
        """The last report aged to ``now`` when a period has passed without one; else None."""
        if self._last is None or self._last.state == "stopped" or now - self._sent_at < self.period_s:
            return None
        age = max(now - self._last_at, 0.0)
        self._sent_at = now
        self.resent += 1
        return self._last.model_copy(update={"uptime_s": round(self._last.uptime_s + age, 3), "stale_s": round(self._last.stale_s + age, 3)})


def heartbeat_transport(transport: Any) -> dict:
    """The heartbeat's transport: the service's, but never listening. It connects where the
    service connects, and to the service's own listening endpoints (a peer that others join)."""
    doc = transport.model_dump(mode="json")
    listen = [ep.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]") for ep in doc.get("listen", [])]
    doc["connect"] = list(dict.fromkeys([*doc.get("connect", []), *listen]))
    doc["listen"] = []
    if doc.get("mode") == "router":
        doc["mode"] = "client"
    return doc


class StatusSidecar:
    """The service's end of its heartbeat: starts the process, then :meth:`send` writes each
    report down the pipe. ``ready`` is False until the heartbeat can publish and again after
    it has gone; the caller publishes itself meanwhile."""

    def __init__(self, transport: Any, robot_id: str, key: str, *, period_s: float) -> None:
        self.key = key
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self._dead = False
        root = str(Path(__file__).resolve().parents[2])  # the folder holding ``shared``
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p))
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "shared.runtime.heartbeat"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None, env=env, close_fds=True,
        )  # fmt: skip
        header = {"transport": heartbeat_transport(transport), "robot_id": robot_id, "key": key, "period_s": period_s}
        self._write(json.dumps(header))
        self._waiter = threading.Thread(target=self._wait_ready, name=f"heartbeat:{key}", daemon=True)
        self._waiter.start()

    @property
    def ready(self) -> bool:
        return self._ready.is_set() and not self._dead

    def _wait_ready(self) -> None:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().decode(errors="replace").strip()
        if line == READY:
            self._ready.set()
            return
        self._dead = True
        log.warning("%s: status heartbeat did not start (exit %s); the service publishes its reports itself", self.key, self.proc.poll())

    def _write(self, line: str) -> bool:
        with self._lock:
            if self._dead or self.proc.stdin is None:
                return False
            try:
                self.proc.stdin.write(line.encode() + b"\n")
                self.proc.stdin.flush()
                return True
            except (BrokenPipeError, OSError, ValueError):
                self._dead = True
                log.warning("%s: status heartbeat has gone (exit %s); the service publishes its reports itself", self.key, self.proc.poll())
                return False

    def send(self, report: ServiceStatus) -> bool:
        """Hand one report to the heartbeat; False when it is not there to take it."""
        return self.ready and self._write(report.model_dump_json())

    def wait_ready(self, timeout: float) -> bool:
        return self._ready.wait(timeout) and not self._dead

    def close(self, final: ServiceStatus | None = None, timeout: float = 10.0) -> bool:
        """Send ``final`` (when the heartbeat is up), close the pipe and wait for the process;
        True if the heartbeat took ``final``."""
        took = final is not None and self.send(final)
        with self._lock:
            self._dead = True
            if self.proc.stdin is not None:
                try:
                    self.proc.stdin.close()
                except OSError:
                    pass
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("%s: status heartbeat did not exit in %.0f s; killed", self.key, timeout)
            self.proc.kill()
            self.proc.wait()
            took = False
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return took and self.proc.returncode == 0


def main() -> int:
    """The heartbeat process: a JSON header line on stdin (transport, robot_id, key,
    period_s), then one ServiceStatus JSON per line until end of input."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)-7s heartbeat: %(message)s", datefmt="%H:%M:%S")
    from shared.config.transport import TransportConfig
    from shared.transport import ZenohBus

    stdin = sys.stdin.buffer
    try:
        header = json.loads(stdin.readline())
        transport = TransportConfig.model_validate(header["transport"])
        robot_id, key, period_s = str(header["robot_id"]), str(header["key"]), float(header["period_s"])
    except (ValueError, KeyError, TypeError) as exc:
        log.error("bad header on stdin: %s", exc)
        return 2
    try:
        bus = ZenohBus.open(transport, robot_id)
    except Exception as exc:  # noqa: BLE001 - the service publishes itself when this one cannot
        log.error("%s: %s", key, exc)
        return 1
    beat = Heartbeat(period_s)
    lock = threading.Lock()
    done = threading.Event()
    bad = 0
    try:
        pub = bus.publisher(key, ServiceStatus)

        def put(report: ServiceStatus | None) -> None:
            if report is None:
                return
            try:
                pub.put(report)
            except Exception:  # noqa: BLE001 - one lost report; the next period sends again
                log.warning("%s: report not sent", key, exc_info=True)

        def read() -> None:
            nonlocal bad
            for line in stdin:
                try:
                    report = ServiceStatus.model_validate_json(line)
                except ValueError as exc:
                    bad += 1
                    log.warning("%s: line %d from the service is not a ServiceStatus (%s)", key, bad, str(exc).splitlines()[0])
                    continue
                with lock:
                    put(beat.received(report, time.monotonic()))
            done.set()

        reader = threading.Thread(target=read, name="heartbeat:read", daemon=True)
        reader.start()
        sys.stdout.write(READY + "\n")
        sys.stdout.flush()
        while not done.wait(period_s / 4):
            with lock:
                put(beat.tick(time.monotonic()))
        reader.join()
    finally:
        bus.close()
    if beat.resent:
        log.info("%s: %d reports sent again while the service was busy", key, beat.resent)
    return 0


if __name__ == "__main__":
    sys.exit(main())
