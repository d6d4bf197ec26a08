"""``trackgraph bench run``: the rate search, the variants, the report, and one small run end to
end through the command line."""

from __future__ import annotations

import json

import pytest

from services.bench.rate import search_rate, trial_result
from services.bench.report import markdown, plots
from services.bench.runs import REPO, write_variant
from shared.config import load_config
from shared.messages.status import InputCounters, ServiceStatus
from shared.runtime.status import status_path, write_status


def fake_trial(limit: float):
    calls: list[float] = []

    def trial(rate: float) -> dict:
        calls.append(rate)
        ok = rate <= limit
        return {"rate_hz": rate, "published": 60, "dropped": 0 if ok else 7, "sustained": ok,
                "drops": {"source": 0, "tracker": 0 if ok else 7, "fusion": 0}}  # fmt: skip

    return trial, calls


@pytest.mark.parametrize("limit, start", [(3.0, 2.0), (3.0, 5.0), (0.05, 1.0), (100.0, 1.0)])
def test_search_brackets_then_bisects(limit, start):
    trial, calls = fake_trial(limit)
    best, done = search_rate(trial, start, 5)
    assert len(done) == len(calls) == 5
    sustained = [r for r in calls if r <= limit]
    assert best == (max(sustained) if sustained else None)
    assert best is None or best <= limit
    if limit == 3.0:
        # five trials from either side get within 25% of the limit
        assert best is not None and best >= 0.75 * limit
    # after a pass the next rate is higher, after a failure lower
    for a, b in zip(calls, calls[1:], strict=False):
        assert (b > a) if a <= limit else (b < a)


def test_search_with_one_trial():
    trial, calls = fake_trial(3.0)
    assert search_rate(trial, 2.0, 1)[0] == 2.0
    assert search_rate(trial, 4.0, 1)[0] is None


def _status(service: str, inputs: dict[str, dict] | None = None, **figures) -> ServiceStatus:
    return ServiceStatus(service=service, pid=1, state="stopped", uptime_s=10.0,
                         inputs=[InputCounters(name=k, **v) for k, v in (inputs or {}).items()], figures=figures)  # fmt: skip


KEYFRAMES = {"requested": 2, "answered": 2, "masks": 2, "failed": 0, "stale": 0, "timed_out": 0,
             "request_hz": 0.25, "answer_hz": 0.25, "latency_max_s": 1.0, "latency_mean_s": 0.5}  # fmt: skip


def write_trial(tmp_path, *, fusion_dropped: int = 0, in_map: int = 16, skip: tuple[str, ...] = ()):
    logs, out = tmp_path / "logs", tmp_path / "map"
    logs.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    reports = {
        "source": _status("source", {"frame_ack": {"received": 32}}, published=16, dropped=0, rejected=0, seconds=8.0, hz=2.0, held_s=0.0),
        "tracker": _status("tracker", {"frames": {"received": 16, "processed": 16}}, frames=16, timeouts=0, pending_keyframes=0, keyframes=KEYFRAMES),
        "keyframe_vl": _status("keyframe_vl", {"keyframe_request": {"received": 2, "processed": 2}}, processed=2, failed=0),
        "fusion": _status("fusion", {"tracks_frame": {"received": 16 - fusion_dropped, "dropped": fusion_dropped}}, frames=in_map, frames_in_map=in_map),
    }
    for name, st in reports.items():
        if name not in skip:
            write_status(status_path(logs, name), st)
    (out / "run.json").write_text(json.dumps({"frames_in_map": in_map, "fused_seconds": 7.0}))
    return logs, out


def test_a_trial_is_judged_from_the_status_files(tmp_path):
    logs, out = write_trial(tmp_path)
    res, ok = trial_result(logs, out, 2.0)
    assert ok and res["published"] == 16 and res["dropped"] == 0 and res["lost"] == 0
    assert res["drops"] == {"source": 0, "tracker": 0, "keyframe_vl": 0, "fusion": 0}
    assert res["frames_in_map"] == 16 and res["fused_hz"] == pytest.approx(15 / 7, abs=1e-4)
    assert res["keyframes"] == KEYFRAMES and res["keyframes_kept_up"]
    assert set(res) == {"rate_hz", "published", "dropped", "drops", "frames_in_map", "lost", "fused_hz", "keyframes", "keyframes_kept_up"}
    # The map fused a frame too slowly for 3 Hz: not sustained there.
    assert not trial_result(logs, out, 3.0)[1]


