"""Benchmark: the whole distributed system with the paper's models, per stage, per process.

Run from the repository root::

    python benchmarks/gpu_pipeline.py --device cuda        # the full run (on a GPU machine)
    python benchmarks/gpu_pipeline.py --tiny               # a few small frames on the CPU (CI)
    python benchmarks/gpu_pipeline.py --resolution 1200x680 --frames 60 --device cpu

For each config (``--configs``, default the ``paper`` and ``onboard`` presets of
deploy/configs), on random weights in the official layouts (``services.models.random_weights``:
the real architectures, FLOPs and loading paths, written once into ``--weights``), over a
synthetic sequence (``--preset demo`` at ``--resolution`` 1200x680, Replica's size, and
``--frames`` 600; generated once into the output folder):

1. **Stages**: ``trackgraph map`` (the in-process pipeline, one child process) with a timer on
   each stage: DINOv3 (the tracker's dense features, one call a frame), propagation (eq. 1,
   every propagated frame), upsample (propagated labels to full resolution), FastSAM (one
   keyframe), CLIP (one keyframe's crops), and in fusion the service's own timers of one
   frame's TSDF integration and hypothesis vote (``IntegrateStats``), marching cubes (mesh),
   the segment updater (segments) and the whole graph update (graph_update). Median ms per
   call, the first call (warm-up: compilation, cudnn, allocations) left out when there are
   others. On CUDA each timer synchronises torch's device, so this run is not timed as a
   whole; Open3D work still queued when its integrate returns is waited for in the vote's
   first copy from the GPU, so on CUDA read integrate + vote together as a frame's fusion.
2. **Rate**: the highest input rate the distributed system sustains, by the bench's own search
   and rule (``services.bench.rate``): router, keyframe_vl, tracker, fusion and query as
   processes and a live source; sustained when no stage dropped a frame, every frame reached
   the map and the map fused at 90% of the input rate or more (and keyframe_vl answered at
   that pace). The search starts at 75% of the stage run's in-process rate, like
   ``trackgraph bench run``. While a trial runs, every service process's peak RAM (VmHWM) and,
   where ``nvidia-smi`` reports them, its GPU memory are sampled; fusion's own
   ``torch.cuda.max_memory_allocated`` (its ``run.json``) is kept too.
3. **Time per sequence** at 3 cm and 5 cm voxels: ``trackgraph map`` of the whole sequence,
   each in its own process (``services.bench.runs.map_run``, as the bench's efficiency table).

Random weights: the times and memory are the models' own; the maps mean nothing. ``--tiny``
(for CI and CPUs): the ``small`` scene at 160x120 in 20 frames, FastSAM-s at 160 px, CLIP
ViT-B-32, DINOv3 at 128 px, a keyframe every 4 frames, one rate trial, the 3 cm map only,
on the CPU.
Writes ``OUT/gpu_pipeline.json`` (device, torch/CUDA/Open3D versions, git commit) and prints
the tables.
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from services.bench.core import RATE_START_SHARE, VARIANTS  # noqa: E402
from services.bench.rate import PACE_SHARE, live_trial, search_rate, trial_frames  # noqa: E402
from services.bench.runs import BenchError, git_commit, machine, map_run, write_variant  # noqa: E402
from shared.config.base import deep_merge  # noqa: E402
from shared.devices import resolve_device  # noqa: E402
from shared.io import atomic_write_text  # noqa: E402
from shared.logs import setup_logging  # noqa: E402
from shared.procfs import status_mb  # noqa: E402

log = logging.getLogger("bench.gpu_pipeline")

DEFAULT_OUT = ROOT / "benchmarks" / "out" / "gpu_pipeline"
DEFAULT_WEIGHTS = ROOT / "benchmarks" / "out" / "random_weights"
RESULT = "gpu_pipeline.json"
CONFIGS = ROOT / "deploy" / "configs"
STAGES = ("dinov3", "propagation", "upsample", "fastsam", "clip", "vote", "integrate", "mesh", "segments", "graph_update")
"""Timed stages, in pipeline order (the issue's eight, plus the label upsampling and the whole
graph update that holds mesh and segments)."""
PROCESSES = ("router", "keyframe_vl", "tracker", "fusion", "query", "source")
EXTRA_SERVICES = ({"name": "query"},)
"""Started with every rate trial beside the bench's four stages (the query service only
serves; the rule does not judge it)."""
VOXELS = ("3cm", "5cm")
SAMPLE_S = 0.5
"""How often a trial's processes are sampled (memory)."""

