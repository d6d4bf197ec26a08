"""Voxel anchors: the frame each voxel's surface is pinned to, so a pose correction moves it
with that frame (:mod:`services.fusion.volume.move`).

Each voxel a frame updated is anchored to the weighted mean of the frames fused into it
(rounded): a surface averaged over frames with different drift sits where their mean puts it.
One rule, two implementations that agree bit for bit (tested): numpy over any array (torch
tensors on CUDA through ``services.fusion.volume.mesh``'s helpers), and a numba kernel that
updates Open3D's CPU attribute views in place, without the (B, res^3) float64 temporaries
(a frame at 1200x680 touches about a thousand blocks of 512 voxels).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np

try:
    import numba
except ImportError:  # numpy does the same, slower
    numba = None


def anchor_rule(
    after: Annotated[np.ndarray, "(B, V) float64 weights after the frame"],
    old: Annotated[np.ndarray, "(B, V) float64 anchors before it"],
    before: Annotated[np.ndarray, "(B, V) weights before it"],
    frame: int,
) -> Annotated[np.ndarray, "(B, V) int32"]:
    """The anchors after fusing ``frame``: the running weighted mean of the frames, rounded,
    where the frame added weight; unchanged where it did not; ``frame`` for new voxels."""
    added = after - before
    mean = np.where(before > 0, old + (frame - old) * added / np.maximum(after, 1e-9), frame)
    return np.where(added > 0, np.floor(mean + 0.5), np.where(before > 0, old, frame)).astype(np.int32)


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def anchor_blocks(weight, anchor, bufs, before, frame):  # pragma: no cover - compiled
        """:func:`anchor_rule` in place: ``weight`` and ``anchor`` are (capacity, V) views of
        the grid, ``bufs`` the frame's block rows, ``before`` (B, V) their weights before it."""
        f = np.float64(frame)
        for b in range(bufs.shape[0]):
            r = bufs[b]
            for v in range(before.shape[1]):
                bef = np.float64(before[b, v])
                aft = np.float64(weight[r, v])
                added = aft - bef
                if added > 0:
                    if bef > 0:
                        old = np.float64(anchor[r, v])
                        mean = old + (f - old) * added / max(aft, 1e-9)
                    else:
                        mean = f
                    anchor[r, v] = np.int32(np.floor(mean + 0.5))
                elif not bef > 0:
                    anchor[r, v] = np.int32(frame)


def anchor_in_place(
    weight: np.ndarray, anchor: np.ndarray, bufs: Annotated[np.ndarray, "(B,) int64"], before: Annotated[np.ndarray, "(B, V) float32"], frame: int
) -> bool:
    """Apply the rule to the grid's CPU views with the numba kernel; False (nothing done)
    when numba is missing or the views are not plain contiguous numpy arrays."""
    if numba is None or not all(isinstance(a, np.ndarray) and a.flags.c_contiguous for a in (weight, anchor)):
        return False
    cap = weight.shape[0]
    anchor_blocks(weight.reshape(cap, -1), anchor.reshape(cap, -1), np.ascontiguousarray(bufs, np.int64), np.ascontiguousarray(before), int(frame))
    return True
