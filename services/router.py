"""``trackgraph router``: a Zenoh router started from Python, so no separate binary is needed."""

from __future__ import annotations

import logging
import signal
import threading

from shared.config import TransportConfig
from shared.transport import open_session

log = logging.getLogger(__name__)


def run_router(cfg: TransportConfig, stop: threading.Event | None = None) -> None:
    """Serve as a router until SIGINT/SIGTERM (or ``stop`` is set), then close cleanly."""
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    session = open_session(cfg)
    try:
        log.info("zenoh router %s listening on %s", session.zid(), ", ".join(cfg.listen) or "(default)")
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
        log.info("router closed")
