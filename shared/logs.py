"""One logging setup for every command and service."""

from __future__ import annotations

import logging
import os
import sys


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record, not the stream it was
    when logging was set up: a command run inside another program (a test runner, a
    notebook) that swaps and closes stderr afterwards must not leave a handler on a closed file."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def setup_logging(verbosity: int = 0, service: str | None = None) -> None:
    """INFO by default, DEBUG with -v; ``TRACKGRAPH_LOG`` overrides (e.g. WARNING)."""
    level = os.environ.get("TRACKGRAPH_LOG") or ("DEBUG" if verbosity > 0 else "INFO")
    name = f"[{service}] " if service else ""
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter(f"%(asctime)s %(levelname)-7s {name}%(name)s: %(message)s", datefmt="%H:%M:%S"))
    logging.basicConfig(level=level, handlers=[handler], force=True)
