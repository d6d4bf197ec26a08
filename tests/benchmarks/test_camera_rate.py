"""``benchmarks/camera_rate.py``: its pure helpers (percentiles, update lags, the flag parsers,
the table), its exits on a bad flag and on a failed part, and one tiny run of the fusion and
tracker parts end to end."""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import camera_rate  # noqa: E402


def test_percentile_matches_numpy_and_handles_the_edges():
    values = [5.0, 1.0, 4.0, 2.0, 3.0, 10.0, 7.5]
    for q in (0, 25, 50, 90, 99, 100):
        assert camera_rate.percentile(values, q) == pytest.approx(float(np.percentile(values, q)))
    assert camera_rate.percentile([], 50) is None
    assert camera_rate.percentile([3.0], 99) == 3.0
    with pytest.raises(ValueError, match="0..100"):
        camera_rate.percentile(values, 101)


def test_update_lag_runs_from_each_frame_to_the_first_delta_that_covers_it():
    fused = {0: 0.0, 1: 1.0, 2: 2.0, 3: 3.0, 4: 4.0, 5: 5.0}
    # a delta covering frames up to 2 at 2.5 s, one up to 4 at 3.9 s (before frame 4's ack:
    # its own delta went out first), a later one up to 4 that must not count
    deltas = [(2.5, 2), (3.9, 4), (9.0, 4)]
    lags, uncovered = camera_rate.update_lags(fused, deltas)
    assert lags == pytest.approx([2.5, 1.5, 0.5, 0.9, 0.0])
    assert uncovered == 1  # frame 5: no delta reached it
    assert camera_rate.update_lags(fused, []) == ([], 6)


