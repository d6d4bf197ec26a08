"""Config variants and mapping runs of the bench, each ``trackgraph map`` in its own process.

A run in its own process has its own wall time and peak memory: runs one after another in one
process would report the largest peak of all of them, and share warmed-up caches.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

from shared.config import TrackGraphConfig, load_config
from shared.config.base import deep_merge, save_resolved, validate

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]


class BenchError(RuntimeError):
    """A bench step failed; the message names the step and the reason."""


def write_variant(config: Path, overrides: dict, path: Path) -> Path:
    """``config`` with ``overrides`` merged in, validated and written resolved to ``path``."""
    base = load_config(config).model_dump(mode="json")
    cfg = validate(TrackGraphConfig, deep_merge(base, overrides), f"{config} with {overrides}")
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_resolved(cfg, path)


def map_run(
    sequence: Path, config: Path, out: Path, *, dataset: str | None = None, max_frames: int | None = None
) -> dict[str, Any]:
    """``trackgraph map`` in a child process; its ``run.json`` summary."""
    cmd = [sys.executable, "-m", "services.cli", "map", str(sequence), "--config", str(config), "--out", str(out), "--json"]
    if dataset:
        cmd += ["--dataset", dataset]
    if max_frames:
        cmd += ["--max-frames", str(max_frames)]
    log.info("mapping %s with %s", sequence, config.name)
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, check=False)
    if proc.returncode != 0:
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        raise BenchError(f"trackgraph map with {config} failed: {lines[-1] if lines else f'exit {proc.returncode}'}")
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip().startswith("{")]
    if not lines:
        raise BenchError(f"trackgraph map with {config} printed no summary")
    return json.loads(lines[-1])


def evaluate_map(map_dir: Path, gt: Path) -> dict[str, Any]:
    """OpenLex3D segmentation and retrieval, class-agnostic instances, and the top-1 query hit
    rates with the gallery's max (eq. 10) and mean."""
    from services.query.evaluate import top1_hit_rates
    from services.query.offline import map_text_encoder
    from shared.eval.gt import load_gt
    from shared.eval.instances import evaluate_instances
    from shared.eval.openlex3d import evaluate_openlex3d
    from shared.eval.prediction import load_prediction

    # Both scorings take the loaded map and ground truth; read them once.
    gt_data, pred = load_gt(gt), load_prediction(map_dir)
    ol = evaluate_openlex3d(pred, gt_data, map_text_encoder(map_dir))
    inst = evaluate_instances(pred, gt_data)
    keys = (
        "synonyms", "depictions", "vis_sim", "clutter", "missing", "incorrect", "ap", "ap50", "ap25", "top1_hit_rate",
        "alignment", "alignment_threshold",
    )  # fmt: skip
    out: dict[str, Any] = {k: ol.get(k) for k in keys}
    out["instances"] = {k: inst.get(k) for k in ("ap", "ap50", "ap25", "segments_per_object")}
    out["gallery"] = top1_hit_rates(map_dir, gt)
    return out


def machine() -> dict[str, Any]:
    """What ran the bench: OS, CPU model and count, Python, and the GPUs ``nvidia-smi`` lists."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = None
    try:  # the mapping runs are child processes: ask the driver, not torch, what they ran on
        names = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True, timeout=10, check=True).stdout
        gpu = ", ".join(n.strip() for n in names.splitlines() if n.strip()) or None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"platform": platform.platform(), "cpu": cpu, "cpus": os.cpu_count(), "python": platform.python_version(), "gpu": gpu}


def git_commit() -> str | None:
    """The checkout's commit, with ``-dirty`` when it has uncommitted changes; None outside git
    (an installed package)."""
    if not (REPO / ".git").exists():
        return None
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return sha + ("-dirty" if dirty else "")
