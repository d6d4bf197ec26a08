"""The check that two saved maps are the same map: segments with the same tracks, galleries
holding the same tracks' features, rooms with the same names (for a distributed or
interrupted run against the in-process one)."""

from __future__ import annotations

import numpy as np

from shared.messages.graph import GraphSnapshot


def assert_same_map(got: GraphSnapshot, want: GraphSnapshot, *, min_segments: int = 10) -> None:
    assert len(got.segments) == len(want.segments) > min_segments
    assert [(s.id, s.tracks) for s in got.segments] == [(s.id, s.tracks) for s in want.segments]
    # CLIP features come back asynchronously; still every gallery holds the same tracks'
    # features (the last keyframes' included).
    assert [s.gallery_tracks for s in got.segments] == [s.gallery_tracks for s in want.segments]
    for a, b in zip(got.segments, want.segments, strict=True):
        np.testing.assert_allclose(a.gallery, b.gallery, atol=1e-5, err_msg=f"segment {a.id}")
    # Fusion fetches the room labels over vl/embed when keyframe_vl answers; the names end the same.
    assert [(r.id, r.name) for r in got.rooms] == [(r.id, r.name) for r in want.rooms]
