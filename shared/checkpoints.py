"""Reports on checkpoints that do not fit their model, shared by every loader."""

from __future__ import annotations

from collections.abc import Iterable


def key_report(
    missing: Iterable[str],
    unexpected: Iterable[str],
    mismatched: Iterable[tuple[str, tuple[int, ...], tuple[int, ...]]],
    first: int = 5,
) -> str:
    """``"N missing keys (first: ...); N unexpected keys (...); N keys of the wrong shape
    (...)"``: what a refused checkpoint lacks, adds and sizes wrongly, short enough to read."""

    def head(keys: list[str]) -> str:
        more = ", ..." if len(keys) > first else ""
        return ", ".join(keys[:first]) + more

    # Lists keep the model's order (blocks.0 before blocks.10); sets have none, so sort them.
    missing = list(missing) if isinstance(missing, list) else sorted(missing)
    unexpected = list(unexpected) if isinstance(unexpected, list) else sorted(unexpected)
    mismatched = list(mismatched) if isinstance(mismatched, list) else sorted(mismatched, key=lambda m: m[0])
    shapes = [f"{k} (file {tuple(a)}, model {tuple(b)})" for k, a, b in mismatched]
    parts = [
        f"{len(keys)} {what if len(keys) == 1 else plural} (first: {head(keys)})"
        for keys, what, plural in (
            (missing, "missing key", "missing keys"),
            (unexpected, "unexpected key", "unexpected keys"),
            (shapes, "key of the wrong shape", "keys of the wrong shape"),
        )
        if keys
    ]
    return "; ".join(parts)