def test_a_trial_with_a_drop_or_a_missing_report_is_not_sustained(tmp_path):
    res, ok = trial_result(*write_trial(tmp_path / "a", fusion_dropped=1, in_map=15), 2.0)
    assert not ok and res["drops"]["fusion"] == 1 and res["dropped"] == 1 and res["lost"] == 0
    # A stage that wrote no report (it crashed): its drops are unknown, and so is the total.
    res, ok = trial_result(*write_trial(tmp_path / "b", skip=("keyframe_vl",)), 2.0)
    assert not ok and res["drops"]["keyframe_vl"] is None and res["dropped"] is None and res["lost"] is None
    # A file that is not a report counts as none (and is logged).
    logs, out = write_trial(tmp_path / "c")
    status_path(logs, "tracker").write_text("{not json")
    res, ok = trial_result(logs, out, 2.0)
    assert not ok and res["drops"]["tracker"] is None and res["keyframes"] is None and not res["keyframes_kept_up"]


def test_variant_is_validated_and_complete(tmp_path):
    base = REPO / "deploy" / "configs" / "synthetic.yaml"
    path = write_variant(base, {"fusion": {"tsdf": {"voxel_size": 0.05}}, "tracker": {"mode": "per_frame"}}, tmp_path / "v.yaml")
    cfg = load_config(path)
    assert cfg.fusion.tsdf.voxel_size == 0.05 and cfg.tracker.mode == "per_frame"
    assert cfg.fusion.segments.theta_sim == load_config(base).fusion.segments.theta_sim
    from shared.config import ConfigError

    with pytest.raises(ConfigError, match="voxel_sise"):
        write_variant(base, {"fusion": {"tsdf": {"voxel_sise": 0.05}}}, tmp_path / "bad.yaml")


def _result() -> dict:
    def ev(x: float) -> dict:
        return {"synonyms": 0.5 + x, "depictions": 0.05, "vis_sim": 0.1, "clutter": 0.05, "missing": 0.2 - x, "incorrect": 0.1,
                "ap": 0.3, "ap50": 0.5 + x, "ap25": 0.7, "top1_hit_rate": 0.8,
                "instances": {"ap": 0.4, "ap50": 0.7, "ap25": 0.8, "segments_per_object": 1.05},
                "gallery": {"max": 0.86, "mean": 0.74}}  # fmt: skip

    def run(hz: float, secs: float, mb: float) -> dict:
        return {"frames": 120, "seconds": secs, "hz": hz, "peak_rss_mb": mb, "gpu_peak_mb": None}

    trials = [
        {"rate_hz": 3.0, "published": 60, "dropped": 0, "sustained": True, "drops": {"source": 0, "tracker": 0, "fusion": 0}},
        {"rate_hz": 6.0, "published": 60, "dropped": 12, "sustained": False, "drops": {"source": 0, "tracker": 12, "fusion": 0}},
    ]
    cfg = {
        "name": "synthetic", "path": "deploy/configs/synthetic.yaml",
        "backends": {"segmenter": "simulated", "vl_encoder": "simulated", "dense_features": "classical"},
        "runs": {"3cm": {"run": run(6.4, 18.6, 1400), "eval": ev(0.1)}, "5cm": {"run": run(7.9, 15.2, 900), "eval": ev(0.05)},
                 "per_frame": {"run": run(3.1, 38.0, 1500), "eval": ev(0.0)}},
        "rate": {"3cm": {"max_sustained_hz": 3.0, "trials": trials}, "per_frame": {"max_sustained_hz": 1.5, "trials": trials[:1]}},
    }  # fmt: skip
    return {"sequence_name": "small preset, seed 0", "commit": "abc1234", "when": "2026-12-02T15:00:00+00:00",
            "machine": {"cpu": "Test CPU", "cpus": 2, "gpu": None, "platform": "Linux", "python": "3.11"}, "configs": [cfg]}  # fmt: skip


def test_markdown_has_every_table_and_the_ratio():
    md = markdown(_result())
    for title in ("## Segmentation", "## Retrieval", "## Efficiency", "## Tracker ablation", "## Gallery ablation"):
        assert title in md
    assert "| synthetic | 0.600 | 0.050 | 0.100 | 0.050 | 0.100 | 0.100 |" in md
    assert "| synthetic | 5 cm | 120 | 0.25 min | 7.90 | 0.88 GB | n/a |" in md
    assert "propagation sustains 2.00x the input rate of per-frame segmentation" in md
    assert "Simulated perception" in md and "abc1234" in md and "Test CPU (2 cores), no GPU" in md
    assert "| synthetic | 0.860 | 0.740 |" in md


def test_plots_are_written(tmp_path):
    paths = plots(_result(), tmp_path)
    assert sorted(p.name for p in paths) == ["efficiency.png", "gallery.png", "retrieval.png", "segmentation.png", "tracker.png"]
    for p in paths:
        assert p.stat().st_size > 10_000 and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_needs_a_scene(capsys):
    from services.cli import main

    assert main(["bench", "run"]) == 2
    assert "--preset" in capsys.readouterr().err
    assert main(["bench", "run", "--sequence", "nowhere"]) == 2
    assert "--config" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.zenoh
