"""The track ids a tracked frame reports: np.unique's answer from one counting pass."""

from __future__ import annotations

import numpy as np
import pytest

from services.tracker.core import _ids_present


@pytest.mark.parametrize("seed", range(4))
def test_ids_present_equals_unique_without_the_background(seed):
    rng = np.random.default_rng(seed)
    labels = rng.integers(-1, 40, (68, 120)).astype(np.int32)
    labels[rng.random(labels.shape) < 0.5] = -1
    labels[labels == 7] = -1  # a gap in the ids
    want = [int(t) for t in np.unique(labels) if t >= 0]
    assert _ids_present(labels) == want and 7 not in want


def test_edge_cases():
    assert _ids_present(np.full((4, 5), -1, np.int32)) == []
    assert _ids_present(np.zeros((0, 5), np.int32)) == []
    assert _ids_present(np.array([[0, 0], [-1, 3]], np.int32)) == [0, 3]
    huge = np.array([[-1, 5], [2_000_000_000, 5]], np.int32)  # sparse huge ids take np.unique
    assert _ids_present(huge) == [5, 2_000_000_000]
