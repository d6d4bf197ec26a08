"""The one error type of the evaluation package: a bad input file, named in the message."""

from __future__ import annotations

from pathlib import Path


class EvalInputError(ValueError):
    """An evaluation input is missing, unreadable or inconsistent.

    The message starts with the offending file's path, so a command-line caller can print it
    as its one-line reason; ``path`` holds the same path.
    """

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")
