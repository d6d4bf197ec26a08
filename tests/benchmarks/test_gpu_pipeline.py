"""``benchmarks/gpu_pipeline.py``: the stage timers' summary, and ``--tiny`` end to end (every
stage timed, the distributed system's rate trial, both voxel sizes, the JSON and the tables)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import gpu_pipeline  # noqa: E402

REQUIRED_STAGES = ("dinov3", "propagation", "fastsam", "clip", "vote", "integrate", "mesh", "segments")


def test_stage_summary_leaves_the_first_call_out():
    s = gpu_pipeline.stage_summary([100.0, 2.0, 4.0, 3.0])
    assert s["calls"] == 4 and s["first_ms"] == 100.0
    assert s["ms_median"] == 3.0 and s["ms_mean"] == 3.0 and s["ms_max"] == 4.0
    assert s["ms_total"] == 109.0
    one = gpu_pipeline.stage_summary([5.0])
    assert one["ms_median"] == one["first_ms"] == 5.0


def test_stage_timer_counts_every_call_and_keeps_results():
    times = gpu_pipeline.StageTimes()
    f = times.timed(lambda x: x * 2, "mesh")
    assert [f(i) for i in range(3)] == [0, 2, 4]
    assert len(times.ms["mesh"]) == 3 and all(v >= 0 for v in times.ms["mesh"])
    assert list(times.summary()) == ["mesh"]


def test_a_process_that_is_no_service_is_not_counted():
    assert gpu_pipeline.service_of(os.getpid()) is None
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(5)"])
    try:
        assert child.pid in gpu_pipeline._children(os.getpid())
        assert gpu_pipeline.service_of(child.pid) is None
    finally:
        child.kill()
        child.wait()


def _positive(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0


@pytest.mark.slow
@pytest.mark.zenoh
@pytest.mark.timeout(900)
def test_tiny_run_times_every_stage_and_writes_the_json(tmp_path):
    out = tmp_path / "out"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "gpu_pipeline.py"), "--tiny", "--out", str(out), "--weights", str(tmp_path / "weights")]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=840, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.returncode == 0, proc.stderr[-4000:]
    res = json.loads((out / "gpu_pipeline.json").read_text())

    assert res["benchmark"] == "gpu_pipeline" and res["mode"] == "tiny" and res["complete"] is True
    env = res["environment"]
    for key in ("device", "device_name", "torch", "torch_cuda", "cuda_available", "open3d", "open3d_cuda", "commit", "machine"):
        assert key in env, key
    assert env["device"] == "cpu" and env["torch"] and env["device_name"]
    assert res["sequence"]["resolution"] == [160, 120] and res["sequence"]["frames"] == 20
    assert [c["name"] for c in res["configs"]] == ["paper", "onboard"]

    for c in res["configs"]:
        name = c["name"]
        assert set(REQUIRED_STAGES) <= set(c["stages"]), (name, sorted(c["stages"]))
        assert set(c["stages"]) <= set(gpu_pipeline.STAGES)
        for stage, st in c["stages"].items():
            assert st["calls"] >= 1, (name, stage)
            for k in ("ms_median", "ms_mean", "ms_p90", "ms_max", "ms_total", "first_ms"):
                assert _positive(st[k]), (name, stage, k, st[k])
        assert _positive(c["stage_run"]["seconds"]) and c["stage_run"]["frames"] >= 1

        assert set(c["processes"]) == set(gpu_pipeline.PROCESSES)
        for proc_name, m in c["processes"].items():
            assert _positive(m["peak_rss_mb"]), (name, proc_name, m)
            assert m["peak_gpu_mb"] is None, (name, proc_name, m)  # on the CPU: none

        rate = c["rate"]
        assert len(rate["trials"]) == 1 and _positive(rate["start_hz"])
        t = rate["trials"][0]
        assert isinstance(t["sustained"], bool) and set(t["drops"]) == {"source", "tracker", "keyframe_vl", "fusion"}
        assert t["published"] >= 1 and t["error"] is None
        assert rate["max_sustained_hz"] in (None, t["rate_hz"])

        assert set(c["maps"]) == {"3cm"}  # --tiny maps at one voxel size
        for voxel, m in c["maps"].items():
            assert m["voxel_size"] == {"3cm": 0.03, "5cm": 0.05}[voxel]
            assert _positive(m["seconds"]) and m["frames"] == c["stage_run"]["frames"]
            assert _positive(m["peak_rss_mb"]) and m["gpu_peak_mb"] is None

    assert res["configs"][0]["stage_run"]["frames"] == 20  # paper: every frame
    assert res["configs"][1]["stage_run"]["frames"] == 5  # onboard: every 4th
    for line in ("Per-stage ms", "Peak memory per process", "Highest input rate sustained", "Time per sequence", "gpu_pipeline.json"):
        assert line in proc.stdout, line
