"""Benchmark: TSDF integration with source-track hypotheses against plain Open3D TSDF.

Run from the repository root::

    python benchmarks/fusion.py --quick     # 60 frames per voxel size
    python benchmarks/fusion.py             # 240 frames per voxel size
    python benchmarks/fusion.py --source analytic --frames 100 -v

Frames: the ``demo`` preset of ``trackgraph synth`` (three furnished rooms, 640x480, the whole
walk resampled to N frames; generated once into ``benchmarks/out/fusion_synth_demo_N`` and
reused), read back through ``shared.datasets.open_sequence``, with the ground-truth instance
map standing in for the tracker's source tracks. If the synthetic generator is unavailable,
``--source analytic`` (also the fallback) ray-casts a furnished box room at 640x480.

For each voxel size (3 cm and 5 cm) the same frames go, one by one, into two volumes in this
one process, alternating which goes first:

* **plain**: Open3D's VoxelBlockGrid (tsdf, weight, color) with the same input conversions
  (depth range filter, float colour), ``compute_unique_block_coordinates`` + ``integrate``;
* **hypotheses**: :class:`services.fusion.volume.tsdf.HypothesisTSDF` (K = 4 track slots per
  voxel), ``update_window`` + ``integrate`` with per-track confidences from eq. 6 (a keyframe
  every 24 frames, propagated masks in between).

Reported per voxel size: median ms per frame and frames/s of each, the ratio hypotheses /
plain (target at 3 cm: at most 2), the hypothesis share of the time, marching cubes time,
blocks, the volumes' memory (Open3D preallocates: capacity x bytes per block) and the
process's peak RSS, and an extrapolation of the volume memory to a Replica room. The first
frame of each volume is untimed (numba compilation or cache load, first allocations). The
process's peak RSS includes the decoded frames and libraries; the volume memory is the part
that grows with the map. Then fusion's write-ahead journal (``services.fusion.durability.journal``):
ms and bytes per tracked-frame record on the first 60 frames, at their resolution and scaled
to Replica's 1200x680. Results go to ``benchmarks/out/fusion.json`` and tables on stdout.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from services.fusion.volume.hypotheses import confidence  # noqa: E402
from services.fusion.volume.tsdf import HypothesisTSDF  # noqa: E402
from shared.config.fusion import TSDFConfig  # noqa: E402
from shared.geometry import Intrinsics, invert  # noqa: E402
from shared.logs import setup_logging  # noqa: E402
from shared.o3d import import_open3d  # noqa: E402

log = logging.getLogger("bench.fusion")

DEFAULT_OUT = ROOT / "benchmarks" / "out" / "fusion.json"
VOXEL_SIZES = (0.03, 0.05)
KEYFRAME_EVERY = 24
RATIO_TARGET = 2.0
REPLICA_ROOM_SURFACE_M2 = 160.0
"""Assumed surface of a Replica room (room0-like: a 6.5 x 4.5 x 2.7 m shell, about 117 m^2,
plus about 45 m^2 of furniture), for the memory extrapolation."""
WIDTH, HEIGHT = 640, 480

Frame = tuple[
    Annotated[np.ndarray, "(H, W) float32 metres"],
    Annotated[np.ndarray, "(H, W, 3) uint8"],
    Annotated[np.ndarray, "(H, W) int32 track ids, -1 = none"],
    Intrinsics,
    Annotated[np.ndarray, "(4, 4) camera-to-world"],
]


# ---------------------------------------------------------------------------------------------
# frames


def synth_frames(n: int) -> tuple[Any, str]:
    """The demo preset walk in ``n`` frames, generated once and cached under benchmarks/out."""
    from shared.datasets import open_sequence
    from shared.synth import run_synth

    folder = ROOT / "benchmarks" / "out" / f"fusion_synth_demo_{n}"
    if not (folder / "traj.txt").is_file():
        log.info("generating the synth demo walk in %d frames into %s", n, folder)
        run_synth("demo", 0, folder, overrides={"camera": {"frames": n}}, overwrite=True)
    reader = open_sequence(folder, "replica")
    if len(reader) < n:
        raise RuntimeError(f"{folder} holds {len(reader)} frames, expected {n}")

    def frames() -> Iterator[Frame]:
        for i in range(n):
            f, instances = reader.frame(i), reader.instances(i)
            depth = f.depth.astype(np.float32) / np.float32(f.depth_scale)
            tracks = instances if instances is not None else np.full(depth.shape, -1, np.int32)
            yield depth, f.rgb, tracks.astype(np.int32), f.intrinsics, f.T_world_cam

    return frames, f"synth demo preset (seed 0), {n} frames, {folder.name}"


def _boxes(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """A 6 x 5 x 2.7 m room (walls, floor, ceiling; y down) with 14 boxes of furniture."""
    t = 0.1
    shell = [
        ((-3 - t, -2.7, -2.5), (-3, 0, 2.5)), ((3, -2.7, -2.5), (3 + t, 0, 2.5)),
        ((-3, -2.7, -2.5 - t), (3, 0, -2.5)), ((-3, -2.7, 2.5), (3, 0, 2.5 + t)),
        ((-3, 0, -2.5), (3, t, 2.5)), ((-3, -2.7 - t, -2.5), (3, -2.7, 2.5)),
    ]  # fmt: skip
    out = [(np.array(lo, float), np.array(hi, float), i) for i, (lo, hi) in enumerate(shell)]
    for i in range(14):
        size = rng.uniform([0.3, 0.3, 0.3], [1.2, 1.4, 1.0])
        side = rng.integers(4)
        along = rng.uniform(-2.2, 2.2)
        c = {0: (-3 + size[0] / 2, along), 1: (3 - size[0] / 2, along),
             2: (along, -2.5 + size[2] / 2), 3: (along, 2.5 - size[2] / 2)}[int(side)]  # fmt: skip
        lo = np.array([c[0] - size[0] / 2, -size[1], c[1] - size[2] / 2])
        out.append((lo, lo + size, len(shell) + i))
    return out


def analytic_frames(n: int) -> tuple[Any, str]:
    """Ray-cast box room, camera circling at 1.5 m height looking around and outwards."""
    rng = np.random.default_rng(0)
    boxes = _boxes(rng)
    colours = rng.integers(40, 230, (len(boxes), 3), dtype=np.uint8)
    K = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=WIDTH, height=HEIGHT)
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], -1).reshape(-1, 3)

    def frames() -> Iterator[Frame]:
        for i in range(n):
            a = 2 * np.pi * i / max(n, 1)
            eye = np.array([1.2 * np.cos(a), -1.5, 1.0 * np.sin(a)])
            yaw = a + np.pi / 2 + 0.6 * np.sin(3 * a)
            z = np.array([np.cos(yaw), 0.25, np.sin(yaw)])
            z /= np.linalg.norm(z)
            x = np.cross(z, [0.0, -1.0, 0.0])
            x /= np.linalg.norm(x)
            T = np.eye(4)
            T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
            d = d_cam @ T[:3, :3].T
            best = np.full(len(d), np.inf)
            ids = np.full(len(d), -1, np.int32)
            with np.errstate(divide="ignore", invalid="ignore"):
                for lo, hi, oid in boxes:
                    t1, t2 = (lo - eye) / d, (hi - eye) / d
                    tn = np.nanmax(np.minimum(t1, t2), 1)
                    hit = (tn <= np.nanmin(np.maximum(t1, t2), 1)) & (tn > 0) & (tn < best)
                    best[hit], ids[hit] = tn[hit], oid
            depth = np.where(np.isfinite(best), best, 0).astype(np.float32).reshape(HEIGHT, WIDTH)
            ids = ids.reshape(HEIGHT, WIDTH)
            yield depth, colours[np.maximum(ids, 0)], ids, K, T

    return frames, f"analytic box room (6 x 5 x 2.7 m, 14 boxes), {n} frames"


# ---------------------------------------------------------------------------------------------
# volumes


class PlainTSDF:
    """Open3D's own TSDF with the same input handling as HypothesisTSDF, minus the hypotheses."""

    def __init__(self, cfg: TSDFConfig) -> None:
        self.o3d = import_open3d()
        o3c = self.o3d.core
        self.cfg = cfg
        self.vbg = self.o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=cfg.voxel_size,
            block_resolution=cfg.block_resolution,
            block_count=cfg.initial_blocks,
            device=o3c.Device("CPU:0"),
        )

    def integrate(self, depth_m: np.ndarray, rgb: np.ndarray, K: Intrinsics, T: np.ndarray) -> None:
        o3d, o3c, cfg = self.o3d, self.o3d.core, self.cfg
        depth = np.where(
            (depth_m >= cfg.depth_min) & (depth_m <= cfg.depth_max), depth_m, np.float32(0)
        )
        dimg = o3d.t.geometry.Image(o3c.Tensor.from_numpy(depth))
        cimg = o3d.t.geometry.Image(
            o3c.Tensor.from_numpy(rgb.astype(np.float32) * np.float32(1 / 255))
        )
        intr = o3c.Tensor(K.matrix(), o3c.float64)
        extr = o3c.Tensor(invert(T), o3c.float64)
        trunc = float(cfg.trunc_voxels)
        bc = self.vbg.compute_unique_block_coordinates(dimg, intr, extr, 1.0, cfg.depth_max, trunc)
        self.vbg.integrate(bc, dimg, cimg, intr, extr, 1.0, cfg.depth_max, trunc)

    def nbytes(self) -> int:
        return int(self.vbg.hashmap().capacity()) * self.cfg.block_resolution**3 * 20


