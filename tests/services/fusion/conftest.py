"""Fixtures shared by the fusion tests."""

from __future__ import annotations

import pytest

FRAMES = 150
"""Frames of the drifting scene."""


@pytest.fixture(scope="session")
def drifting(tmp_path_factory):
    """A small synthetic walk (160x120, 150 frames) with odometry drifting 0.1 m per m, its
    true poses in ``traj_gt.txt`` (generated once per test run)."""
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out, {"camera": {"width": 160, "height": 120, "frames": FRAMES}}, drift=0.1)
    return out
