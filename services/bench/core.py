"""The whole bench: for each config, mapping runs at 3 cm, at 5 cm and with per-frame
segmentation, their evaluations, and the highest input rate the distributed system sustains
with each tracker mode; then ``bench.json``, ``bench.md`` and ``plots/`` in the output folder.

Every mapping run is ``trackgraph map`` in its own process, and every rate trial a fresh set
of service processes, so no figure carries another run's memory or warm caches.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from services.bench.rate import live_trial, search_rate, trial_frames
from services.bench.report import markdown, plots
from services.bench.runs import (
    BenchError,
    evaluate_map,
    git_commit,
    machine,
    map_run,
    write_variant,
)
from shared.config.base import ConfigError
from shared.io import atomic_write_text

log = logging.getLogger(__name__)

DEFAULT_CONFIG = "synthetic"
"""The preset a bench without ``--config`` runs (shared/presets.py)."""
VARIANTS: dict[str, dict] = {
    "3cm": {"fusion": {"tsdf": {"voxel_size": 0.03}}},
    "5cm": {"fusion": {"tsdf": {"voxel_size": 0.05}}},
    "per_frame": {"fusion": {"tsdf": {"voxel_size": 0.03}}, "tracker": {"mode": "per_frame"}},
}
"""Run name -> overrides on the config: the efficiency table's two voxel sizes (IV-A) and the
tracker ablation's per-frame segmentation."""
HIERARCHY_RUN = "3cm"
"""The run whose rooms the hierarchy table scores (the other quality tables' run)."""
HIERARCHY_KEYS = (
    "n_pred", "n_gt", "precision", "recall", "f1", "over_segmented", "under_segmented", "mean_iou", "type_accuracy",
    "room_type_top1",
)  # fmt: skip
RATE_START_SHARE = 0.75
"""The rate search starts at this share of the mode's in-process rate: the distributed system
shares the same cores between more processes."""


def _config_names(paths: Sequence[Path]) -> list[str]:
    names: list[str] = []
    for p in paths:
        name = p.stem
        k = 2
        while name in names:
            name, k = f"{p.stem}-{k}", k + 1
        names.append(name)
    return names


def _rate_search(
    seq: Path, cfg: Path, work: Path, start: float, trials: int, frames: int | None, seconds: float | None,
    advance: Callable[[str], None],
) -> tuple[float | None, list[dict[str, Any]]]:
    """``search_rate`` over live trials of ``cfg``, each in its own folder under ``work``."""
    from shared.config import load_config

    tracker = load_config(cfg).tracker
    interval = 1 if tracker.mode == "per_frame" else tracker.keyframe_interval
    count = 0

    def trial(rate: float) -> dict[str, Any]:
        nonlocal count
        res = live_trial(seq, cfg, work / f"trial{count}", rate, trial_frames(rate, seconds, frames, interval))
        count += 1
        advance(f"{work.name} at {rate:.3g} Hz: {'sustained' if res['sustained'] else 'not sustained'}")
        return res

    return search_rate(trial, start, trials)


def _room_ranker(map_dir: Path):
    """The query core's room ranking on the map, or None where it cannot be built (logged)."""
    from services.query.core import QueryError
    from services.query.roomtypes import map_room_ranker

    try:
        return map_room_ranker(map_dir)
    except (QueryError, OSError, ValueError) as exc:
        log.warning("hierarchy table: no room-type queries for %s: %s", map_dir, exc)
        return None


def evaluate_hierarchy(map_dir: Path, gt: Path) -> dict[str, Any]:
    """The rooms of ``map_dir`` against the ground truth (``shared.eval.rooms``): precision,
    recall and F1 at IoU 0.5, over/under-segmentation, mean IoU and type accuracy. A map without ``rooms.npz``, or ground truth
    without rooms, gives None figures and the reason in ``error`` (logged), not a failure."""
    from shared.eval.errors import EvalInputError
    from shared.eval.rooms import eval_rooms

    out: dict[str, Any] = {k: None for k in HIERARCHY_KEYS}
    out.update(n_types=None, per_room=[], room_queries=None, error=None)
    try:
        rooms = eval_rooms(map_dir, gt, rank_rooms=_room_ranker(map_dir))
        out.update({k: rooms[k] for k in HIERARCHY_KEYS}, per_room=rooms["per_room"], room_queries=rooms["room_queries"])
        out["n_types"] = len({r["gt_type"] for r in rooms["per_room"]})
    except EvalInputError as exc:
        out["error"] = str(exc)
        log.warning("hierarchy table: n/a for %s: %s", map_dir, exc)
    return out