def gammas(i: int, tracks: np.ndarray) -> dict[int, float]:
    """Eq. 6 for every track in the frame, keyframes every KEYFRAME_EVERY frames."""
    ids = np.unique(tracks)
    k = i % KEYFRAME_EVERY
    g = confidence(k == 0, k, 0.25, 0.1)
    return {int(t): g for t in ids if t >= 0}


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (vertices[faces[:, j]].astype(np.float64) for j in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _time_plain(plain: PlainTSDF, depth, rgb, K, T) -> float:
    t0 = time.perf_counter()
    plain.integrate(depth, rgb, K, T)
    return time.perf_counter() - t0


def _time_hyp(hyp: HypothesisTSDF, depth, rgb, K, T, tracks, gamma) -> tuple[float, float, Any]:
    """(window + integrate seconds, window seconds, stats)."""
    t0 = time.perf_counter()
    hyp.update_window(T[:3, 3])
    t1 = time.perf_counter()
    st = hyp.integrate(depth, rgb, K, T, tracks, gamma)
    return time.perf_counter() - t0, t1 - t0, st


def run_voxel(voxel: float, frames: Any, backend: str) -> dict:
    cfg = TSDFConfig(voxel_size=voxel, vote_backend=backend)
    plain = PlainTSDF(cfg)
    hyp = HypothesisTSDF(cfg, device="cpu")
    t_plain, t_hyp, t_part, t_window, t_tsdf = [], [], [], [], []
    replaced = 0
    for i, (depth, rgb, tracks, K, T) in enumerate(frames()):
        gamma = gammas(i, tracks)

        # alternate the order so neither volume always runs on a warmer cache
        if i % 2:
            tp = _time_plain(plain, depth, rgb, K, T)
            th, tw, st = _time_hyp(hyp, depth, rgb, K, T, tracks, gamma)
        else:
            th, tw, st = _time_hyp(hyp, depth, rgb, K, T, tracks, gamma)
            tp = _time_plain(plain, depth, rgb, K, T)
        replaced += st.replaced
        if i == 0:
            continue
        t_plain.append(tp)
        t_hyp.append(th)
        t_part.append(st.seconds_hypotheses)
        t_tsdf.append(st.seconds_tsdf)
        t_window.append(tw)
        if i % 20 == 0:
            log.debug(
                "%.0f cm frame %d: plain %.1f ms, hypotheses %.1f ms",
                voxel * 100,
                i,
                tp * 1e3,
                th * 1e3,
            )

    t0 = time.perf_counter()
    plain.vbg.extract_triangle_mesh(weight_threshold=hyp.mesh_weight_threshold)
    mesh_plain = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh = hyp.extract_mesh()
    mesh_hyp = time.perf_counter() - t0

    med_p, med_h = statistics.median(t_plain), statistics.median(t_hyp)
    area = mesh_area(mesh.vertices, mesh.faces)
    hyp_bytes = hyp.nbytes()
    per_block_hyp = hyp_bytes["grid"] / max(int(hyp.vbg.hashmap().capacity()), 1)
    blocks_per_m2 = hyp.active_blocks / area if area > 0 else float("nan")
    room_blocks = blocks_per_m2 * REPLICA_ROOM_SURFACE_M2
    return {
        "voxel_m": voxel,
        "frames_timed": len(t_plain),
        "plain_ms_median": med_p * 1e3,
        "hyp_ms_median": med_h * 1e3,
        "plain_fps": 1.0 / med_p,
        "hyp_fps": 1.0 / med_h,
        "ratio_median": med_h / med_p,
        "ratio_total": sum(t_hyp) / sum(t_plain),
        "hyp_part_ms_median": statistics.median(t_part) * 1e3,
        "hyp_tsdf_ms_median": statistics.median(t_tsdf) * 1e3,
        "window_ms_median": statistics.median(t_window) * 1e3,
        "plain_ms_p90": float(np.percentile(t_plain, 90) * 1e3),
        "hyp_ms_p90": float(np.percentile(t_hyp, 90) * 1e3),
        "mesh_plain_ms": mesh_plain * 1e3,
        "mesh_hyp_ms": mesh_hyp * 1e3,
        "mesh_vertices": len(mesh),
        "mesh_area_m2": area,
        "winner_vertices": int((mesh.winners() >= 0).sum()),
        "replaced_hypotheses": replaced,
        "active_blocks": hyp.active_blocks,
        "archived_blocks": hyp.archived_blocks,
        "plain_volume_mb": plain.nbytes() / 2**20,
        "hyp_volume_mb": hyp_bytes["grid"] / 2**20,
        "hyp_archive_mb": hyp_bytes["archive"] / 2**20,
        "blocks_per_m2": blocks_per_m2,
        "replica_room_blocks": room_blocks,
        "replica_room_plain_mb": room_blocks
        * plain.nbytes()
        / max(int(plain.vbg.hashmap().capacity()), 1)
        / 2**20,
        "replica_room_hyp_mb": room_blocks * per_block_hyp / 2**20,
        "peak_rss_mb_so_far": rss_mb(),
    }


def run_journal(frames: Any, limit: int = 60) -> dict:
    """fusion's write-ahead journal on these frames (services.fusion.durability.journal, the default
    config: zstd level 1, fsync at most once a second): ms and bytes per TrackedFrame record,
    at the frames' resolution and scaled to Replica's 1200x680 (nearest neighbour)."""
    import tempfile

    from services.fusion.durability.journal import Journal
    from shared.config.fusion import JournalConfig
    from shared.messages.frames import Frame, TrackedFrame

    def record(depth, rgb, tracks, K, T, i, scale=None):
        d = np.clip(depth * 1000.0, 0, 65535).astype(np.uint16)
        if scale is not None:
            h, w = scale
            ys = (np.arange(h) * d.shape[0] // h)[:, None]
            xs = (np.arange(w) * d.shape[1] // w)[None, :]
            d, rgb, tracks = d[ys, xs], rgb[ys, xs], tracks[ys, xs]
            K = K.model_copy(update={"fx": K.fx * w / K.width, "fy": K.fy * h / K.height, "cx": K.cx * w / K.width,
                                     "cy": K.cy * h / K.height, "width": w, "height": h})  # fmt: skip
        fr = Frame(frame_index=i, rgb=np.ascontiguousarray(rgb), depth=np.ascontiguousarray(d), depth_scale=1000.0, intrinsics=K, T_world_cam=T)
        conf = np.full(tracks.shape, 200, np.uint8)
        return TrackedFrame(frame=fr, track_ids=np.ascontiguousarray(tracks), tracks=[], confidence=conf)

    out = {}
    for label, scale in (("native", None), ("replica_1200x680", (680, 1200))):
        with tempfile.TemporaryDirectory() as tmp:
            j = Journal(Path(tmp) / "journal", JournalConfig())
            j.reset()
            ms, sizes, raw = [], [], 0
            for i, (depth, rgb, tracks, K, T) in enumerate(frames()):
                if i >= limit:
                    break
                tf = record(depth, rgb, tracks, K, T, i, scale)
                t0 = time.perf_counter()
                n = j.append("frame", tf)
                ms.append((time.perf_counter() - t0) * 1e3)
                sizes.append(n)
                raw = tf.frame.rgb.nbytes + tf.frame.depth.nbytes + tf.track_ids.nbytes + tf.confidence.nbytes
            j.close()
            out[label] = {
                "resolution": list(tf.frame.depth.shape[::-1]), "records": len(ms),
                "ms_median": statistics.median(ms), "ms_p90": float(np.percentile(ms, 90)),
                "bytes_median": int(statistics.median(sizes)), "raw_bytes": raw, "ratio": raw / statistics.median(sizes),
            }  # fmt: skip
    return out


def machine_info() -> dict:
    try:
        import numba

        numba_version = numba.__version__
    except ImportError:
        numba_version = None
    o3d = import_open3d()
    return {
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "loadavg": os.getloadavg(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "open3d": o3d.__version__,
        "numba": numba_version,
    }


def print_table(rows: list[dict], source: str) -> None:
    print(f"\nTSDF integration, 640x480, {source}")
    print(
        "| voxel | plain ms (fps) | hypotheses ms (fps) | ratio | vote ms | mesh ms plain / hyp "
        "| blocks | volume MB plain / hyp | Replica room MB plain / hyp |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['voxel_m'] * 100:.0f} cm | {r['plain_ms_median']:.1f} ({r['plain_fps']:.0f}) "
            f"| {r['hyp_ms_median']:.1f} ({r['hyp_fps']:.0f}) | {r['ratio_median']:.2f} "
            f"| {r['hyp_part_ms_median']:.1f} | {r['mesh_plain_ms']:.0f} / {r['mesh_hyp_ms']:.0f} "
            f"| {r['active_blocks']} | {r['plain_volume_mb']:.0f} / {r['hyp_volume_mb']:.0f} "
            f"| {r['replica_room_plain_mb']:.0f} / {r['replica_room_hyp_mb']:.0f} |"
        )
    three = [r for r in rows if abs(r["voxel_m"] - 0.03) < 1e-9]
    if three:
        ok = three[0]["ratio_median"] <= RATIO_TARGET
        print(f"target (3 cm: hypotheses <= {RATIO_TARGET:.0f}x plain): {'pass' if ok else 'FAIL'}")
    print(f"peak RSS of this process: {rss_mb():.0f} MB")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="60 frames per voxel size (default 240)")
    ap.add_argument("--frames", type=int, help="frames per voxel size")
    ap.add_argument("--source", choices=("synth", "analytic"), default="synth")
    ap.add_argument("--backend", choices=("auto", "numba", "torch"), default="auto")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON results")
    ap.add_argument("-v", "--verbose", action="count", default=0)
    args = ap.parse_args(argv)
    setup_logging(args.verbose, service="bench")
    n = args.frames or (60 if args.quick else 240)
    if n < 3:
        ap.error("need at least 3 frames")

    frames, source = None, ""
    if args.source == "synth":
        try:
            frames, source = synth_frames(n)
        except Exception as exc:  # noqa: BLE001 - the analytic room is a complete stand-in
            log.warning(
                "synthetic frames unavailable (%s: %s); using the analytic room",
                type(exc).__name__,
                exc,
            )
    if frames is None:
        frames, source = analytic_frames(n)

    started = time.monotonic()
    rows = []
    for voxel in VOXEL_SIZES:
        log.info("voxel %.0f cm: %d frames", voxel * 100, n)
        rows.append(run_voxel(voxel, frames, args.backend))
    log.info("journal: %d frames", min(n, 60))
    journal = run_journal(frames)
    result = {
        "benchmark": "fusion",
        "timestamp": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "source": source,
        "resolution": [WIDTH, HEIGHT],
        "hypotheses_k": TSDFConfig().hypotheses,
        "backend": args.backend,
        "ratio_target_3cm": RATIO_TARGET,
        "replica_room_surface_m2_assumed": REPLICA_ROOM_SURFACE_M2,
        "rows": rows,
        "journal": journal,
        "peak_rss_mb": rss_mb(),
        "wall_s": time.monotonic() - started,
        "machine": machine_info(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print_table(rows, source)
    print("\nwrite-ahead journal, per TrackedFrame record (zstd 1, fsync <= 1/s):")
    print(f"{'resolution':>12} {'ms median':>10} {'ms p90':>8} {'KB':>8} {'raw KB':>8} {'ratio':>6}")
    for row in journal.values():
        w, h = row["resolution"]
        print(f"{w:>7}x{h:<4} {row['ms_median']:>10.2f} {row['ms_p90']:>8.2f} {row['bytes_median'] / 1e3:>8.0f} {row['raw_bytes'] / 1e3:>8.0f} {row['ratio']:>6.2f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
