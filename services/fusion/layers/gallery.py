"""Per-segment open-vocabulary galleries (paper III-F).

A gallery maps each source track of a segment to that track's aggregated CLIP feature (the
running mean of eq. 4). Rows are kept per track rather than averaged into one node feature,
because different tracks tend to be different views and averaging CLIP features across views
loses accuracy; a query scores a segment by its best row (eq. 10).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Annotated

import numpy as np

from services.fusion.types import TrackState

Gallery = dict[int, np.ndarray]
"""track id -> (Dc,) float32 CLIP feature, exactly as the track holds it (not re-normalised)."""


def sync_gallery(
    gallery: Gallery, track_ids: Iterable[int], tracks: Mapping[int, TrackState]
) -> bool:
    """Copy each listed track's current CLIP mean into ``gallery``; True if any row changed.

    A track absent from ``tracks`` or still without a CLIP feature keeps its row (or has none):
    the caller may forget retired tracks, and their last mean is still the best description.
    """
    changed = False
    for tid in track_ids:
        state = tracks.get(tid)
        if state is None or state.clip is None:
            continue
        row = gallery.get(tid)
        if row is None or row.shape != state.clip.shape or not np.array_equal(row, state.clip):
            gallery[tid] = np.array(state.clip, dtype=np.float32, copy=True)
            changed = True
    return changed


def gallery_rows(
    gallery: Gallery,
) -> tuple[Annotated[np.ndarray, "(T', Dc) float32"], list[int]]:
    """The gallery as a matrix in ascending track order, with the track id of each row."""
    ids = sorted(gallery)
    if not ids:
        return np.zeros((0, 0), np.float32), []
    return np.stack([gallery[t] for t in ids]).astype(np.float32, copy=False), ids


def gallery_score(
    rows: Annotated[np.ndarray, "(T', Dc) float"], query: Annotated[np.ndarray, "(Dc,) float"]
) -> float:
    """Eq. 10: the largest cosine between ``query`` and any gallery row; -inf for an empty gallery."""
    if rows.shape[0] == 0:
        return float("-inf")
    q = np.asarray(query, np.float64)
    r = np.asarray(rows, np.float64)
    norms = np.linalg.norm(r, axis=1) * np.linalg.norm(q)
    # A zero row (or query) has no direction; it must not win the max.
    cos = np.where(norms > 0, r @ q / np.where(norms > 0, norms, 1.0), -np.inf)
    return float(cos.max())


def gallery_state(gallery: Gallery) -> dict:
    """Plain python + numpy form of a gallery (no int-keyed maps, so any serialiser takes it)."""
    rows, ids = gallery_rows(gallery)
    return {"tracks": ids, "rows": rows.copy()}


def gallery_from_state(state: Mapping) -> Gallery:
    rows = np.asarray(state["rows"], np.float32)
    return {int(t): rows[i].copy() for i, t in enumerate(state["tracks"])}
