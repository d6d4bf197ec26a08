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

``--while-mapping --novel`` measures the real system instead (issue 22)::

    python benchmarks/query.py --while-mapping --novel               # the demo scene
    python benchmarks/query.py --while-mapping --novel --preset small

It runs ``trackgraph launch deploy/local.yaml`` (router, keyframe_vl, fusion, query, tracker,
source as their own processes, on a free loopback port) on the preset's synthetic sequence
(generated into ``benchmarks/out/seq-<preset>`` once) and, from this process:

1. the moment the launcher's log says every service is alive, one novel text query (one
   never embedded before, by any cache) from a client whose session is already open; target:
   answered in under 2 s;
2. at once, ``--clients`` (16) clients, threads with a Zenoh session each, asking
   ``--queries`` (50) novel texts each one after another while the map is built, each with a
   ``--timeout`` (2 s) time-out (so ``deadline_s`` 1.8 s); target: no time-out, every request
   answered by a result or an "overloaded" reply within its time-out;
3. then the same clients asking texts they asked before (in the service's LRU); target: p99
   under 100 ms.

Novel texts carry a per-run random tag, so no cache on disk (MiniLM's) or in memory has them.
JSON goes to ``benchmarks/out/query-mapping.json``, with the share of the load's requests sent
while fusion was still mapping.
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import json
import multiprocessing as mp
import os
import platform
import queue
import signal
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
MAPPING_OUT = ROOT / "benchmarks" / "out" / "query-mapping.json"
TARGET_P99_MS = 50.0
PHRASES = [f"object number {i}" for i in range(40)]
TARGET_FIRST_NOVEL_S = 2.0
"""The issue's bound on the first novel text query after the launcher reports everything alive."""
TARGET_CACHED_P99_MS = 100.0
ADJECTIVES = ["red", "small", "wooden", "striped", "old", "shiny", "soft", "tall", "round", "dark", "green", "folded"]
NOUNS = ["armchair", "lamp", "mug", "book", "plant", "rug", "cushion", "vase", "clock", "shelf", "box", "picture frame"]


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
    ap.add_argument("--clients", type=int, default=None, help="default 8, 16 with --while-mapping")
    ap.add_argument("--queries", type=int, default=None, help="per client (default 100, 20 with --quick)")
    ap.add_argument("--segments", type=int, default=500)
    ap.add_argument("--dim", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=4, help="query service threads")
    ap.add_argument("--clients-in", choices=("processes", "threads"), default="processes",
                    help="each client its own process (default), or all as threads of one process: "
                    "clients on other machines cost the service's cores nothing, one process costs them least here")
    ap.add_argument("--out", type=Path, default=None, help=f"JSON result (default {DEFAULT_OUT}, {MAPPING_OUT} with --while-mapping)")
    ap.add_argument("--while-mapping", action="store_true", help="against `trackgraph launch` mapping a synthetic sequence (see above)")
    ap.add_argument("--novel", action="store_true", help="with --while-mapping: every load query a text never asked before")
    ap.add_argument("--preset", choices=("demo", "small"), default="demo", help="with --while-mapping: the synthetic scene")
    ap.add_argument("--sequence", type=Path, help="with --while-mapping: replay this sequence instead of the preset's")
    ap.add_argument("--timeout", type=float, default=2.0, help="with --while-mapping: each client's time-out (s)")
    args = ap.parse_args()
    if args.while_mapping:
        return run_while_mapping(args)
    if args.novel:
        ap.error("--novel goes with --while-mapping")
    args.out = args.out or DEFAULT_OUT
    args.clients = args.clients or 8
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


# ------------------------------------------------------------------ --while-mapping


def _sequence(args) -> Path:
    if args.sequence is not None:
        return args.sequence
    seq = ROOT / "benchmarks" / "out" / f"seq-{args.preset}"
    if not (seq / "traj.txt").is_file():
        print(f"generating the {args.preset} scene into {seq} (once) ...", flush=True)
        subprocess.run([sys.executable, "-m", "services.cli", "synth", "--preset", args.preset, "--seed", "0", "--out", str(seq), "--overwrite"],
                       check=True, cwd=ROOT)  # fmt: skip
    return seq


def _launch_file(tmp: Path, port: int) -> Path:
    import yaml

    doc = yaml.safe_load((ROOT / "deploy" / "local.yaml").read_text())
    endpoint = f"tcp/127.0.0.1:{port}"
    # The query service stays up after the sequence, for the cached phase.
    doc.update(config=str(ROOT / "deploy" / doc["config"]), connect=[endpoint], listen=[endpoint], exit_when_finished=False)
    path = tmp / "launch.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


class _LaunchLog:
    """The launcher's log lines as they come, with the time each was first seen here."""

    def __init__(self, path: Path) -> None:
        self.path, self.seen, self._done = path, {}, 0

    def poll(self) -> dict[str, float]:
        if self.path.is_file():
            text = self.path.read_text(errors="replace")
            now = time.monotonic()
            for line in text[self._done:].splitlines(keepends=True):
                if not line.endswith("\n"):
                    break
                self._done += len(line)
                self.seen.setdefault(line.strip(), now)
        return self.seen

    def when(self, event: str) -> float | None:
        """When a line ending in ``event`` (a launcher event such as "query alive") was seen."""
        return next((t for msg, t in self.poll().items() if msg.endswith(f" {event}")), None)


def _classify(reply_or_exc) -> str:
    if isinstance(reply_or_exc, Exception):
        msg = str(reply_or_exc)
        if "overloaded: " in msg:
            return "overloaded"
        # Zenoh's own time-out comes back as an error reply "Timeout"; ours as "no reply within".
        return "timeout" if "no reply within" in msg or msg.endswith(": Timeout") else "transport_error"
    if reply_or_exc.error is None:
        return "result"
    return "deadline" if reply_or_exc.error.startswith("deadline exceeded") else "refused"


def _ask_timed(client, text: str) -> tuple[str, float, str | None]:
    from shared.messages.rpc import QueryRequest
    from shared.transport import TransportError

    t0 = time.perf_counter()
    try:
        out = client.ask(QueryRequest(text=text, top_k=10))
    except TransportError as exc:
        out = exc
    ms = 1e3 * (time.perf_counter() - t0)
    kind = _classify(out)
    detail = str(out) if isinstance(out, Exception) else out.error
    return kind, ms, detail


def _pct(xs: list[float], f: float) -> float | None:
    xs = sorted(xs)
    return round(xs[min(len(xs) - 1, int(round(f * (len(xs) - 1))))], 2) if xs else None


def _phase(records: list[tuple[str, float, str | None]], timeout_s: float) -> dict:
    kinds = collections.Counter(k for k, _, _ in records)
    lat = [ms for _, ms, _ in records]
    answered = [ms for k, ms, _ in records if k in ("result", "overloaded")]
    return {
        "requests": len(records),
        **{k: kinds.get(k, 0) for k in ("result", "overloaded", "deadline", "refused", "timeout", "transport_error")},
        "later_than_timeout": sum(ms > 1e3 * timeout_s for ms in lat),
        "p50_ms": _pct(lat, 0.5), "p99_ms": _pct(lat, 0.99), "max_ms": round(max(lat), 2) if lat else None,
        "result_p99_ms": _pct([ms for k, ms, _ in records if k == "result"], 0.99),
        "overloaded_max_ms": round(max((ms for k, ms, _ in records if k == "overloaded"), default=0.0), 2),
        "answered_in_time": sum(ms <= 1e3 * timeout_s for ms in answered),
        "error_samples": sorted({d for k, _, d in records if k not in ("result", "overloaded") and d})[:5],
    }  # fmt: skip


def run_while_mapping(args) -> int:
    from services.query.client import QueryClient, deadline_for
    from shared.config import TransportConfig

    out_path = args.out or MAPPING_OUT
    n_clients, n_queries, timeout_s = args.clients or 16, args.queries or 50, args.timeout
    seq = _sequence(args)
    tmp = Path(tempfile.mkdtemp(prefix="tg-bench-query-mapping-"))
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    launch_file = _launch_file(tmp, port)
    log_path, summary_path = tmp / "launcher.log", tmp / "launcher.json"
    tag = os.urandom(4).hex()  # novel for every cache, on disk and in memory, this run
    rng = np.random.default_rng(7)

    def novel(c: int, k: int) -> str:
        return f"{ADJECTIVES[int(rng.integers(len(ADJECTIVES)))]} {NOUNS[int(rng.integers(len(NOUNS)))]} {tag}-{c}-{k}"

    texts = [[novel(c, k) for k in range(n_queries)] for c in range(n_clients)] if args.novel else \
        [[PHRASES[int(rng.integers(len(PHRASES)))] for _ in range(n_queries)] for _ in range(n_clients)]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    t_launch = time.monotonic()
    with open(log_path, "wb") as log_f, open(summary_path, "wb") as sum_f:
        launcher = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "launch", str(launch_file), "--sequence", str(seq), "--out", str(tmp / "map"), "--json"],
            stdout=sum_f, stderr=log_f, env=env, cwd=ROOT,
        )  # fmt: skip
    log = _LaunchLog(log_path)
    clients: list = []
    result: dict = {}
    try:
        import yaml

        names = [s["name"] for s in yaml.safe_load(launch_file.read_text())["services"]]
        while log.when("router alive") is None:
            if launcher.poll() is not None or time.monotonic() - t_launch > 120:
                raise SystemExit(f"the launcher did not start its router; see {log_path}")
            time.sleep(0.05)
        transport = TransportConfig(mode="client", connect=[endpoint], shared_memory=False, connect_timeout_s=30.0)
        probe = QueryClient(transport, timeout_s=timeout_s)
        clients = [QueryClient(transport, timeout_s=timeout_s) for _ in range(n_clients)]
        while not all(log.when(f"{n} alive") is not None for n in names):
            if launcher.poll() is not None or time.monotonic() - t_launch > 600:
                raise SystemExit(f"not every service came up; see {log_path}")
            time.sleep(0.02)
        all_alive = max(log.when(f"{n} alive") for n in names)
        alive_at = {n: round(log.when(f"{n} alive") - t_launch, 2) for n in names}
        first = _ask_timed(probe, f"a {NOUNS[0]} never asked before {tag}")
        first_lag_s = time.monotonic() - all_alive  # the probe went out within one log poll of "alive"
        print(f"everything alive {all_alive - t_launch:.1f} s after the launch; first novel query: {first[0]} in {first[1]:.0f} ms", flush=True)

        def run_phase(texts_of) -> tuple[list, float, float]:
            go, parts = threading.Barrier(n_clients + 1), [[] for _ in range(n_clients)]

            def one(c: int) -> None:
                go.wait()
                for text in texts_of(c):
                    kind, ms, detail = _ask_timed(clients[c], text)
                    parts[c].append((kind, ms, detail, time.monotonic()))

            threads = [threading.Thread(target=one, args=(c,), daemon=True) for c in range(n_clients)]
            for t in threads:
                t.start()
            go.wait()
            t0 = time.monotonic()
            for t in threads:
                t.join()
            return [r for p in parts for r in p], t0, time.monotonic()

        load, load_t0, load_t1 = run_phase(lambda c: texts[c])
        mapped_at = log.when("fusion finished")
        while_mapping = sum(1 for *_, t in load if mapped_at is None or t <= mapped_at)
        order = np.random.default_rng(11)
        cached, cached_t0, cached_t1 = run_phase(lambda c: [texts[c][int(i)] for i in order.permutation(n_queries)])
        mapped_at = log.when("fusion finished")
        result = {
            "mode": "while-mapping" + (" novel" if args.novel else ""),
            "preset": None if args.sequence else args.preset,
            "sequence": str(seq),
            "clients": n_clients,
            "queries_per_client": n_queries,
            "timeout_s": timeout_s,
            "deadline_s": round(deadline_for(timeout_s), 3),
            "alive_after_launch_s": alive_at,
            "first_novel": {"outcome": first[0], "ms": round(first[1], 2), "error": first[2], "sent_after_alive_s": round(first_lag_s - first[1] / 1e3, 3)},
            "first_novel_ok": first[0] == "result" and first[1] < 1e3 * TARGET_FIRST_NOVEL_S,
            "novel" if args.novel else "load": {
                **_phase([r[:3] for r in load], timeout_s), "wall_s": round(load_t1 - load_t0, 2),
                "sent_while_mapping": while_mapping,
            },
            "cached": {**_phase([r[:3] for r in cached], timeout_s), "wall_s": round(cached_t1 - cached_t0, 2),
                       "sent_while_mapping": sum(1 for *_, t in cached if mapped_at is None or t <= mapped_at)},
            "mapping_finished_after_launch_s": None if mapped_at is None else round(mapped_at - t_launch, 1),
            "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
            "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        }  # fmt: skip
        probe.close()
    finally:
        for c in clients:
            c.close()
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
            try:
                launcher.wait(60)
            except subprocess.TimeoutExpired:
                launcher.kill()
    try:
        summary = json.loads(summary_path.read_text() or "{}")
        status = json.loads(Path(summary["services"]["query"]["status_file"]).read_text())
        result["query_status"] = {k: status["figures"].get(k) for k in ("queries", "refused", "overloaded", "expired", "warmup_s")}
        result["query_status"]["latency_p99_ms"] = status.get("latency_p99_ms")
    except (OSError, KeyError, TypeError, ValueError) as exc:
        result["query_status"] = f"not read: {exc}"
    load_key = "novel" if args.novel else "load"
    ld, ca = result[load_key], result["cached"]
    result["load_ok"] = ld["timeout"] == 0 and ld["transport_error"] == 0 and ld["answered_in_time"] == ld["requests"]
    result["cached_ok"] = ca["p99_ms"] is not None and ca["p99_ms"] < TARGET_CACHED_P99_MS and ca["result"] == ca["requests"]
    result["logs"] = str(tmp)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=2))
    r = result
    print(f"\nQuery service while `{r['preset'] or seq}` maps: first novel query after everything alive, then {r['clients']} clients x "
          f"{r['queries_per_client']} {'novel' if args.novel else 'repeated'} texts, then the same texts again (cached); time-out {timeout_s:g} s")
    print("| phase | requests | results | overloaded | deadline exceeded | time-outs | p50 | p99 | max | sent while mapping | target |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    f = r["first_novel"]
    print(f"| first novel | 1 | {int(f['outcome'] == 'result')} | - | - | {int(f['outcome'] == 'timeout')} | {f['ms']} ms | | | yes | < 2 s: {'pass' if r['first_novel_ok'] else 'FAIL'} |")
    for name, ph, ok, target in ((load_key, ld, r["load_ok"], "0 time-outs, all answered in time"), ("cached", ca, r["cached_ok"], "p99 < 100 ms")):
        print(f"| {name} | {ph['requests']} | {ph['result']} | {ph['overloaded']} | {ph['deadline']} | {ph['timeout']} | {ph['p50_ms']} ms | "
              f"{ph['p99_ms']} ms | {ph['max_ms']} ms | {ph['sent_while_mapping']} | {target}: {'pass' if ok else 'FAIL'} |")
    print(f"query service: {r['query_status']}; wrote {out_path}; logs in {tmp}")
    return 0 if r["first_novel_ok"] and r["load_ok"] and r["cached_ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
