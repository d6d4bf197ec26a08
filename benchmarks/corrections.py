"""Benchmark: pose corrections (loop closures) on drifting synthetic odometry.

Run from the repository root::

    python benchmarks/corrections.py --quick    # the cost of one correction on the 900-frame demo walk
    python benchmarks/corrections.py            # and the map quality table (oracle and synthetic configs)

Two parts.

**Cost** (always): the ``demo`` preset (three rooms, 900 frames at 640x480, generated once
into ``benchmarks/out/``) with odometry drift 0.02 m/m, fused frame by frame by
:class:`services.fusion.core.FusionCore` from ground-truth tracks (the tracker and perception
are not what is measured), once: the map is kept in ``benchmarks/out/`` and loaded as a
resumed fusion loads it. After the 900th frame one correction states the true pose of every
frame: the largest correction a map of that length can get. Reported: the time to move the
map (TSDF voxels, segments, surface, views, trajectory), the time of the graph update after
it, the voxels and segments moved, the host memory the move allocates at its peak (RSS sampled
every 20 ms, above the RSS before it), and what corrections keep for good (the pose book: two
poses per frame and one table per applied correction).

**Quality** (without ``--quick``): the ``revisit`` preset (room A, a 9 m corridor, room B and
back) with drift 0.02 and its loop-closure corrections, mapped by ``trackgraph map`` with the
oracle and the synthetic configs: true poses, drifting odometry alone, with the corrections,
and with each correction arriving 100 frames after its loop closure. Reported: instance AP50
and segments per object against the ground truth (``trackgraph eval instances``).

Results go to ``benchmarks/out/corrections.json`` and tables on stdout.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from shared.procfs import status_mb  # noqa: E402

OUT = ROOT / "benchmarks" / "out"
DRIFT = 0.02
LATE_FRAMES = 100


def _sequence(preset: str, frames: int | None, seed: int = 0, drift: float = DRIFT) -> Path:
    """A drifting synthetic sequence, generated once and reused."""
    from shared.synth import run_synth

    name = f"corrections_{preset}_{seed}" + (f"_{frames}" if frames else "") + ("" if drift == DRIFT else f"_drift{drift:g}")
    out = OUT / name
    if not (out / "corrections.jsonl").is_file():
        overrides = {"camera": {"frames": frames}} if frames else None
        run_synth(preset, seed, out, overrides, overwrite=True, progress=True, drift=drift)
    return out


def _true_copy(seq: Path) -> Path:
    """The same sequence with its true poses as traj.txt (images linked, not copied)."""
    out = seq.parent / (seq.name + "_true")
    if not (out / "traj.txt").is_file():
        out.mkdir(parents=True, exist_ok=True)
        for entry in seq.iterdir():
            if entry.name in ("traj.txt", "traj_gt.txt", "corrections.jsonl"):
                continue
            link = out / entry.name
            if not link.exists():
                os.symlink(entry.resolve(), link)
        shutil.copyfile(seq / "traj_gt.txt", out / "traj.txt")
    return out


class PeakRss:
    """Peak resident memory of this process while the block runs, sampled every 20 ms."""

    def __enter__(self) -> PeakRss:
        self.before = status_mb("VmRSS") or 0.0
        self.peak = self.before
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, status_mb("VmRSS") or 0.0)
            time.sleep(0.02)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, status_mb("VmRSS") or 0.0)


def cost(frames: int) -> dict:
    """One correction of every frame of a ``frames``-frame drifting map."""
    from services.fusion.core import FusionCore
    from services.mapping import prepare_config
    from services.tracker.build import build_tracker
    from shared.config import TrackGraphConfig
    from shared.datasets import open_sequence
    from shared.graph.store import MapStore
    from shared.messages.poses import PoseCorrection

    seq = _sequence("demo", None if frames == 900 else frames)
    cfg = prepare_config(TrackGraphConfig.model_validate({"keyframe_vl": {"vl": {"backend": "simulated"}}, "tracker": {"mode": "ground_truth"}}), seq)
    reader = open_sequence(seq)
    core = FusionCore(cfg.fusion, device="cpu")
    n = min(frames, len(reader))
    # the drifting map, fused once and kept (saved and loaded as fusion resumes)
    store = MapStore(OUT / f"corrections_map_demo_{n}" / "graph")
    fuse_s = None
    if store.latest_name() is not None:
        state = store.load()
        core.load_state_dict(state.extra, state.snapshot)
    else:
        tracker = build_tracker(cfg)
        t0 = time.perf_counter()
        for i in range(n):
            tracker.begin_frame(reader.frame(i))
            tracked = tracker.end_frame()
            feats = tracker.take_track_features(i)
            if feats is not None:
                core.add_track_features(feats)
            core.add_frame(tracked)
            if i % 100 == 0:
                logging.info("fused %d of %d frames", i, n)
        core.finish()
        fuse_s = round(time.perf_counter() - t0, 2)
        store.save(core.snapshot(with_mesh=True), extra_state=core.state_dict())
    true = np.loadtxt(seq / "traj_gt.txt").reshape(-1, 4, 4)[:n]
    c = PoseCorrection(correction_id=1, frame_index=n - 1, frames=np.arange(n), poses=true)
    tsdf_bytes = core.tsdf.nbytes()
    with PeakRss() as mem:
        out = core.apply_correction(c)
    book = core.book.state_dict()
    return {
        "frames": n,
        "fuse_seconds": fuse_s,
        "seconds_move": round(out.seconds_move, 3),
        "seconds_update": round(out.seconds_update, 3),
        "frames_moved": out.frames_moved,
        "max_shift_m": round(out.max_shift_m, 3),
        "segments": len(core.segments.segments),
        "active_blocks": core.tsdf.active_blocks,
        "archived_blocks": core.tsdf.archived_blocks,
        "tsdf_mb": round(sum(tsdf_bytes.values()) / 1e6, 1),
        "rss_before_mb": round(mem.before, 1),
        "rss_peak_extra_mb": round(mem.peak - mem.before, 1),
        "pose_book_kb": round(sum(np.asarray(v).nbytes for v in book.values()) / 1e3, 1),
    }


def quality(configs: list[str], drift: float = DRIFT) -> list[dict]:
    from services.mapping import run_map
    from shared.config import load_config
    from shared.eval import eval_instances
    from shared.messages.poses import read_corrections

    seq = _sequence("revisit", None, drift=drift)
    true_seq = _true_copy(seq)
    late = seq / "corrections_late.jsonl"
    if not late.is_file():
        lines = [c.model_copy(update={"apply_after_frame": c.frame_index + LATE_FRAMES}).to_json() for c in read_corrections(seq / "corrections.jsonl")]
        late.write_text("\n".join(lines) + "\n")
    rows = []
    for name in configs:
        cfg = load_config(ROOT / "deploy" / "configs" / f"{name}.yaml")
        for variant, path, corrections in (
            ("true poses", true_seq, None),
            ("drift, no corrections", seq, None),
            ("drift, corrections", seq, seq / "corrections.jsonl"),
            (f"drift, corrections {LATE_FRAMES} frames late", seq, late),
        ):
            out = OUT / f"corrections_map_{seq.name}_{name}_{variant.split(',')[0].replace(' ', '_')}_{'none' if corrections is None else corrections.stem}"
            summary = run_map(path, cfg, out, corrections=corrections, progress=True)
            ev = eval_instances(out, seq / "gt")
            rows.append({
                "config": name, "drift": drift, "variant": variant, "ap50": round(ev["ap50"], 3), "ap": round(ev["ap"], 3),
                "segments_per_object": round(ev["segments_per_object"], 3), "map_seconds": summary["seconds"],
                "corrections": summary.get("corrections"),
            })  # fmt: skip
            logging.info("%s / %s: AP50 %.3f", name, variant, ev["ap50"])
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="only the cost of one correction")
    p.add_argument("--frames", type=int, default=900, help="frames of the map corrected (the demo walk resampled)")
    p.add_argument("--configs", nargs="+", default=["oracle", "synthetic"], help="configs of the quality table")
    p.add_argument("--drift", type=float, nargs="+", default=[DRIFT], help="odometry drift rates (m per m) of the quality table")
    p.add_argument("--out", type=Path, default=OUT / "corrections.json")
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    OUT.mkdir(parents=True, exist_ok=True)
    result = {
        "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count()},
        "drift": DRIFT,
        "cost": cost(args.frames),
    }
    c = result["cost"]
    print(f"\none correction of all {c['frames']} frames of a drifting map (demo walk, 640x480, 3 cm)")
    print("| move s | graph update s | frames moved | max shift m | segments | active / archived blocks | TSDF MB | peak extra RSS MB | pose book KB |")
    print("|---|---|---|---|---|---|---|---|---|")
    print(f"| {c['seconds_move']:.3f} | {c['seconds_update']:.3f} | {c['frames_moved']} | {c['max_shift_m']:.2f} | {c['segments']} | "
          f"{c['active_blocks']} / {c['archived_blocks']} | {c['tsdf_mb']:.0f} | {c['rss_peak_extra_mb']:.0f} | {c['pose_book_kb']:.0f} |")
    print(f"target: move under 1 s: {'pass' if c['seconds_move'] < 1.0 else 'FAIL'}")
    if not args.quick:
        result["quality"] = [row for d in args.drift for row in quality(args.configs, d)]
        print("\nrevisit, seed 0, instance quality against the ground truth")
        print("| config | drift m/m | variant | AP50 | AP | segments / object |")
        print("|---|---|---|---|---|---|")
        for r in result["quality"]:
            print(f"| {r['config']} | {r['drift']:g} | {r['variant']} | {r['ap50']:.3f} | {r['ap']:.3f} | {r['segments_per_object']:.3f} |")
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
