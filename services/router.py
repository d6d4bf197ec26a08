"""``trackgraph router``: a Zenoh router started from Python, so no separate binary is needed."""

from __future__ import annotations

import logging
import threading

from shared.config import TransportConfig
from shared.runtime.lifeline import install_stop_handlers, start_lifeline
from shared.transport import open_session

log = logging.getLogger(__name__)


def run_router(cfg: TransportConfig, stop: threading.Event | None = None) -> None:
    """Serve as a router until SIGINT/SIGTERM/SIGHUP (or ``stop`` is set), then close cleanly."""
    stop = stop or threading.Event()
    install_stop_handlers(stop.set)
    lifeline = start_lifeline()  # launched: end with the launcher, however it ends
    session = open_session(cfg)
    if lifeline is not None:
        lifeline.stop_with(stop.set)
    try:
        log.info("zenoh router %s listening on %s", session.zid(), ", ".join(cfg.listen) or "(default)")
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
        if lifeline is not None:
            lifeline.close()
        log.info("router closed")
