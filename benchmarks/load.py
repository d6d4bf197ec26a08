"""Benchmark: the whole system under a live 30 Hz, 640x480 stream for 10 minutes.

Run from the repository root::

    python benchmarks/load.py                 # 10 minutes (the issue's load)
    python benchmarks/load.py --minutes 1     # a quick look

What runs, each an OS process (``trackgraph launch``'s Supervisor) on loopback Zenoh: router,
keyframe_vl, tracker, fusion, query, and the source in ``live`` mode at ``--rate`` Hz,
replaying a 640x480 synthetic sequence (``small`` at 640x480, 300 frames) in laps for
``--minutes``. A slow stage never slows the source: frames it cannot take are dropped,
and each drop is counted by the service that made it:

* the source, frames it was too late to send (``live`` replay);
* the tracker, frames its newest-only input queue replaced (``tracks/frame`` input);
* fusion, tracked frames its bounded input queue had no room for.

The counts come from the ``status.json`` each service writes beside its log at stop (its last
``ServiceStatus`` report).

Every 5 s the resident memory (VmRSS) of each process is sampled. Reported per process: RSS
after the warm-up (the first ``--warmup`` fraction of the run), the maximum, the growth
between them and the growth per minute over the rest; and the frame accounting: published,
dropped per stage, in the map. JSON goes to benchmarks/out/load.json and a table to stdout.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from services.bench.rate import figure, input_count, stage_reports, start_live_system  # noqa: E402
from shared.procfs import status_mb  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "out" / "load.json"
SYNTHETIC = ROOT / "deploy" / "configs" / "synthetic.yaml"
SAMPLE_S = 5.0


def rss_mb(pid: int | None) -> float | None:
    return None if pid is None else status_mb("VmRSS", pid)


def make_sequence(path: Path, frames: int) -> Path:
    from shared.synth import run_synth

    if not (path / "traj.txt").exists():
        run_synth("small", 0, path, {"camera": {"width": 640, "height": 480, "frames": frames}}, overwrite=True, progress=False)
    return path


def run_load(seq: Path, work: Path, *, minutes: float, rate_hz: float, warmup: float = 0.2, progress: bool = True) -> dict:
    """Run the live system for ``minutes``; returns the measurements."""
    from shared.datasets import open_sequence

    n = len(open_sequence(seq))
    loops = max(1, math.ceil(minutes * 60 * rate_hz / n))
    overrides = {"source": {"mode": "live", "rate_hz": rate_hz, "loops": loops}, "tracker": {"device": "cpu"}}
    services = [
        {"name": "router"},
        {"name": "keyframe_vl"},
        {"name": "fusion", "args": ["--exit-at-end"]},
        {"name": "query"},
        {"name": "tracker", "after": ["keyframe_vl"]},
        {"name": "source", "after": ["tracker", "fusion", "query"]},
    ]
    plan, sup, runner = start_live_system(SYNTHETIC, seq, work, overrides, services)
    out = plan.out
    samples: dict[str, list[tuple[float, float]]] = {name: [] for name in sup.procs}
    t_source = None
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=round(minutes * 60), unit="s", desc="load")
    while runner.is_alive():
        if t_source is None and sup.procs["source"].state == "alive":
            t_source = time.monotonic()
        if t_source is not None:
            now = time.monotonic() - t_source
            for name, p in sup.procs.items():
                mb = rss_mb(p.pid)
                if mb is not None:
                    samples[name].append((now, mb))
            if bar is not None:
                bar.n = min(round(now), bar.total)
                bar.refresh()
        runner.join(timeout=SAMPLE_S)
    if bar is not None:
        bar.close()
    if sup.error:
        raise RuntimeError(sup.error)
    duration = max((t for s in samples.values() for t, _ in s), default=0.0)

    memory = {}
    for name, s in samples.items():
        if len(s) < 2:
            continue
        after = [mb for t, mb in s if t >= warmup * duration] or [s[-1][1]]
        base, peak = after[0], max(mb for _, mb in s)
        span_min = max((duration * (1 - warmup)) / 60, 1e-9)
        memory[name] = {
            "rss_after_warmup_mb": round(base, 1),
            "rss_max_mb": round(peak, 1),
            "rss_end_mb": round(s[-1][1], 1),
            "growth_after_warmup_mb": round(max(after) - base, 1),
            "growth_mb_per_min": round((after[-1] - base) / span_min, 2),
        }

    reports = stage_reports(plan.log_dir, ("source", "tracker", "fusion"))
    source, tracker, fusion = reports["source"], reports["tracker"], reports["fusion"]
    fusion_run = json.loads((out / "run.json").read_text()) if (out / "run.json").exists() else {}
    seconds = figure(source, "seconds")
    accounting = {
        "planned": loops * n,
        "published": figure(source, "published"),
        "source_dropped": figure(source, "dropped"),
        "source_hz": figure(source, "hz"),
        "tracker_received": input_count(tracker, "frames", "received"),
        "tracker_dropped": input_count(tracker, "frames", "dropped"),
        "tracker_frames": figure(tracker, "frames"),
        "fusion_dropped": input_count(fusion, "tracks_frame", "dropped"),
        "frames_in_map": fusion_run.get("frames_in_map", figure(fusion, "frames_in_map")),
        "fusion_hz": fusion_run.get("hz"),
    }
    return {
        "minutes": minutes,
        "rate_hz": rate_hz,
        "resolution": "640x480",
        "sequence_frames": n,
        "loops": loops,
        "duration_s": round(duration, 1),
        "source_seconds": seconds,
        "memory": memory,
        "frames": accounting,
        "segments": fusion_run.get("segments"),
        "processes": {k: v["peak_rss_mb"] for k, v in sup.summary()["services"].items()},
    }


def table(res: dict) -> str:
    rows = [f"{'process':<12} {'RSS warm (MB)':>13} {'max':>8} {'growth':>8} {'MB/min':>8}"]
    for name, m in res["memory"].items():
        rows.append(f"{name:<12} {m['rss_after_warmup_mb']:>13.0f} {m['rss_max_mb']:>8.0f} {m['growth_after_warmup_mb']:>8.0f} {m['growth_mb_per_min']:>8.2f}")
    f = res["frames"]
    rows.append("")
    rows.append(
        f"frames: planned {f['planned']}, published {f['published']} ({f['source_hz']} Hz), dropped by source {f['source_dropped']}, "
        f"tracker received {f['tracker_received']} dropped {f['tracker_dropped']}, fusion dropped {f['fusion_dropped']}, in map {f['frames_in_map']}"
    )
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=30.0, help="source rate, Hz")
    ap.add_argument("--frames", type=int, default=300, help="frames of the 640x480 sequence replayed in laps")
    ap.add_argument("--sequence", type=Path, default=None, help="a sequence folder instead of the generated one")
    ap.add_argument("--json", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="tg-load-") as tmp:
        work = Path(tmp)
        seq = args.sequence or make_sequence(ROOT / "benchmarks" / "out" / f"load_seq_{args.frames}", args.frames)
        res = run_load(seq, work, minutes=args.minutes, rate_hz=args.rate)
    res["machine"] = {"platform": platform.platform(), "cpus": __import__("os").cpu_count(), "python": platform.python_version()}
    res["when"] = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    res["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=2))
    print(table(res))
    print(f"JSON: {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
