"""A process's stop signals, and the lifeline that ends a launched service with its launcher.

Every long-running command (``trackgraph launch``, ``serve``, ``source``, ``router``) treats
SIGINT, SIGTERM and SIGHUP alike: an orderly stop. SIGHUP is what a closing terminal sends;
left at its default it ended the launcher without its cleanup and orphaned every service.

A service started by ``trackgraph launch`` finds the launcher's pid in
:data:`LAUNCHER_PID_ENV` and ends with it even when the launcher gets no chance to clean up
(SIGKILL, the OOM killer, a crash), two ways:

- On Linux, ``prctl(PR_SET_PDEATHSIG, SIGTERM)``: the kernel sends SIGTERM the moment the
  parent goes, and the stop handler stops the service in order. It is set by the service
  itself at start, not in the launcher between fork and exec (``preexec_fn`` is unsafe in a
  launcher that runs Zenoh threads), so the service then checks that its parent is still the
  launcher: one that died before the prctl would never signal.
  The kernel fires it when the *thread* that forked the child exits; the launcher spawns
  every service from the thread that supervises, which lives until it has stopped them all.
- Everywhere, a watch thread polls ``os.getppid()`` every :data:`WATCH_PERIOD_S`: an orphan
  is re-parented (to init or a subreaper), so a changed parent means the launcher is gone.
  This is the only mechanism where prctl does not exist (macOS, Windows), and on Linux it
  bounds the stop when something ignores the signal. When the orderly stop has not ended the
  process :data:`LAUNCHER_GRACE_ENV` seconds after the launcher went (the launcher's own
  ``stop_timeout_s``), the watch ends it with ``os._exit``, as the launcher would have
  SIGKILLed it.

A service run any other way (systemd, Docker, a shell) has no :data:`LAUNCHER_PID_ENV` and
no lifeline: its parent's fate is never a reason to stop. No zenoh here (ruff TID251).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

LAUNCHER_PID_ENV = "TRACKGRAPH_LAUNCHER_PID"
"""Set by ``trackgraph launch`` in each service's environment: the launcher's pid."""
LAUNCHER_GRACE_ENV = "TRACKGRAPH_LAUNCHER_GRACE_S"
"""Set by ``trackgraph launch``: how long an orphaned service may take over its orderly stop."""
WATCH_PERIOD_S = 0.5
"""How often the watch looks at the parent pid: a launcher's death is noticed within this
even where no parent-death signal exists (one getppid() call, nothing measurable)."""
DEFAULT_GRACE_S = 30.0
"""Grace when the launcher named none: the launch file's default ``stop_timeout_s``."""
PR_SET_PDEATHSIG = 1
"""From <linux/prctl.h>."""

STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)
"""The signals that mean "stop in order" (SIGHUP does not exist on Windows)."""


def install_stop_handlers(on_stop: Callable[[], None]) -> bool:
    """Route every stop signal to ``on_stop``; False (nothing done) off the main thread,
    where Python cannot install handlers (a service run inside a test or another program)."""
    if threading.current_thread() is not threading.main_thread():
        return False
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda *_: on_stop())
    return True


def launcher_pid(environ: dict[str, str] | None = None) -> int | None:
    """The launcher's pid from the environment, or None when not launched by it (or garbled)."""
    raw = (os.environ if environ is None else environ).get(LAUNCHER_PID_ENV, "").strip()
    if not raw:
        return None
    try:
        pid = int(raw)
    except ValueError:
        log.warning("%s=%r is not a pid: no launcher lifeline", LAUNCHER_PID_ENV, raw)
        return None
    # pid 1 (a container whose entrypoint is the launcher) is nobody's lifeline: when it dies the
    # kernel ends the whole container, and an orphan's parent would be 1 again.
    return pid if pid > 1 else None


def _grace_s(environ: dict[str, str] | None = None) -> float:
    raw = (os.environ if environ is None else environ).get(LAUNCHER_GRACE_ENV, "")
    try:
        return max(float(raw), 0.0) if raw else DEFAULT_GRACE_S
    except ValueError:
        return DEFAULT_GRACE_S


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent dies; False elsewhere."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            log.warning("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(ctypes.get_errno()))
            return False
    except (OSError, AttributeError) as exc:
        log.warning("no prctl (%s): the launcher watch alone ends this service with its launcher", exc)
        return False
    return True


def exit_now() -> None:
    """What a launcher's death does before the service can stop in order (still opening its
    bus, loading models): a Zenoh open waiting for a router that went with the launcher
    never returns to look at a stop event, and there is nothing to save yet."""
    logging.shutdown()
    os._exit(1)


class Lifeline:
    """Ends this process with its launcher: see the module docstring. ``on_gone`` is called
    once, from the watch thread, when the launcher has gone: :func:`exit_now` until the
    service is up, then (:meth:`stop_with`) its orderly stop. The parent-death SIGTERM goes to
    the stop handler instead, which the watch backs up within one period."""

    def __init__(self, launcher: int, on_gone: Callable[[], None], *, grace_s: float, period_s: float = WATCH_PERIOD_S) -> None:
        self.launcher = launcher
        self.on_gone = on_gone
        self.grace_s = grace_s
        self.period_s = period_s
        self.gone_at: float | None = None
        self.pdeathsig = set_parent_death_signal(signal.SIGTERM)
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="lifeline", daemon=True)
        self._thread.start()

    def launcher_gone(self) -> bool:
        return os.getppid() != self.launcher

    def _watch(self) -> None:
        while not self._closed.is_set():
            if self.gone_at is None and self.launcher_gone():
                self.gone_at = time.monotonic()
                log.warning("launcher (pid %d) has gone: stopping (at most %.0f s)", self.launcher, self.grace_s)
                self.on_gone()
            if self.gone_at is not None and time.monotonic() - self.gone_at > self.grace_s:
                log.error("orderly stop took over %.0f s after the launcher went: exiting now", self.grace_s)
                exit_now()
            self._closed.wait(self.period_s)

    def stop_with(self, on_gone: Callable[[], None]) -> None:
        """The service is up: from now on the launcher's death means ``on_gone`` (an orderly
        stop), and :func:`exit_now` only once the grace has run out."""
        self.on_gone = on_gone
        if self.gone_at is not None:
            on_gone()

    def close(self) -> None:
        self._closed.set()


def start_lifeline(on_gone: Callable[[], None] = exit_now) -> Lifeline | None:
    """The lifeline when launched by ``trackgraph launch`` (its pid in the environment), else
    None. A launcher already gone by now triggers ``on_gone`` within one watch period."""
    pid = launcher_pid()
    if pid is None:
        return None
    return Lifeline(pid, on_gone, grace_s=_grace_s())
