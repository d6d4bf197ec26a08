"""``trackgraph serve SERVICE``: run one service node in this process until SIGINT/SIGTERM/SIGHUP
(or, for fusion, until the sequence it maps has ended when ``exit_at_end``).

Every node has a ``book`` (its session's :class:`~shared.runtime.status.StatusBook`) and a
``bus``; this loop publishes the book as a ``ServiceStatus`` on ``status/<service>`` once a
second and once at stop, and writes the last report to ``status_file``."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from shared.config.root import TrackGraphConfig
from shared.runtime.lifeline import install_stop_handlers, start_lifeline

log = logging.getLogger(__name__)

def build_node(service: str, cfg: TrackGraphConfig, *, out: Path | None = None, resume: bool = False):
    """The node of ``service`` as its registry entry builds it (shared/registry.py ``SERVICES``)."""
    from shared.registry import SERVICES, load_object

    entry = SERVICES.get(service)
    if not entry.servable:
        raise ValueError(f"{service} is not run by `trackgraph serve`: {entry.summary}")
    if entry.out is not None and out is None:
        raise ValueError(entry.out_help or f"{service} needs --out")
    return load_object(entry.node)(cfg, out=out, resume=resume)


def serve(
    service: str,
    cfg: TrackGraphConfig,
    *,
    out: Path | None = None,
    resume: bool = False,
    exit_at_end: bool = False,
    stop: threading.Event | None = None,
    status_file: Path | None = None,
    make_node: Callable[[], Any] | None = None,
    max_seconds: float | None = None,
) -> Any:
    """Run ``service`` (``build_node``'s, or ``make_node()``'s) until stopped, or for
    ``max_seconds``; returns the node, closed."""
    stop = stop or threading.Event()
    install_stop_handlers(stop.set)
    lifeline = start_lifeline()  # launched: end with the launcher, however it ends
    from shared.runtime.status import StatusReporter
    from shared.topics import Topics

    node = make_node() if make_node is not None else build_node(service, cfg, out=out, resume=resume)
    started = time.monotonic()
    heartbeat = cfg.transport if service in cfg.transport.status_heartbeat else None
    reporter = StatusReporter(node.book, node.bus, Topics(cfg.robot_id).status(service), heartbeat=heartbeat)
    try:
        start = getattr(node, "start", None)
        if start is not None:
            start()  # what takes a while to be ready (model loading) runs while "starting" is reported
        if lifeline is not None:
            lifeline.stop_with(stop.set)  # up: from now on the launcher's death is an orderly stop
        log.info("%s serving as robot %s", service, cfg.robot_id)
        while not stop.wait(1.0 if max_seconds is None else min(1.0, max(max_seconds - (time.monotonic() - started), 0.01))):
            if max_seconds is not None and time.monotonic() - started >= max_seconds:
                break
            if exit_at_end and getattr(node, "finished", None) is not None and node.finished.is_set():
                break
            log.debug("%s: %s", service, node.stats())
    finally:
        node.close(keep_bus=True)
        reporter.stop(status_file)
        node.bus.close()
        if lifeline is not None:
            lifeline.close()
        log.info("%s stopped: %s", service, node.stats())
    return node
