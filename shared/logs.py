"""One logging setup for every command and service."""

from __future__ import annotations

import logging
import os


def setup_logging(verbosity: int = 0, service: str | None = None) -> None:
    """INFO by default, DEBUG with -v; ``TRACKGRAPH_LOG`` overrides (e.g. WARNING)."""
    level = os.environ.get("TRACKGRAPH_LOG") or ("DEBUG" if verbosity > 0 else "INFO")
    name = f"[{service}] " if service else ""
    logging.basicConfig(
        level=level,
        format=f"%(asctime)s %(levelname)-7s {name}%(name)s: %(message)s",
        datefmt="%H:%M:%S",
        force=True,
    )
