"""Atomic file writes: a crash mid-write never leaves a half-written map or config."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from shared.procfs import status_field


def _umask() -> int:
    # Linux reports it without changing it; setting and restoring it races other threads.
    value = status_field("Umask")
    if value:
        return int(value, 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_replace(path: Path, write: Callable[[Path], object], suffix: str = ".tmp") -> Path:
    """Have ``write`` fill a temporary file in the same folder, fsync it, then rename it over
    ``path``; on any failure the temporary file is removed and ``path`` left as it was.

    ``suffix`` ends the temporary name, for writers that choose a format by extension. The
    file gets the permissions a plain ``open()`` would give it (0666 less the umask), not the
    0600 of the temporary file, so maps and reports can be shared and served.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    tmp = Path(name)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        os.close(fd)
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_replace`)."""
    return atomic_replace(path, lambda tmp: tmp.write_bytes(data))


def atomic_write_text(path: Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def fsync_dir(path: Path) -> None:
    """Make a rename or a new file in ``path`` durable; some filesystems refuse fsync on directories."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