def test_bench_run_end_to_end(tmp_path, capsys):
    """A short run of the real thing: the small preset cut to 24 frames, one live trial per
    tracker mode."""
    from services.cli import main

    out = tmp_path / "bench"
    args = ["bench", "run", "--preset", "small", "--out", str(out), "--max-frames", "24", "--rate-trials", "1", "--rate-frames", "16", "--json"]
    assert main(args) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {"out", "markdown", "json", "plots", "seconds"} <= set(printed)
    res = json.loads((out / "bench.json").read_text())
    (cfg,) = res["configs"]
    assert set(cfg["runs"]) == {"3cm", "5cm", "per_frame"}
    assert cfg["runs"]["3cm"]["run"]["frames"] == 24 and cfg["runs"]["per_frame"]["run"]["frames"] == 24
    assert 0.0 <= cfg["runs"]["3cm"]["eval"]["ap50"] <= 1.0
    assert cfg["backends"]["segmenter"] == "simulated" and res["machine"]["cpus"] >= 1
    for mode in ("3cm", "per_frame"):
        (trial,) = cfg["rate"][mode]["trials"]
        assert trial["published"] == 16 and trial["dropped"] is not None, trial
    md = (out / "bench.md").read_text()
    assert "## Tracker ablation" in md and "Simulated perception" in md
    assert len(list((out / "plots").glob("*.png"))) == 5


def test_trial_frames_by_count_or_by_time():
    from services.bench.rate import trial_frames

    assert trial_frames(2.0, None, 16, 24) == 16
    assert trial_frames(2.0, None, None, 24) is None
    # by time: the frames sent in that time, two keyframes at least
    assert trial_frames(0.1, 240.0, 16, 24) == 25
    assert trial_frames(0.5, 240.0, None, 24) == 120
    assert trial_frames(0.02, 240.0, None, 1) == 5


def test_rates_keep_three_digits():
    from services.bench.rate import MIN_RATE_HZ, round_rate

    assert round_rate(12.3456) == 12.3 and round_rate(0.045678) == 0.0457
    assert round_rate(0.0) == MIN_RATE_HZ
    trial, calls = fake_trial(0.03)
    best, _ = search_rate(trial, 0.0125, 4)
    assert calls[:3] == [0.0125, 0.025, 0.05] and best == 0.025


def test_a_keyframe_vl_that_falls_behind_is_in_the_report():
    res = _result()
    slow = {"requested": 6, "answered": 6, "masks": 6, "failed": 0, "stale": 0, "timed_out": 0,
            "request_hz": 0.025, "answer_hz": 0.0185, "latency_max_s": 90.0, "latency_mean_s": 60.0}  # fmt: skip
    res["configs"][0]["rate"]["per_frame"]["trials"][0].update(keyframes=slow, sustained=False)
    res["configs"][0]["random_weights"] = True
    md = markdown(res)
    assert "| 6/6 | 0.0185 / 0.025 | no |" in md
    assert "Random weights in `synthetic`" in md


def test_resume_scores_finished_maps_without_mapping_again(tmp_path, monkeypatch):
    from services.bench import core

    res = _result()
    runs = res["configs"][0]["runs"]
    for name, r in runs.items():
        d = tmp_path / "maps" / f"synthetic-{name}"
        d.mkdir(parents=True)
        (d / "run.json").write_text(json.dumps({**r["run"], "backends": res["configs"][0]["backends"]}))
    seq = tmp_path / "seq"
    seq.mkdir()

    def no_mapping(*a, **k):
        raise AssertionError("a finished map was made again")

    monkeypatch.setattr(core, "map_run", no_mapping)
    monkeypatch.setattr(core, "evaluate_map", lambda map_dir, gt: runs[map_dir.name.split("-", 1)[1]]["eval"])
    out = core.run_bench(tmp_path, sequence=seq, gt=seq, rate_trials=0, resume=True, progress=False)
    (cfg,) = out["configs"]
    assert {k: v["run"]["hz"] for k, v in cfg["runs"].items()} == {"3cm": 6.4, "5cm": 7.9, "per_frame": 3.1}
    assert "## Tracker ablation" in (tmp_path / "bench.md").read_text()
    # without resume the maps are made again
    with pytest.raises(AssertionError, match="made again"):
        core.run_bench(tmp_path, sequence=seq, gt=seq, rate_trials=0, progress=False)


def test_markdown_says_which_alignment_scored_it():
    res = _result()
    assert "OpenLex3D instance alignment: not recorded." in markdown(res)
    for c in res["configs"]:
        for r in c["runs"].values():
            r["eval"].update(alignment="per_mask", alignment_threshold=0.001)
    assert "OpenLex3D instance alignment: `per_mask` at 0.001 (the public toolbox's default" in markdown(res)
