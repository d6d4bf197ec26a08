"""Fields of Linux's ``/proc/<pid>/status`` (memory high-water marks, the umask)."""

from __future__ import annotations


def status_field(name: str, pid: int | str = "self") -> str | None:
    """The value of field ``name`` (e.g. ``VmRSS``), or None where /proc cannot tell."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key == name:
                    return value.strip()
    except OSError:
        return None
    return None


def status_mb(name: str, pid: int | str = "self") -> float | None:
    """A memory field (``VmRSS``, ``VmHWM``) in MB, or None."""
    value = status_field(name, pid)
    try:
        return int(value.split()[0]) / 1024 if value else None
    except ValueError:
        return None