def prepare_sequence(out: Path, preset: str | None, seed: int, sequence: Path | None, gt: Path | None) -> tuple[Path, Path, str]:
    """(sequence folder, ground-truth folder, a name for the report)."""
    if sequence is not None:
        if not Path(sequence).is_dir():
            raise BenchError(f"{sequence}: no such sequence folder")
        if gt is None:
            raise BenchError("--sequence needs --gt GT_DIR (the OpenLex3D ground truth of the scene)")
        if not Path(gt).is_dir():
            raise BenchError(f"{gt}: no such ground-truth folder")
        return Path(sequence), Path(gt), Path(sequence).name
    if preset is None:
        from shared.synth.config import PRESETS

        raise BenchError(f"give --preset {'|'.join(PRESETS)}, or --sequence SEQ_DIR --gt GT_DIR")
    from shared.synth import run_synth

    seq = out / f"sequence-{preset}-{seed}"
    if not (seq / "traj.txt").is_file():
        log.info("generating the %s scene (seed %d)", preset, seed)
        run_synth(preset, seed, seq, overwrite=True, progress=False)
    return seq, Path(gt) if gt is not None else seq, f"{preset} preset, seed {seed}"


def run_bench(
    out: Path,
    *,
    preset: str | None = None,
    seed: int = 0,
    sequence: Path | None = None,
    gt: Path | None = None,
    configs: Sequence[Path] = (),
    dataset: str | None = None,
    max_frames: int | None = None,
    rate_trials: int = 3,
    rate_frames: int | None = 60,
    rate_seconds: float | None = None,
    random_weights: Path | None = None,
    resume: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """Run every step; returns the result written to ``out/bench.json``.

    ``rate_seconds``: each live trial lasts about this long at its rate (instead of
    ``rate_frames`` frames), two keyframes at least. ``random_weights``: a folder for
    random-weight files of each config's models, which the runs then use (timings of the
    real architectures without their weights; the quality columns mean nothing then).
    ``resume``: a map already in ``out/maps`` with its ``run.json`` is scored, not made
    again, so an interrupted bench goes on where it stopped.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    from shared.presets import config_path

    try:
        configs = [config_path(c) for c in configs] or [config_path(DEFAULT_CONFIG)]
    except ConfigError as exc:
        raise BenchError(str(exc)) from None
    seq, gt_dir, seq_name = prepare_sequence(out, preset, seed, sequence, gt)
    names = _config_names(configs)
    steps = len(configs) * (len(VARIANTS) + 2 * max(rate_trials, 0))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps, unit="step", desc="bench")

    def advance(what: str) -> None:
        if bar is not None:
            bar.set_postfix_str(what)
            bar.update(1)

    t0 = time.monotonic()
    results = []
    hierarchy: list[dict[str, Any]] = []
    try:
        for name, path in zip(names, configs, strict=True):
            entry: dict[str, Any] = {"name": name, "path": str(path), "runs": {}, "rate": {}, "random_weights": random_weights is not None}
            base = path
            if random_weights is not None:
                from services.models.random_weights import random_weight_overrides
                from shared.config import load_config

                log.info("random-weight models of %s in %s", path, random_weights)
                base = write_variant(path, random_weight_overrides(load_config(path), random_weights), out / "configs" / f"{name}-random.yaml")
            for run_name, overrides in VARIANTS.items():
                cfg = write_variant(base, overrides, out / "configs" / f"{name}-{run_name}.yaml")
                map_dir = out / "maps" / f"{name}-{run_name}"
                done = map_dir / "run.json"
                if resume and done.is_file():
                    log.info("reusing the finished map %s", map_dir)
                    run = json.loads(done.read_text())
                else:
                    run = map_run(seq, cfg, map_dir, dataset=dataset, max_frames=max_frames)
                ev = evaluate_map(map_dir, gt_dir)
                entry["runs"][run_name] = {"config": str(cfg), "map": str(map_dir), "run": run, "eval": ev}
                entry.setdefault("backends", run.get("backends", {}))
                advance(f"{name} {run_name}")
            if rate_trials > 0:
                for run_name in ("3cm", "per_frame"):
                    run = entry["runs"][run_name]
                    start = RATE_START_SHARE * float(run["run"]["hz"] or 1.0)
                    work = out / "rate" / f"{name}-{run_name}"
                    best, trials = _rate_search(seq, Path(run["config"]), work, start, rate_trials, rate_frames, rate_seconds, advance)
                    entry["rate"][run_name] = {
                        "max_sustained_hz": best, "trials": trials, "frames_per_trial": rate_frames, "seconds_per_trial": rate_seconds,
                    }  # fmt: skip
            if HIERARCHY_RUN in entry["runs"]:
                run = entry["runs"][HIERARCHY_RUN]
                hierarchy.append({"config": name, "run": HIERARCHY_RUN, "map": run["map"], **evaluate_hierarchy(Path(run["map"]), gt_dir)})
            results.append(entry)
    finally:
        if bar is not None:
            bar.close()

    res: dict[str, Any] = {
        "sequence": str(seq),
        "sequence_name": seq_name,
        "gt": str(gt_dir),
        "preset": preset,
        "seed": seed if sequence is None else None,
        "commit": git_commit(),
        "machine": machine(),
        "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "seconds": round(time.monotonic() - t0, 1),
        "configs": results,
        "hierarchy": hierarchy,
    }
    for entry in results:
        entry["commit"], entry["machine"] = res["commit"], res["machine"]
    atomic_write_text(out / "bench.md", markdown(res))
    res["plots"] = [str(p) for p in plots(res, out / "plots")]
    atomic_write_text(out / "bench.json", json.dumps(res, indent=2))
    return res
