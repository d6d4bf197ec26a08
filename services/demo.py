"""``trackgraph demo``: the whole system on the built-in synthetic scene, as a new user first
sees it.

1. the ``demo`` scene (three furnished rooms, 900 RGB-D frames with ground truth), unless
   it is there already;
2. the distributed pipeline of ``deploy/demo.yaml``: a Zenoh router on loopback and every
   service as its own process (keyframe_vl, tracker, fusion, query, viewer, source), with
   real models when their weights are present (``deploy/configs/paper.yaml``) and simulated
   perception with classical features otherwise;
3. example text queries and one image query through the live query service;
4. the map scored against the ground truth, PNG renders with the hits, a Rerun recording of
   the final map with the hits (the viewer service also records the run live), and
   ``report.md`` with the queries, hits, timings and resources.
"""

from __future__ import annotations

import json
import logging
import platform
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = "demo"
"""The launch file (shared/presets.py): ``deploy/demo.yaml``, installed with the package."""
TEXT_QUERIES = 6


def choose_config(config: Path | None) -> tuple[Path, str]:
    """The given config, else the paper's models if their weights load, else simulated."""
    if config is not None:
        return Path(config), "given with --config"
    from services.models.check import check_models
    from shared.config import load_config
    from shared.presets import config_path

    paper, synthetic = config_path("paper"), config_path("synthetic")
    check = check_models(load_config(paper), load=False)
    if check["ok"]:
        return paper, "the paper's models (FastSAM-x, OpenCLIP ViT-H-14, DINOv3 ViT-S+): their weights are present"
    missing = ", ".join(Path(m).name for m in check["missing"]) or "weights"
    return synthetic, f"simulated segmenter and CLIP, classical dense features: no model weights here ({missing} missing)"


def pick_queries(seq: Path, n: int = TEXT_QUERIES) -> list[str]:
    """Names of the scene's largest objects (one per name, structure left out)."""
    from shared.eval.gt import EXCLUDED_LABELS, load_gt

    gt = load_gt(seq / "gt")
    sizes: dict[str, float] = {}
    for oid in gt.evaluated_object_ids(EXCLUDED_LABELS):
        labels = gt.objects[int(oid)]
        pts = gt.points[gt.labels == oid]
        name = labels.name()
        if name and len(pts):
            sizes[name] = max(sizes.get(name, 0.0), float((pts.max(0) - pts.min(0)).max()))
    return [name for name, _ in sorted(sizes.items(), key=lambda kv: (-kv[1], kv[0]))][:n]


def image_query(seq: Path, out_png: Path) -> tuple[np.ndarray, str]:
    """A crop around the largest furniture object of a frame mid-sequence, and that object's
    name. The query sends only the crop's pixels: the simulated encoder finds the crop in the
    sequence and reads its ground truth there."""
    from PIL import Image

    from shared.datasets import open_sequence
    from shared.eval.gt import EXCLUDED_LABELS, load_gt

    gt = load_gt(seq / "gt")
    keep = {int(o) for o in gt.evaluated_object_ids(EXCLUDED_LABELS)}
    reader = open_sequence(seq, "replica")
    i = len(reader) // 3
    rgb_full, inst = reader.rgb(i), reader.instances(i)
    if inst is None:
        raise ValueError(f"{seq}: frame {i} has no ground-truth instances (instances/ folder)")
    ids, counts = np.unique(inst[np.isin(inst, list(keep))], return_counts=True)
    oid = int(ids[counts.argmax()])
    ys, xs = np.nonzero(inst == oid)
    pad = 12
    y0, y1 = max(int(ys.min()) - pad, 0), min(int(ys.max()) + pad + 1, inst.shape[0])
    x0, x1 = max(int(xs.min()) - pad, 0), min(int(xs.max()) + pad + 1, inst.shape[1])
    rgb = np.ascontiguousarray(rgb_full[y0:y1, x0:x1])
    out_png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(out_png)
    return rgb, gt.objects[oid].name() or f"object {oid}"