def test_resolution_parser():
    assert camera_rate.parse_resolution("1200x680") == (1200, 680)
    assert camera_rate.parse_resolution("160X120") == (160, 120)
    for bad in ("1200", "1200x", "wide", "1200x680x3", "16x16"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected WxH"):
            camera_rate.parse_resolution(bad)


def test_parts_and_rates_parsers():
    assert camera_rate.parse_parts("tracker,fusion") == ("fusion", "tracker")
    assert camera_rate.parse_parts("live") == ("live",)
    with pytest.raises(Exception, match="fusion, tracker, map, live"):
        camera_rate.parse_parts("fusion,gpu")
    assert camera_rate.parse_rates("10,15,30") == (10.0, 15.0, 30.0)
    with pytest.raises(Exception, match="positive"):
        camera_rate.parse_rates("15,0")


def _result(**parts) -> dict:
    return {"resolution": [1200, 680], "voxel_size": 0.03, "frames": 240, "preset": "demo", "quick": False, "commit": "abc1234-dirty",
            "machine": {"cpus": 2, "cpu": "some CPU", "loadavg": [0.1, 0.1, 0.1]}, "parts": list(parts), **parts}  # fmt: skip


def test_table_shows_each_figure_against_its_target():
    res = _result(
        fusion={"fusion_hz": 31.5, "fusion_frame_ms_p50": 20.0, "fusion_frame_ms_p99": 74.0, "update_lag_s_p50": 0.5,
                "update_lag_s_p99": 1.5, "updates": 24, "frames_without_update": 0, "final_write_s": 2.0},
        tracker={"error": "RuntimeError: boom"},
        map={"map_hz": 4.3},
        live={"rates": {"10": {"live_mapped_share": 0.35, "frames_in_map": 84, "frames_played": 240, "published": 84, "dropped": 156},
                        "15": {"live_mapped_share": 0.96, "frames_in_map": 230, "frames_played": 240, "published": 230, "dropped": 10},
                        "30": {"rate_hz": 30.0, "error": "RuntimeError: not up"}}},
    )  # fmt: skip
    text = camera_rate.table(res)
    lines = text.splitlines()
    assert "1200x680" in lines[0] and "abc1234-dirty" in lines[0]

    def row(start: str) -> str:
        found = [ln for ln in lines if ln.startswith(start)]
        assert len(found) == 1, (start, text)
        return found[0]

    assert "31.50 Hz" in row("| fusion | fusion_hz") and "pass" in row("| fusion | fusion_hz")
    assert "20.0 / 74.0" in row("| fusion | frame ms") and "FAIL" in row("| fusion | frame ms")
    assert "pass" in row("| fusion | update lag")
    assert "RuntimeError: boom" in row("| tracker | error")
    assert "4.30 Hz" in row("| map |") and "FAIL" in row("| map |")
    assert "35% (84 of 240)" in row("| live 10 Hz | mapped share") and "pass" not in row("| live 10 Hz | mapped share")
    assert "96%" in row("| live 15 Hz | mapped share") and "pass" in row("| live 15 Hz | mapped share")
    assert "not up" in row("| live 30 Hz | error")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--resolution", "wide"], "--resolution"),
        (["--parts", "fusion,gpu"], "--parts"),
        (["--frames", "2"], "--frames: at least 3"),
        (["--frames", "50", "--walk-frames", "40"], "--walk-frames 40"),
        (["--voxel", "0"], "--voxel"),
        (["--no-such-flag"], "unrecognized arguments"),
    ],
)
def test_a_bad_flag_exits_2_naming_it(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        camera_rate.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_a_failed_part_is_recorded_and_exits_1_with_one_line(tmp_path, monkeypatch, capsys):
    def fake_run(args):
        return {**_result(fusion={"error": "RuntimeError: no map written", "wall_s": 1.0}, tracker={"tracker_hz": 40.0, "wall_s": 1.0}),
                "parts": list(args.parts), "wall_s": 2.0}  # fmt: skip

    monkeypatch.setattr(camera_rate, "run", fake_run)
    monkeypatch.setattr(camera_rate, "setup_logging", lambda *a, **k: None)
    code = camera_rate.main(["--parts", "fusion,tracker", "--out", str(tmp_path)])
    assert code == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert err == ["camera_rate: failed: fusion: RuntimeError: no map written"]
    saved = json.loads((tmp_path / "camera_rate.json").read_text())
    assert saved["fusion"] == {"error": "RuntimeError: no map written", "wall_s": 1.0}


def _positive(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_tiny_run_of_fusion_and_tracker_writes_the_json(tmp_path):
    cmd = [sys.executable, str(ROOT / "benchmarks" / "camera_rate.py"), "--quick", "--resolution", "160x120", "--frames", "10",
           "--walk-frames", "10", "--parts", "fusion,tracker", "--out", str(tmp_path)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=280, env={**os.environ, "TRACKGRAPH_LOG": "WARNING"})
    assert proc.returncode == 0, proc.stderr[-4000:]
    res = json.loads((tmp_path / "camera_rate.json").read_text())
    for key in ("resolution", "voxel_size", "frames", "commit", "machine", "date", "quick", "fusion", "tracker"):
        assert key in res, key
    assert res["resolution"] == [160, 120] and res["voxel_size"] == 0.03 and res["frames"] == 10 and res["quick"] is True
    assert "map" not in res and "live" not in res
    assert res["commit"] and {"cpus", "cpu", "platform", "loadavg"} <= set(res["machine"])

    fusion, tracker = res["fusion"], res["tracker"]
    assert "error" not in fusion and "error" not in tracker, (fusion, tracker)
    for key in ("fusion_hz", "fusion_frame_ms_p50", "fusion_frame_ms_p99", "final_write_s"):
        assert _positive(fusion[key]), (key, fusion[key])
    assert fusion["frames"] == 10 and fusion["updates"] >= 1 and fusion["journal"]["records"] >= 10
    for key in ("update_lag_s_p50", "update_lag_s_p99"):
        assert fusion[key] is not None and 0 <= fusion[key] < 600, (key, fusion[key])
    for key in ("tracker_hz", "tracker_frame_ms_p50", "tracker_frame_ms_p99"):
        assert _positive(tracker[key]), (key, tracker[key])
    assert tracker["frames"] == 10 and tracker["keyframes"] == 2 and tracker["keyframes_unplanned"] == 0
    assert "| fusion | fusion_hz" in proc.stdout and "| tracker | tracker_hz" in proc.stdout
