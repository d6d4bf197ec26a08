"""Pairing streams by time stamp (TUM's ``associate.py`` rule, also used for ROS bags)."""

from __future__ import annotations

from typing import Annotated

import numpy as np


def associate(
    a: Annotated[np.ndarray, "(N,) float seconds"],
    b: Annotated[np.ndarray, "(M,) float seconds"],
    max_diff: float,
) -> list[tuple[int, int]]:
    """One-to-one pairs (i, j) with |a[i] - b[j]| <= max_diff, closest pairs first.

    Greedy on the sorted differences like TUM's ``associate.py``, so two colour frames never
    share one depth image. Returned in increasing ``i``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    order = np.argsort(b, kind="stable")
    bs = b[order]
    lo = np.searchsorted(bs, a - max_diff, side="left")
    hi = np.searchsorted(bs, a + max_diff, side="right")
    candidates = [
        (abs(a[i] - bs[k]), i, int(order[k])) for i in range(len(a)) for k in range(lo[i], hi[i])
    ]
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def nearest(
    query: Annotated[np.ndarray, "(N,) float seconds"],
    ref: Annotated[np.ndarray, "(M,) float seconds, sorted"],
    max_diff: float,
) -> Annotated[np.ndarray, "(N,) int index into ref, -1 if none within max_diff"]:
    """Nearest reference stamp for each query; several queries may share one (pose streams)."""
    query = np.asarray(query, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    out = np.full(len(query), -1, dtype=np.int64)
    if len(ref) == 0:
        return out
    k = np.clip(np.searchsorted(ref, query), 1, len(ref) - 1) if len(ref) > 1 else np.zeros(len(query), int)
    if len(ref) > 1:
        k = np.where(np.abs(ref[k - 1] - query) <= np.abs(ref[k] - query), k - 1, k)
    ok = np.abs(ref[k] - query) <= max_diff
    out[ok] = k[ok]
    return out