TINY = {
    "preset": "small",
    "resolution": (160, 120),
    "frames": 20,
    "rate_trials": 1,
    # One voxel size: the 5 cm map is the same code at another voxel and took a quarter of
    # the tiny run's CI time (each map loads every model again).
    "voxels": ("3cm",),
    "overrides": {
        "keyframe_vl": {"segmenter": {"weights": "weights/FastSAM-s.pt", "imgsz": 160}, "vl": {"model": "ViT-B-32"}},
        "tracker": {"keyframe_interval": 4, "features": {"short_side": 128}},
    },
    "max_masks": 8,
}
"""``--tiny``: small models at a small resolution, every stage still run."""


# ---------------------------------------------------------------------------------------------
# stage timers (in the child process that maps the sequence)


def _sync() -> None:
    """Wait for queued GPU work, so a timer holds its stage's kernels (no-op without CUDA)."""
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


class StageTimes:
    """Milliseconds of each call of each stage (appended from any thread)."""

    def __init__(self) -> None:
        self.ms: dict[str, list[float]] = defaultdict(list)
        self._lock = threading.Lock()

    def add(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.ms[stage].append(1e3 * float(seconds))

    def timed(self, fn: Any, stage: str) -> Any:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            _sync()
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                _sync()
                self.add(stage, time.perf_counter() - t0)

        return wrapper

    def summary(self) -> dict[str, dict[str, Any]]:
        return {s: stage_summary(self.ms[s]) for s in STAGES if self.ms.get(s)}


def stage_summary(ms: list[float]) -> dict[str, Any]:
    """calls, the first call, and median / mean / p90 / max of the others (of all if only one)."""
    rest = ms[1:] if len(ms) > 1 else ms
    srt = sorted(rest)
    return {
        "calls": len(ms),
        "first_ms": round(ms[0], 3),
        "ms_median": round(statistics.median(rest), 3),
        "ms_mean": round(statistics.fmean(rest), 3),
        "ms_p90": round(srt[min(len(srt) - 1, int(0.9 * len(srt)))], 3),
        "ms_max": round(srt[-1], 3),
        "ms_total": round(sum(ms), 3),
    }


class _TimedCallable:
    """A callable (the tracker's dense features) timed per call; attributes pass through."""

    def __init__(self, inner: Any, stage: str, times: StageTimes) -> None:
        self._inner = inner
        self._call = times.timed(inner.__call__, stage)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._call(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def install_stage_timers(times: StageTimes) -> None:
    """Wrap the pipeline's stage calls in timers (this process only: the child that maps)."""
    import services.tracker.core as tracker_core
    from services.fusion.core import FusionCore
    from services.fusion.layers.segments import SegmentLayer
    from services.fusion.volume.tsdf import HypothesisTSDF
    from services.keyframe_vl.core import KeyframeVLCore

    init = tracker_core.TrackerCore.__init__

    def tracker_init(self: Any, cfg: Any, features: Any, *args: Any, **kwargs: Any) -> None:
        init(self, cfg, _TimedCallable(features, "dinov3", times), *args, **kwargs)

    tracker_core.TrackerCore.__init__ = tracker_init  # type: ignore[method-assign]
    tracker_core.propagate_with_config = times.timed(tracker_core.propagate_with_config, "propagation")
    tracker_core.upsample_ids = times.timed(tracker_core.upsample_ids, "upsample")  # slots to track ids, upsampled
    KeyframeVLCore.segment = times.timed(KeyframeVLCore.segment, "fastsam")  # type: ignore[method-assign]
    KeyframeVLCore.features = times.timed(KeyframeVLCore.features, "clip")  # type: ignore[method-assign]
    integrate = HypothesisTSDF.integrate

    def tsdf_integrate(self: Any, *args: Any, **kwargs: Any) -> Any:
        _sync()
        stats = integrate(self, *args, **kwargs)
        times.add("integrate", stats.seconds_tsdf)  # fusion's own timers (IntegrateStats)
        times.add("vote", stats.seconds_hypotheses)
        return stats

    HypothesisTSDF.integrate = tsdf_integrate  # type: ignore[method-assign]
    # a graph update meshes through one of these: Open3D on the grid (CUDA), or the numba
    # marching cubes over the copied blocks (CPU; extract_mesh is not called then), of the
    # changed blocks only with fusion.incremental_mesh
    HypothesisTSDF.extract_mesh = times.timed(HypothesisTSDF.extract_mesh, "mesh")  # type: ignore[method-assign]
    HypothesisTSDF.mesh_of = times.timed(HypothesisTSDF.mesh_of, "mesh")  # type: ignore[method-assign]
    HypothesisTSDF.mesh_of_update = times.timed(HypothesisTSDF.mesh_of_update, "mesh")  # type: ignore[method-assign]
    SegmentLayer.update = times.timed(SegmentLayer.update, "segments")  # type: ignore[method-assign]
    FusionCore.update = times.timed(FusionCore.update, "graph_update")  # type: ignore[method-assign]


def stage_child(config: Path, sequence: Path, map_dir: Path, result: Path) -> int:
    """The child process of :func:`profile_stages`: map with timers, write the result JSON."""
    from services.mapping import run_map
    from shared.config import load_config

    times = StageTimes()
    install_stage_timers(times)
    summary = run_map(sequence, load_config(config), map_dir, progress=False)
    result.write_text(json.dumps({"stages": times.summary(), "run": summary}, indent=2))
    return 0


def profile_stages(config: Path, sequence: Path, work: Path) -> dict[str, Any]:
    """Per-stage ms of ``config`` on ``sequence``: the timed map in a child process."""
    work.mkdir(parents=True, exist_ok=True)
    result = work / "stages.json"
    result.unlink(missing_ok=True)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--stage-child", str(config), str(sequence), str(work / "map"), str(result)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "TRACKGRAPH_LOG": os.environ.get("TRACKGRAPH_LOG", "WARNING")}
    log.info("timing the stages of %s", config.name)
    with open(work / "stages.log", "wb") as logf:
        proc = subprocess.run(cmd, stdout=logf, stderr=subprocess.STDOUT, env=env, cwd=ROOT, check=False)
    if proc.returncode != 0 or not result.is_file():
        lines = [ln for ln in (work / "stages.log").read_text(errors="replace").splitlines() if ln.strip()]
        raise BenchError(f"stage timing of {config} failed: {lines[-1] if lines else f'exit {proc.returncode}'} (see {work / 'stages.log'})")
    return json.loads(result.read_text())


# ---------------------------------------------------------------------------------------------
# processes of a trial: peak RAM and GPU memory


def _children(root: int) -> list[int]:
    """Every descendant of ``root`` (Linux /proc)."""
    kids: dict[int, list[int]] = defaultdict(list)
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        kids[ppid].append(int(d))
    out, todo = [], [root]
    while todo:
        for c in kids.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def service_of(pid: int) -> str | None:
    """Which service a process of ``python -m services.cli ...`` is, from its command line."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = [a.decode(errors="replace") for a in f.read().split(b"\0") if a]
    except OSError:
        return None
    if "services.cli" not in argv:
        return None
    rest = argv[argv.index("services.cli") + 1 :]
    if not rest:
        return None
    if rest[0] == "serve" and len(rest) > 1:
        return rest[1]
    return rest[0] if rest[0] in ("router", "source") else None


def gpu_memory_by_pid() -> dict[int, float] | None:
    """MB of GPU memory of each process ``nvidia-smi`` lists; None without nvidia-smi."""
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-compute-apps=pid,used_memory", "--format=csv,noheader,nounits"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    res: dict[int, float] = {}
    for line in out.splitlines():
        parts = [p.strip() for p in line.split(",")]
        if len(parts) == 2 and parts[0].isdigit():
            try:
                res[int(parts[0])] = res.get(int(parts[0]), 0.0) + float(parts[1])
            except ValueError:
                continue
    return res


class ProcessWatch:
    """Samples the service processes this process started, while a trial runs: the largest
    VmHWM (peak RSS) of each, and with ``gpu``, the largest GPU memory ``nvidia-smi`` shows."""

    def __init__(self, gpu: bool) -> None:
        self.gpu = gpu
        self.rss: dict[str, float] = {}
        self.gpu_mb: dict[str, float] = {}
        self.gpu_matched = False
        """nvidia-smi listed one of the services at least once (in a container it may show
        other pids than ours: then no process has a GPU figure, rather than 0)."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> ProcessWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def sample(self) -> None:
        pids = {pid: service_of(pid) for pid in _children(os.getpid())}
        pids = {pid: name for pid, name in pids.items() if name}
        for pid, name in pids.items():
            mb = status_mb("VmHWM", pid)
            if mb:
                self.rss[name] = max(self.rss.get(name, 0.0), mb)
        if self.gpu:
            used = gpu_memory_by_pid()
            for pid, name in pids.items():
                if used and pid in used:
                    self.gpu_matched = True
                    self.gpu_mb[name] = max(self.gpu_mb.get(name, 0.0), used[pid])

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(SAMPLE_S)

    def result(self) -> dict[str, dict[str, float | None]]:
        return {
            name: {
                "peak_rss_mb": round(self.rss[name], 1) if name in self.rss else None,
                "peak_gpu_mb": (round(self.gpu_mb.get(name, 0.0), 1) if self.gpu_matched else None),
            }
            for name in PROCESSES
        }


# ---------------------------------------------------------------------------------------------
# the run


def environment(device: str) -> dict[str, Any]:
    """Device name, torch / CUDA / cuDNN / Open3D versions, the git commit, the machine."""
    import torch

    from shared.o3d import import_open3d

    cuda = torch.cuda.is_available()
    o3d = import_open3d()
    return {
        "device": device,
        "device_name": torch.cuda.get_device_name(0) if cuda and device.startswith("cuda") else (machine()["cpu"] or platform.processor()),
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "torch_threads": torch.get_num_threads(),
        "cudnn": torch.backends.cudnn.version() if cuda else None,
        "cuda_available": cuda,
        "gpus": [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if cuda else [],
        "open3d": o3d.__version__,
        "open3d_cuda": bool(o3d.core.cuda.is_available()),
        "tsdf_device": "cuda" if device.startswith("cuda") and cuda and o3d.core.cuda.is_available() else "cpu",
        "commit": git_commit(),
        "machine": machine(),
        "loadavg": os.getloadavg(),
    }


def make_sequence(out: Path, preset: str, size: tuple[int, int], frames: int, seed: int) -> Path:
    """The synthetic ``preset`` walk at ``size`` in ``frames`` frames, generated once."""
    from shared.synth import run_synth

    w, h = size
    seq = out / f"sequence-{preset}-{w}x{h}-{frames}-{seed}"
    if not (seq / "traj.txt").is_file():
        log.info("generating the %s scene at %dx%d, %d frames, into %s", preset, w, h, frames, seq)
        run_synth(preset, seed, seq, overrides={"camera": {"width": w, "height": h, "frames": frames}}, overwrite=True, progress=False)
    return seq


def config_path(name: str) -> Path:
    p = Path(name)
    if p.suffix in (".yaml", ".yml"):
        return p
    return CONFIGS / f"{name}.yaml"


def prepare_config(name: str, path: Path, out: Path, weights: Path, device: str, tiny: bool, seed: int) -> Path:
    """``path`` with the tiny models (``--tiny``), the device, and random weights for every
    learned model, written resolved to ``out/configs/NAME-random.yaml``."""
    from services.models.random_weights import RANDOM_MAX_MASKS, random_weight_overrides
    from shared.config import load_config

    overrides: dict[str, Any] = dict(TINY["overrides"]) if tiny else {}
    if device != "auto":
        overrides = deep_merge(overrides, {"tracker": {"device": device}, "keyframe_vl": {"device": device}})
    base = write_variant(path, overrides, out / "configs" / f"{name}-base.yaml")
    log.info("random-weight models of %s in %s (written once)", name, weights)
    rw = random_weight_overrides(load_config(base), weights, seed, max_masks=TINY["max_masks"] if tiny else RANDOM_MAX_MASKS)
    return write_variant(base, rw, out / "configs" / f"{name}-random.yaml")


def rate_search(config: Path, sequence: Path, work: Path, start_hz: float, trials: int, frames: int | None, gpu: bool) -> dict[str, Any]:
    """The bench's search over live trials of ``config`` (with the query service), each in its
    own folder under ``work``; each trial's process memory added to it."""
    from shared.config import load_config

    tracker = load_config(config).tracker
    interval = 1 if tracker.mode == "per_frame" else tracker.keyframe_interval
    count = 0

    def trial(rate: float) -> dict[str, Any]:
        nonlocal count
        folder = work / f"trial{count}"
        count += 1
        log.info("%s: live trial at %.3g Hz", config.stem, rate)
        with ProcessWatch(gpu) as watch:
            res = live_trial(sequence, config, folder, rate, trial_frames(rate, None, frames, interval), extra_services=EXTRA_SERVICES)
        procs = watch.result()
        run_json = folder / "map" / "run.json"
        if run_json.is_file():  # fusion's own figures: RSS at its end, torch's allocator peak
            run = json.loads(run_json.read_text())
            f = procs["fusion"]
            if run.get("peak_rss_mb"):
                f["peak_rss_mb"] = max(f["peak_rss_mb"] or 0.0, float(run["peak_rss_mb"]))
            f["torch_gpu_peak_mb"] = run.get("gpu_peak_mb")
        res["processes"] = procs
        log.info("%s at %.3g Hz: %s (drops %s, %s of %s in map, fused %s Hz)", config.stem, rate,
                 "sustained" if res["sustained"] else "not sustained", res["drops"], res.get("frames_in_map"),
                 res.get("published"), res.get("fused_hz"))  # fmt: skip
        return res

    best, done = search_rate(trial, start_hz, trials)
    peaks: dict[str, dict[str, float | None]] = {}
    for name in PROCESSES:
        vals = {k: [t["processes"][name][k] for t in done if t["processes"][name].get(k) is not None] for k in ("peak_rss_mb", "peak_gpu_mb", "torch_gpu_peak_mb")}
        peaks[name] = {k: (max(v) if v else None) for k, v in vals.items()}
    return {"max_sustained_hz": best, "start_hz": start_hz, "frames_per_trial": frames, "trials": done, "processes": peaks}


def run_config(name: str, path: Path, args: argparse.Namespace, seq: Path, device: str) -> dict[str, Any]:
    out: Path = args.out
    # the device as asked: 'auto' stays auto in the config, so the TSDF keeps to the CPU under a
    # CPU open3d while the models take the GPU
    cfg = prepare_config(name, path, out, args.weights, args.device, args.tiny, args.seed)
    from shared.config import load_config

    c = load_config(cfg)
    entry: dict[str, Any] = {
        "name": name,
        "path": str(path),
        "config": str(cfg),
        "backends": {"segmenter": c.keyframe_vl.segmenter.backend, "segmenter_weights": Path(c.keyframe_vl.segmenter.weights or "").name,
                     "vl_encoder": f"{c.keyframe_vl.vl.backend} {c.keyframe_vl.vl.model}", "dense_features": c.tracker.features.backend,
                     "dense_short_side": c.tracker.features.short_side, "keyframe_interval": c.tracker.keyframe_interval,
                     "voxel_size": c.fusion.tsdf.voxel_size, "stride": c.source.stride},
    }  # fmt: skip
    prof = profile_stages(cfg, seq, out / "stages" / name)
    entry["stages"] = prof["stages"]
    run = prof["run"]
    entry["stage_run"] = {k: run.get(k) for k in ("frames", "seconds", "hz", "peak_rss_mb", "gpu_peak_mb", "setup_seconds", "segments")}
    if args.rate_trials > 0:
        start = args.start_hz or RATE_START_SHARE * float(run.get("hz") or 1.0)
        entry["rate"] = rate_search(cfg, seq, out / "rate" / name, start, args.rate_trials, args.rate_frames, device.startswith("cuda"))
        entry["processes"] = entry["rate"]["processes"]
    else:
        entry["rate"], entry["processes"] = None, {}
    entry["maps"] = {}
    for voxel in TINY["voxels"] if args.tiny else VOXELS:
        var = write_variant(cfg, VARIANTS[voxel], out / "configs" / f"{name}-{voxel}.yaml")
        r = map_run(seq, var, out / "maps" / f"{name}-{voxel}")
        entry["maps"][voxel] = {k: r.get(k) for k in ("frames", "seconds", "hz", "peak_rss_mb", "gpu_peak_mb", "setup_seconds", "segments", "voxel_size")}
        log.info("%s at %s: %d frames in %.1f s", name, voxel, r["frames"], r["seconds"])
    return entry


def run(args: argparse.Namespace) -> dict[str, Any]:
    t0 = time.monotonic()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    try:
        device = resolve_device(args.device, "--device")
    except ValueError as exc:  # cuda:N on a machine without it: one line, exit 1
        raise BenchError(str(exc)) from None
    env = environment(device)
    if args.device.startswith("cuda") and not env["cuda_available"]:
        raise BenchError(f"--device {args.device}: torch {env['torch']} sees no CUDA GPU here; use --device cpu or auto")
    if args.device.startswith("cuda") and not env["open3d_cuda"]:
        raise BenchError(
            f"--device {args.device}: open3d {env['open3d']} has no CUDA, and fusion's TSDF runs on tracker.device; "
            "install the `gpu` extra (Open3D's CUDA wheel), or use --device auto (models on the GPU, the TSDF on the CPU)"
        )
    seq = Path(args.sequence or make_sequence(out, args.preset, args.resolution, args.frames, args.seed)).resolve()
    from shared.datasets import open_sequence

    reader = open_sequence(seq)
    first = reader.frame(0)
    size, count = [int(first.rgb.shape[1]), int(first.rgb.shape[0])], len(reader)
    configs: list[dict[str, Any]] = []
    res: dict[str, Any] = {
        "benchmark": "gpu_pipeline",
        "timestamp": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "mode": "tiny" if args.tiny else "full",
        "complete": False,
        "environment": env,
        "sequence": {"path": str(seq), "preset": args.preset if args.sequence is None else None,
                     "seed": args.seed if args.sequence is None else None, "resolution": size, "frames": count},
        "options": {"device": args.device, "configs": list(args.configs), "rate_trials": args.rate_trials,
                    "rate_frames": args.rate_frames, "start_hz": args.start_hz},
        "rule": {"pace_share": PACE_SHARE, "start_share": RATE_START_SHARE,
                 "extra_services": [s["name"] for s in EXTRA_SERVICES]},
        "random_weights": str(args.weights),
        "configs": configs,
        "wall_s": None,
    }  # fmt: skip
    for name in args.configs:
        path = config_path(name)
        if not path.is_file():
            raise BenchError(f"{path}: no such config file")
        configs.append(run_config(Path(name).stem, path, args, seq, device))
        res["wall_s"] = round(time.monotonic() - t0, 1)
        atomic_write_text(out / RESULT, json.dumps(res, indent=2))  # a long run keeps what it has
    res["complete"] = True
    return res


# ---------------------------------------------------------------------------------------------
# tables


def _ms(v: Any) -> str:
    return "-" if v is None else f"{v:.1f}"


def _mb(v: Any) -> str:
    return "-" if v is None else f"{v:,.0f} MB"


def _hz(v: Any) -> str:
    return "none" if v is None else f"{v:.3g} Hz"


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *("| " + " | ".join(r) + " |" for r in rows)]


def tables(res: dict[str, Any]) -> str:
    env, seq, cfgs = res["environment"], res["sequence"], res["configs"]
    names = [c["name"] for c in cfgs]
    w, h = seq["resolution"]
    lines = [
        f"gpu_pipeline ({res['mode']}): {env['device_name']} ({env['device']}), torch {env['torch']} (CUDA {env['torch_cuda']}), "
        f"open3d {env['open3d']} ({'CUDA' if env['open3d_cuda'] else 'CPU'}), commit {env['commit']}",
        f"sequence {Path(seq['path']).name}: {w}x{h}, {seq['frames']} frames; random weights",
        "",
        "Per-stage ms (median per call; calls in brackets):",
        "",
    ]
    rows = []
    for s in STAGES:
        cells = []
        for c in cfgs:
            st = c["stages"].get(s)
            cells.append("-" if st is None else f"{st['ms_median']:.1f} ({st['calls']})")
        rows.append([s, *cells])
    lines += _table(["stage", *names], rows)
    lines += ["", "Backends: " + "; ".join(f"{c['name']}: {c['backends']['segmenter_weights']}, {c['backends']['vl_encoder']}, "
                                           f"{c['backends']['dense_features']} at {c['backends']['dense_short_side']} px, "
                                           f"K_f {c['backends']['keyframe_interval']}, stride {c['backends']['stride']}" for c in cfgs)]  # fmt: skip
    lines += ["", "Peak memory per process (rate trials; RAM = VmHWM, GPU = nvidia-smi, torch = fusion's allocator peak):", ""]
    rows = []
    for p in PROCESSES:
        row = [p]
        for c in cfgs:
            m = c["processes"].get(p) or {}
            gpu = _mb(m.get("peak_gpu_mb")) if m.get("peak_gpu_mb") is not None else "none"
            if m.get("torch_gpu_peak_mb") is not None:
                gpu += f" (torch {_mb(m['torch_gpu_peak_mb'])})"
            row += [_mb(m.get("peak_rss_mb")), gpu]
        rows.append(row)
    lines += _table(["process", *(f"{n} {k}" for n in names for k in ("RAM", "GPU"))], rows)
    lines += ["", "Highest input rate sustained (no drop, every frame in the map, fused at 90% of the rate or more):", ""]
    rows = []
    for c in cfgs:
        r = c.get("rate")
        if not r:
            rows.append([c["name"], "not searched", "", ""])
            continue
        tried = ", ".join(f"{t['rate_hz']:.3g}{'+' if t['sustained'] else '-'}" for t in r["trials"])
        rows.append([c["name"], _hz(r["max_sustained_hz"]), tried, _hz(c["stage_run"]["hz"])])
    lines += _table(["config", "max sustained", "trials (Hz, + sustained)", "in-process (timed stages)"], rows)
    lines += ["", "Rate trials:", ""]
    rows = []
    for c in cfgs:
        for t in (c.get("rate") or {}).get("trials", []):
            d, kf = t["drops"], t.get("keyframes") or {}
            rows.append([c["name"], f"{t['rate_hz']:.3g}", str(t["published"]), str(d.get("source")), str(d.get("tracker")),
                         str(d.get("keyframe_vl")), str(d.get("fusion")), str(t.get("frames_in_map")), _hz(t.get("fused_hz")),
                         f"{kf.get('answered')}/{kf.get('requested')}", "yes" if t["sustained"] else "no", str(t.get("error") or "")])  # fmt: skip
    lines += _table(["config", "Hz", "published", "drop source", "tracker", "keyframe_vl", "fusion", "in map", "fused", "keyframes", "sustained", "error"], rows)
    lines += ["", "Time per sequence (trackgraph map, one process per run):", ""]
    rows = []
    for c in cfgs:
        for v in VOXELS:
            m = c["maps"].get(v)
            if m:
                rows.append([c["name"], v.replace("cm", " cm"), str(m["frames"]), f"{m['seconds']:.1f} s", f"{m['hz']:.3g}",
                             _mb(m["peak_rss_mb"]), _mb(m["gpu_peak_mb"]) if m["gpu_peak_mb"] is not None else "none"])  # fmt: skip
    lines += _table(["config", "voxel", "frames", "time", "Hz", "peak RAM", "GPU (torch)"], rows)
    lines.append(f"\nwall time {res['wall_s']:.0f} s")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT, e.g. 1200x680") from None
    if w < 32 or h < 32:
        raise argparse.ArgumentTypeError(f"{text!r}: at least 32x32")
    return w, h


def _device(text: str) -> str:
    import re

    from shared.devices import DEVICE_PATTERN

    if not re.match(DEVICE_PATTERN, text):
        raise argparse.ArgumentTypeError(f"{text!r}: expected auto, cpu, cuda or cuda:N")
    return text


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--stage-child"]:  # the timed map, in its own process (profile_stages)
        setup_logging(0, service="bench")
        return stage_child(*(Path(a) for a in argv[1:5]))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiny", action="store_true", help="CI / CPU: 160x120, 20 frames, small models, 1 rate trial")
    ap.add_argument("--device", type=_device, default=None, help="auto, cpu, cuda or cuda:N: torch device of the models and the TSDF (default auto; cpu with --tiny)")
    ap.add_argument("--resolution", type=_size, default=None, help="WIDTHxHEIGHT of the synthetic sequence (default 1200x680)")
    ap.add_argument("--frames", type=int, default=None, help="frames of the synthetic sequence (default 600)")
    ap.add_argument("--preset", choices=("small", "demo", "revisit"), default=None, help="synthetic scene (default demo; small with --tiny)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sequence", type=Path, help="an existing sequence folder instead of a synthetic one")
    ap.add_argument("--configs", nargs="+", default=["paper", "onboard"], help="names in deploy/configs or YAML files (default paper onboard)")
    ap.add_argument("--rate-trials", type=int, default=None, help="live trials of the rate search per config (default 4, 1 with --tiny; 0: none)")
    ap.add_argument("--rate-frames", type=int, default=None, help="frames per live trial (default the whole sequence)")
    ap.add_argument("--start-hz", type=float, default=None, help="first rate tried (default 75%% of the in-process rate)")
    ap.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS, help=f"random-weight files, written once (default {DEFAULT_WEIGHTS.relative_to(ROOT)})")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"output folder: gpu_pipeline.json, maps, logs (default {DEFAULT_OUT.relative_to(ROOT)})")
    ap.add_argument("-v", "--verbose", action="count", default=0)
    args = ap.parse_args(argv)
    setup_logging(args.verbose, service="bench")
    args.device = args.device or ("cpu" if args.tiny else "auto")
    args.resolution = args.resolution or (TINY["resolution"] if args.tiny else (1200, 680))
    args.frames = args.frames or (TINY["frames"] if args.tiny else 600)
    args.preset = args.preset or (TINY["preset"] if args.tiny else "demo")
    args.rate_trials = args.rate_trials if args.rate_trials is not None else (TINY["rate_trials"] if args.tiny else 4)
    if args.frames < 2:
        ap.error("--frames: at least 2")
    args.out = args.out.resolve()
    try:
        res = run(args)
    except BenchError as exc:
        log.error("%s", exc)
        return 1
    path = args.out / RESULT
    atomic_write_text(path, json.dumps(res, indent=2))
    print(tables(res))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
