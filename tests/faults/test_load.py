"""The live system under a 30 Hz, 640x480 stream (one minute here; ten in
``benchmarks/load.py``): every process's memory stays bounded, and every frame is accounted
for: sent or dropped by the source, taken or dropped by the tracker, in the map or dropped by
fusion, each drop counted by the service that made it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

from load import run_load  # noqa: E402

pytestmark = [pytest.mark.faults, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(900)]


def test_a_minute_at_30_hz_is_bounded_and_every_frame_is_counted(tmp_path):
    from shared.synth import run_synth

    seq = tmp_path / "seq"
    run_synth("small", 0, seq, {"camera": {"width": 640, "height": 480, "frames": 150}}, progress=False)
    res = run_load(seq, tmp_path, minutes=1.0, rate_hz=30.0, progress=False)
    f = res["frames"]
    assert f["planned"] == res["loops"] * 150 >= 1800
    assert f["published"] + f["source_dropped"] == f["planned"]
    assert f["tracker_received"] + f["tracker_dropped"] == f["published"]
    assert f["tracker_received"] == f["tracker_frames"] > 30
    # Tracked frames Zenoh drops on the way to a saturated fusion (congestion control "drop",
    # live input) reach no service, so none counts them: measured 9 of 760 in a CI run, 1 of 718
    # and 3 of 580 at 60 Hz. They stay a small share; counting them at fusion (gaps in the
    # tracker's order numbers) is issue 35's live-chain work.
    on_wire = f["tracker_frames"] - f["frames_in_map"] - f["fusion_dropped"]
    assert 0 <= on_wire <= max(3, 0.03 * f["tracker_frames"]), f
    assert f["tracker_dropped"] > 0  # the point of the test: the tracker cannot take 30 Hz here
    for name, m in res["memory"].items():
        assert m["rss_max_mb"] < 4096, (name, m)