def _git_commit() -> str:
    if not (ROOT / ".git").exists():  # an installed package, not a checkout
        from importlib.metadata import PackageNotFoundError, version

        try:
            return f"trackgraph {version('trackgraph')}"
        except PackageNotFoundError:
            return "unknown"
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def run_demo(out: Path, *, preset: str = "demo", seed: int = 0, config: Path | str | None = None, launch_file: Path | str = LAUNCH, sets: list[str] | None = None) -> dict[str, Any]:
    """Everything above; returns the report's figures and writes ``out/report.md``."""
    from services.launch import LaunchError, Supervisor, plan_launch
    from services.query.client import QueryClient
    from shared.synth import run_synth

    out = Path(out)
    seq, map_dir = out / "sequence", out / "map"
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    if not (seq / "traj.txt").is_file():
        run_synth(preset, seed, seq, overwrite=True)
    timings["scene_s"] = time.perf_counter() - t0
    cfg_path, why = choose_config(config)
    log.info("perception: %s", why)

    plan = plan_launch(launch_file, sequence=seq, out=map_dir, log_dir=out / "logs", config=cfg_path, sets=sets or [])
    plan.launch = plan.launch.model_copy(update={"exit_when_finished": False})
    sup = Supervisor(plan, status=True)
    runner = threading.Thread(target=sup.run, name="demo:launch", daemon=True)
    t1 = time.perf_counter()
    runner.start()
    queries: list[dict[str, Any]] = []
    try:
        while not all(sup.procs[n].state == "finished" for n in ("source", "fusion")):
            if sup.error is not None or not runner.is_alive():
                raise LaunchError(sup.error or "the launch stopped before the map was finished")
            time.sleep(0.5)
        timings["distributed_map_s"] = time.perf_counter() - t1
        texts = pick_queries(seq)
        crop, crop_name = image_query(seq, out / "queries" / "image_query.png")
        with QueryClient(plan.system.transport, robot_id=plan.system.robot_id, timeout_s=30) as client:
            for text in texts:
                q0 = time.perf_counter()
                hits = client.query(text, top_k=3)
                queries.append({"query": text, "kind": "text", "ms": 1e3 * (time.perf_counter() - q0), "hits": hits})
            q0 = time.perf_counter()
            hits = client.query(image=crop, top_k=3)
            queries.append({"query": f"image of a {crop_name}", "kind": "image", "ms": 1e3 * (time.perf_counter() - q0), "hits": hits, "image": "queries/image_query.png"})
    finally:
        sup.stop_event.set()
        runner.join(timeout=180)
    summary = sup.summary()
    timings["total_s"] = time.perf_counter() - t0
    return _finish(out, seq, map_dir, plan, cfg_path, why, queries, summary, timings)


def _finish(out: Path, seq: Path, map_dir: Path, plan, cfg_path: Path, why: str, queries: list[dict], summary: dict, timings: dict) -> dict[str, Any]:
    from services.query.evaluate import MapTruth, eval_queries
    from services.viewer.recording import write_map_recording
    from services.viewer.render import render_map_pictures
    from shared.eval import eval_instances, eval_openlex3d
    from shared.graph.store import MapStore

    truth = MapTruth(map_dir, seq)
    for q in queries:
        q["labels"] = [truth.best_object(h.segment) for h in q["hits"]]
    state = MapStore(map_dir / "graph").load()
    traj = np.asarray(state.extra.get("trajectory", np.zeros((0, 3))))
    hits_by_text = {q["query"]: q["hits"] for q in queries}
    pictures = out / "pictures"
    render_map_pictures(state.snapshot, pictures, hits_by_text, trajectory=traj)
    for i, q in enumerate(queries):
        q["png"] = f"pictures/query_{i}.png"
    write_map_recording(map_dir, out / "map.rrd", queries=hits_by_text)

    metrics = {
        "instances": eval_instances(map_dir, seq),
        "openlex3d": eval_openlex3d(map_dir, seq),
        "queries": eval_queries(map_dir, seq, min_size_m=0.2),
    }
    run = json.loads((map_dir / "run.json").read_text()) if (map_dir / "run.json").is_file() else {}
    result = {
        "config": str(cfg_path),
        "perception": why,
        "backends": run.get("backends"),
        "frames": run.get("frames"),
        "mapping_hz": run.get("hz"),
        "segments": run.get("segments"),
        "timings": {k: round(v, 1) for k, v in timings.items()},
        "services": summary["services"],
        "queries": [
            {"query": q["query"], "kind": q["kind"], "ms": round(q["ms"], 1),
             "hits": [{"segment": h.segment, "score": round(h.score, 3), "object": lab[1], "iou": round(lab[2], 2)} for h, lab in zip(q["hits"], q["labels"], strict=True)]}
            for q in queries
        ],  # fmt: skip
        "metrics": {
            "ap50": metrics["instances"]["ap50"],
            "ap25": metrics["instances"]["ap25"],
            "segments_per_object": metrics["instances"]["segments_per_object"],
            "synonyms": metrics["openlex3d"]["synonyms"],
            "retrieval_ap50": metrics["openlex3d"]["ap50"],
            "top1_synonym_queries_over_20cm": metrics["queries"]["top1_hit_rate"],
            "n_synonym_queries_over_20cm": metrics["queries"]["n_queries"],
        },
        "commit": _git_commit(),
        "machine": f"{platform.machine()}, {platform.processor() or platform.platform()}, Python {platform.python_version()}",
        "files": {
            "report": str(out / "report.md"),
            "map": str(map_dir),
            "pictures": str(pictures),
            "recording": str(out / "map.rrd"),
            "live_recording": str(map_dir / "live.rrd"),
            "logs": str(out / "logs"),
        },
    }
    from shared.io import atomic_write_text

    atomic_write_text(out / "report.json", json.dumps(result, indent=2))
    atomic_write_text(out / "report.md", report_markdown(result, queries))
    return result


