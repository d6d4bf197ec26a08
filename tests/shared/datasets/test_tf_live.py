"""TfBuffer's additions for live streams: gap-aware interpolation, which dynamic links a
lookup needs and how new they are, pruning and forgetting."""

from __future__ import annotations

import numpy as np
import pytest
from dataset_fixtures import matrix_to_quat, rotation

from shared.datasets.tf import TfBuffer

I4 = np.array([1.0, 0, 0, 0])


def _tree() -> TfBuffer:
    """map -> odom (dynamic, 1 s apart), odom -> base (dynamic, every 0.1 s), base -> cam (static),
    map -> marker (static)."""
    tf = TfBuffer()
    for k in range(3):
        tf.add("map", "odom", k * 10**9, np.array([k * 1.0, 0, 0]), I4, static=False)
    for k in range(31):
        tf.add("odom", "base", k * 10**8, np.array([0, k * 0.1, 0]), matrix_to_quat(rotation([0, 0, 1], 0.01 * k)), static=False)
    tf.add("base", "cam", 0, np.array([0, 0, 1.0]), I4, static=True)
    tf.add("map", "marker", 0, np.array([5.0, 0, 0]), I4, static=True)
    return tf


def test_max_bracket_refuses_interpolating_across_a_gap() -> None:
    tf = _tree()
    # map -> odom has samples 1 s apart: fine without a bracket limit, refused with 0.05 s
    T = tf.lookup("map", "cam", 1_450_000_000, max_gap_ns=0)
    assert T is not None
    np.testing.assert_allclose(T[:3, 3], [1.45, 1.45, 1.0], atol=1e-9)
    assert tf.lookup("map", "cam", 1_450_000_000, max_gap_ns=0, max_bracket_ns=50_000_000) is None
    # on a sample of every dynamic link: exact, whatever the bracket limit
    assert tf.lookup("map", "cam", 10**9, max_gap_ns=0, max_bracket_ns=0) is not None
    # odom -> base alone is dense enough: 0.05 s on each side
    np.testing.assert_allclose(
        tf.lookup("odom", "cam", 1_050_000_000, 0, max_bracket_ns=50_000_000)[:3, 3], [0, 1.05, 1.0], atol=1e-9
    )
    assert tf.lookup("odom", "cam", 1_050_000_000, 0, max_bracket_ns=49_999_999) is None
    # the ends keep using max_gap_ns
    assert tf.lookup("odom", "cam", 3_020_000_000, max_gap_ns=30_000_000, max_bracket_ns=1) is not None
    assert tf.lookup("odom", "cam", 3_020_000_000, max_gap_ns=10_000_000, max_bracket_ns=1) is None


def test_dynamic_edges_and_latest_stamps() -> None:
    tf = _tree()
    assert tf.dynamic_edges("map", "cam") == ["base", "odom"]
    assert tf.dynamic_edges("marker", "cam") == ["base", "odom"]  # across the common ancestor
    assert tf.dynamic_edges("base", "cam") == []
    assert tf.dynamic_edges("/map", "/odom") == ["odom"]
    with pytest.raises(LookupError, match="not connected"):
        tf.add("elsewhere", "lost", 0, np.zeros(3), I4, static=True)
        tf.dynamic_edges("map", "lost")
    assert tf.latest_stamp("odom") == 2 * 10**9 and tf.oldest_stamp("base") == 0
    assert tf.latest_stamp("cam") is None and tf.latest_stamp("nowhere") is None
    tf.add("odom", "base", 5 * 10**7, np.zeros(3), I4, static=False)  # out of order
    assert tf.latest_stamps() == {"odom": 2 * 10**9, "base": 3 * 10**9}
    assert tf.is_static("cam") and not tf.is_static("base")
    assert sorted(tf.static_frames()) == ["cam", "lost", "marker"]
    assert sorted(tf.dynamic_frames()) == ["base", "odom"]
    assert tf.dynamic_parent("base") == "odom" and tf.dynamic_parent("cam") is None
    assert tf.sample_count() == 3 + 31 + 1


def test_prune_forgets_old_samples_per_link_and_keeps_the_newest() -> None:
    tf = _tree()
    assert tf.prune(10**9) == 1 + 20  # odom keeps 1 s, 2 s; base keeps 2.0 .. 3.0 s
    assert tf.oldest_stamp("odom") == 10**9 and tf.oldest_stamp("base") == 2 * 10**9
    assert tf.lookup("map", "cam", 1_500_000_000, max_gap_ns=0) is None  # base no longer reaches back
    assert tf.lookup("map", "cam", 2_000_000_000, max_gap_ns=0) is not None
    assert tf.prune(0) == 1 + 10 and tf.sample_count() == 2  # the newest always stays
    assert tf.prune(0) == 0


def test_remove_and_clear() -> None:
    tf = _tree()
    tf.remove("base")
    with pytest.raises(LookupError):
        tf.lookup("map", "cam", 10**9, 0)  # base hangs from nothing now
    tf.clear()
    assert tf.dynamic_frames() == [] and tf.static_frames() and tf.sample_count() == 0
    assert tf.lookup("base", "cam", 123, 0) is not None  # statics survive a clock reset
    tf.clear(static=True)
    assert tf.frames() == set()
