"""Benchmark: concurrent clients against a live query service over loopback Zenoh.

Run from the repository root::

    python benchmarks/query.py --quick     # 8 clients x 20 queries
    python benchmarks/query.py             # 8 clients x 100 queries (the issue's load)

What runs, each an OS process on one machine, all on ``tcp/127.0.0.1`` (free port, scouting
off):

* a Zenoh router (``trackgraph router``);
* the query service (``trackgraph serve query``), unchanged: it joins late, asks
  ``graph/snapshot``, and embeds every query through ``vl/embed``;
* this process as fusion and keyframe_vl: it serves ``graph/snapshot`` with a graph of
  ``--segments`` segments (500), each with a CLIP gallery of 1-8 rows of ``--dim`` (1024)
  features, publishes a few live deltas while the clients run, and answers ``vl/embed`` with
  a fixed random 1024-d vector per text (an encoder that costs nothing, so the figures are
  the service's);
* ``--clients`` clients (8), each with its own session, sending ``--queries`` (100) text
  queries one after another, each of one of 40 phrases with top_k 10, a third of them with a
  radius filter. Each client is its own process by default; ``--clients-in threads`` runs
  them as threads of one process. Real clients sit on other machines and cost the service's
  cores nothing; here 8 client processes take more CPU than the service itself (their Zenoh
  runtimes and decoding, on the same 2 cores), and one process takes the least.

Latency is measured in the client from the request to the decoded reply. Reported: p50, p99,
max and mean over all queries, errors (there must be none), and queries/s overall. Target:
p99 under 50 ms. JSON goes to benchmarks/out/query.json and a table to stdout.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import multiprocessing as mp
import os
import platform
import queue
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from shared.config import TrackGraphConfig  # noqa: E402
from shared.config.base import save_resolved  # noqa: E402
from shared.graph.scene import GraphReplica  # noqa: E402
from shared.messages.graph import GraphDelta, GraphSnapshot, SegmentNode, SnapshotRequest  # noqa: E402
from shared.messages.rpc import EmbedReply, EmbedRequest  # noqa: E402
from shared.topics import Topics  # noqa: E402
from shared.transport import TypedPublisher, TypedQueryable, open_session  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "out" / "query.json"
TARGET_P99_MS = 50.0
PHRASES = [f"object number {i}" for i in range(40)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def text_vector(text: str, dim: int) -> np.ndarray:
    v = np.random.default_rng(zlib.crc32(text.encode())).standard_normal(dim).astype(np.float32)
    return v / np.linalg.norm(v)


def make_graph(n: int, dim: int, seed: int = 0) -> GraphReplica:
    rng = np.random.default_rng(seed)
    g = GraphReplica()
    segs = []
    track = 0
    for i in range(n):
        rows = int(rng.integers(1, 9))
        gal = rng.standard_normal((rows, dim)).astype(np.float32)
        c = rng.uniform(-10, 10, 3)
        tracks = list(range(track, track + rows))
        track += rows
        segs.append(SegmentNode(
            id=i, centroid=c, bbox_min=c - 0.3, bbox_max=c + 0.3, tracks=tracks, dino=np.ones(8, np.float32),
            gallery=gal / np.linalg.norm(gal, axis=1, keepdims=True), gallery_tracks=tracks, active=True,
        ))  # fmt: skip
    g.apply_snapshot(GraphSnapshot(graph_seq=1, frame_index=0, segments=segs))
    return g


def client_main(endpoint: str, robot: str, n: int, seed: int, go, q) -> None:
    """One client: opens its session, reports ready, waits for ``go`` (set once every client
    is ready, so all of them ask at once), then asks ``n`` queries and reports latencies."""
    from services.query.client import QueryClient, QueryRefused
    from shared.config import TransportConfig
    from shared.transport import TransportError

    transport = TransportConfig(mode="client", connect=[endpoint], shared_memory=False, query_timeout_s=10.0)
    rng = np.random.default_rng(seed)
    lat, errors = [], []
    with QueryClient(transport, robot_id=robot, timeout_s=10.0) as client:
        q.put("ready")
        go.wait(120)
        for k in range(n):
            text = PHRASES[int(rng.integers(len(PHRASES)))]
            near = k % 3 == 0
            t0 = time.perf_counter()
            try:
                client.query(text, top_k=10, center=np.zeros(3) if near else None, radius=8.0 if near else None)
                lat.append(1e3 * (time.perf_counter() - t0))
            except (QueryRefused, TransportError) as exc:
                errors.append(str(exc))
    q.put({"latencies_ms": lat, "errors": errors})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20 queries per client")
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--queries", type=int, default=None, help="per client (default 100, 20 with --quick)")
    ap.add_argument("--segments", type=int, default=500)
    ap.add_argument("--dim", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=4, help="query service threads")
    ap.add_argument("--clients-in", choices=("processes", "threads"), default="processes",
                    help="each client its own process (default), or all as threads of one process: "
                    "clients on other machines cost the service's cores nothing, one process costs them least here")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args()
    n_queries = args.queries or (20 if args.quick else 100)

    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = TrackGraphConfig.model_validate({
        "transport": {"mode": "client", "connect": [endpoint], "shared_memory": False, "query_timeout_s": 5.0},
        "query": {"workers": args.workers, "max_top_k": 100},
    })  # fmt: skip
    tmp = Path(tempfile.mkdtemp(prefix="tg-bench-query-"))
    cfg_path = save_resolved(cfg, tmp / "config.yaml")
    py = [sys.executable, "-m", "services.cli"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    logs = {name: open(tmp / f"{name}.log", "wb") for name in ("router", "query")}  # noqa: SIM115
    procs = [subprocess.Popen([*py, "router", "--listen", endpoint], stdout=logs["router"], stderr=subprocess.STDOUT, env=env, cwd=ROOT)]
    time.sleep(1.0)
    session = open_session(cfg.transport.model_copy(update={"connect_timeout_s": 10.0}))
    topics = Topics(cfg.robot_id)
    graph = make_graph(args.segments, args.dim)
    vectors: dict[str, np.ndarray] = {}
    lock = threading.Lock()

    def embed(env_) -> EmbedReply:
        req: EmbedRequest = env_.body
        with lock:
            v = vectors.get(req.text)
            if v is None:
                v = vectors[req.text] = text_vector(req.text or "image", args.dim)
        return EmbedReply(embedding=v, model="bench")

    def snapshot(env_) -> GraphSnapshot:
        return graph.snapshot()

    vl = TypedQueryable(session, topics.vl_embed, EmbedRequest, EmbedReply, embed, robot_id=cfg.robot_id, workers=4)
    snaps = TypedQueryable(session, topics.graph_snapshot, SnapshotRequest, GraphSnapshot, snapshot, robot_id=cfg.robot_id, workers=1)
    deltas = TypedPublisher(session, topics.graph_delta, GraphDelta, robot_id=cfg.robot_id)
    deltas.seq = 1
    result: dict = {}
    try:
        procs.append(subprocess.Popen([*py, "serve", "query", "--config", str(cfg_path)], stdout=logs["query"], stderr=subprocess.STDOUT, env=env, cwd=ROOT))
        from services.query.client import QueryClient, QueryRefused

        with QueryClient(cfg.transport, robot_id=cfg.robot_id) as probe:
            deadline = time.monotonic() + 60
            while True:
                try:
                    probe.query(PHRASES[0], top_k=1)
                    break
                except QueryRefused:
                    pass
                except Exception:  # noqa: BLE001 - the service is still starting
                    pass
                if time.monotonic() > deadline:
                    raise SystemExit("the query service did not come up; see " + str(tmp / "query.log"))
                time.sleep(0.3)
        if args.clients_in == "processes":
            ctx = mp.get_context("spawn")
            q, go, make = ctx.Queue(), ctx.Event(), ctx.Process
        else:
            q, go, make = queue.Queue(), threading.Event(), threading.Thread
        clients = [make(target=client_main, args=(endpoint, cfg.robot_id, n_queries, 100 + k, go, q)) for k in range(args.clients)]
        for c in clients:
            c.start()
        # Spawned clients take seconds to import on 2 cores; staggered starts would overlap
        # fewer of them and flatter the latency.
        try:
            for _ in clients:
                q.get(timeout=120)
        except queue.Empty:
            raise SystemExit("a client did not open its session within 120 s") from None
        start_at = time.time()
        go.set()

        def live_deltas() -> None:
            # Fusion keeps mapping while clients ask: a changed segment every 0.5 s.
            k = 2
            while any(c.is_alive() for c in clients):
                seg = graph.segments[k % args.segments]
                d = GraphDelta(graph_seq=graph.graph_seq + 1, frame_index=k, segments=[seg])
                graph.apply_delta(d)
                deltas.put(d)
                k += 1
                time.sleep(0.5)

        feeder = threading.Thread(target=live_deltas, daemon=True)
        feeder.start()
        parts = [q.get(timeout=600) for _ in clients]
        t_end = time.time()
        for c in clients:
            c.join(timeout=30)
        feeder.join(timeout=5)
        lat = sorted(x for p in parts for x in p["latencies_ms"])
        errors = [e for p in parts for e in p["errors"]]
        wall = t_end - start_at
        p = lambda f: lat[min(len(lat) - 1, int(round(f * (len(lat) - 1))))]  # noqa: E731
        result = {
            "clients": args.clients,
            "clients_in": args.clients_in,
            "queries_per_client": n_queries,
            "segments": args.segments,
            "gallery_rows": sum(len(s.gallery_tracks) for s in graph.segments.values()),
            "dim": args.dim,
            "workers": args.workers,
            "queries": len(lat),
            "errors": len(errors),
            "error_samples": errors[:5],
            "p50_ms": round(p(0.50), 2) if lat else None,
            "p99_ms": round(p(0.99), 2) if lat else None,
            "max_ms": round(lat[-1], 2) if lat else None,
            "mean_ms": round(statistics.fmean(lat), 2) if lat else None,
            "queries_per_s": round(len(lat) / wall, 1) if wall > 0 else None,
            "graph_versions_during_run": graph.graph_seq,
            "target_p99_ms": TARGET_P99_MS,
            "p99_ok": bool(lat) and p(0.99) < TARGET_P99_MS and not errors,
            "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
            "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        }
    finally:
        for pr in reversed(procs):
            pr.terminate()
            try:
                pr.wait(20)
            except subprocess.TimeoutExpired:
                pr.kill()
        vl.close()
        snaps.close()
        deltas.close()
        session.close()
        for f in logs.values():
            f.close()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    r = result
    print(f"\nQuery service under load: {r['clients']} clients ({r['clients_in']}) x {r['queries_per_client']} queries, "
          f"{r['segments']} segments / {r['gallery_rows']} gallery rows of {r['dim']}-d, {r['workers']} workers")
    print("| p50 | p99 | max | mean | queries/s | errors | target p99 < 50 ms |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {r['p50_ms']} ms | {r['p99_ms']} ms | {r['max_ms']} ms | {r['mean_ms']} ms | {r['queries_per_s']} | {r['errors']} | {'pass' if r['p99_ok'] else 'FAIL'} |")
    print(f"wrote {args.out}")
    return 0 if not r["errors"] else 1


if __name__ == "__main__":
    sys.exit(main())