def report_markdown(r: dict[str, Any], queries: list[dict]) -> str:
    m = r["metrics"]
    lines = [
        "# TrackGraph demo",
        "",
        f"Commit `{r['commit']}` on {r['machine']}.",
        "",
        f"**Perception:** {r['perception']} (`{Path(r['config']).name}`; backends {r['backends']}).",
        "Simulated perception measures the mapping, not FastSAM or CLIP themselves.",
        "",
        "## The run",
        "",
        "| | |",
        "|---|---|",
        f"| scene | {r['frames']} frames (`{Path(r['files']['map']).parent / 'sequence'}`) |",
        f"| scene generation | {r['timings'].get('scene_s', 0):.0f} s |",
        f"| distributed mapping, one process per service | {r['timings'].get('distributed_map_s', 0):.0f} s ({r['mapping_hz'] or 0:.2f} Hz fused) |",
        f"| segments | {r['segments']} |",
        f"| total | {r['timings'].get('total_s', 0):.0f} s |",
        "",
        "| service | final state | restarts | peak RSS |",
        "|---|---|---|---|",
    ]
    for name, s in r["services"].items():
        lines.append(f"| {name} | {s['state']} | {s['restarts']} | {s.get('peak_rss_mb', 0):.0f} MB |")
    lines += [
        "",
        "## Queries (through the live query service)",
        "",
        "| query | latency | #1 | #2 | #3 |",
        "|---|---|---|---|---|",
    ]
    for q in r["queries"]:
        cells = [f"seg {h['segment']} ({h['score']:.2f}): **{h['object']}** IoU {h['iou']:.2f}" for h in q["hits"]]
        cells += [""] * (3 - len(cells))
        lines.append(f"| {q['query']} | {q['ms']:.0f} ms | " + " | ".join(cells) + " |")
    lines += ["", "![all queries](pictures/queries.png)", ""]
    for q in queries:
        extra = f" (the query image: ![query]({q['image']}))" if q.get("image") else ""
        lines.append(f"- [{q['query']}]({q['png']}){extra}")
    lines += [
        "",
        "## Map quality against the ground truth",
        "",
        "| metric | value |",
        "|---|---|",
        f"| class-agnostic instance AP50 / AP25 | {m['ap50']:.3f} / {m['ap25']:.3f} |",
        f"| segments per matched object | {m['segments_per_object']:.3f} |",
        f"| OpenLex3D top-5 synonyms | {m['synonyms']:.3f} |",
        f"| OpenLex3D retrieval AP50 | {m['retrieval_ap50']:.3f} |",
        f"| top-1 hit (IoU >= 0.25) of synonym queries for objects over 20 cm | {m['top1_synonym_queries_over_20cm']:.3f} ({m['n_synonym_queries_over_20cm']} queries) |",
        "",
        "## Files",
        "",
        "![map](pictures/map.png)",
        "",
        f"- the map: `{r['files']['map']}` (graph snapshots, `mesh.ply`, OpenLex3D export, `run.json`)",
        f"- Rerun recordings: `{r['files']['recording']}` (final map and hits), `{r['files']['live_recording']}` (the run, live); open with `rerun FILE`",
        f"- one log per process: `{r['files']['logs']}`",
        "",
    ]
    return "\n".join(lines)
