"""Benchmark: 10^5 hostile payloads into every subscribed key and queryable of a running system.

Run from the repository root::

    python benchmarks/fuzz.py               # 10^5 payloads
    python benchmarks/fuzz.py --n 10000     # the CI size (tests/faults/test_hostile_traffic.py)

Router, keyframe_vl, tracker, fusion and query run in this process, each with its own Zenoh
session on loopback (``tcp/127.0.0.1``, free port, scouting off). The payloads are those of
``tests/faults/hostile.py`` (random bytes, broken envelopes, forbidden arrays, extra keys,
type confusion, truncation, oversized strings and blobs), spread over every key, puts with
congestion control BLOCK so none is lost on the way. Every ``--valid-every`` payloads a valid
text query is sent and must be answered without error. Reported: payloads per kind and key,
rejections counted by each service (must equal what was sent), crashes (worker errors),
valid queries answered, resident memory before, at the peak and after, and payloads/s.
The CI test also streams the ``small`` preset through the system and demands the in-process
map; this benchmark measures volume. JSON goes to benchmarks/out/fuzz.json.
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import json
import platform
import socket
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tests" / "faults"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import zenoh  # noqa: E402
from hostile import QUERYABLE, SUBSCRIBED, key_expr, payloads, rss_mb  # noqa: E402

from services.fusion.node import FusionNode  # noqa: E402
from services.keyframe_vl.node import KeyframeVLNode  # noqa: E402
from services.query.client import QueryClient  # noqa: E402
from services.query.node import QueryNode  # noqa: E402
from services.router import run_router  # noqa: E402
from services.tracker.node import TrackerNode  # noqa: E402
from shared.config import TrackGraphConfig  # noqa: E402
from shared.messages.rpc import QueryRequest  # noqa: E402
from shared.topics import Topics  # noqa: E402
from shared.transport import open_session  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "out" / "fuzz.json"



def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(n: int, seed: int, valid_every: int, work: Path) -> dict:
    import logging

    logging.getLogger("shared.transport").setLevel(logging.ERROR)  # a warning per kind and key is noise here
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    from services.mapping import prepare_config
    from shared.synth import run_synth

    seq = work / "seq"  # the simulated encoders read a synthetic scene's ground truth
    run_synth("small", 0, seq, {"camera": {"frames": 4}}, progress=False)
    cfg = prepare_config(TrackGraphConfig.model_validate({
        "transport": {"mode": "client", "connect": [endpoint], "shared_memory": False},
        "keyframe_vl": {"segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}},
        "tracker": {"features": {"backend": "classical", "short_side": 240}, "device": "cpu"},
    }), seq)  # fmt: skip
    stop = threading.Event()
    router_cfg = cfg.transport.model_copy(update={"mode": "router", "connect": [], "listen": [endpoint]})
    router = threading.Thread(target=run_router, args=(router_cfg, stop), daemon=True)
    router.start()
    time.sleep(0.5)
    nodes = []
    sent: collections.Counter = collections.Counter()
    kinds: collections.Counter = collections.Counter()
    errors_replied = collections.Counter()
    bad_replies: list[str] = []
    valid = {"sent": 0, "answered": 0, "failed": []}
    peak = 0.0
    try:
        kvl, fusion, tracker, query = KeyframeVLNode(cfg), FusionNode(cfg, work / "map"), TrackerNode(cfg), QueryNode(cfg)
        nodes += [kvl, fusion, tracker, query]
        session = open_session(cfg.transport)
        client = QueryClient(cfg.transport, session=session, timeout_s=10)
        topics = Topics(cfg.robot_id)
        time.sleep(1.0)
        before = rss_mb()
        keys = {**SUBSCRIBED, **QUERYABLE}
        t0 = time.monotonic()
        from tqdm import tqdm

        for i, p in enumerate(tqdm(payloads(n, seed, keys), total=n, unit="payload", desc="fuzz")):
            sent[p.key] += 1
            kinds[p.kind] += 1
            key = key_expr(topics, p.key)
            if p.key in QUERYABLE:
                replies = list(session.get(key, payload=p.data, timeout=10.0))
                if len(replies) == 1 and replies[0].err is not None:
                    errors_replied[p.key] += 1
                else:
                    bad_replies.append(f"{p.key}/{p.kind}: {len(replies)} replies")
            else:
                session.put(key, p.data, congestion_control=zenoh.CongestionControl.BLOCK)
            if valid_every and i % valid_every == 0:
                valid["sent"] += 1
                try:
                    reply = client.ask(QueryRequest(text="chair", top_k=3))
                    if reply.error is not None and "empty" not in reply.error:
                        raise RuntimeError(reply.error)
                    valid["answered"] += 1
                except Exception as exc:  # noqa: BLE001 - recorded and reported
                    valid["failed"].append(repr(exc))
            if i % 1000 == 0:
                peak = max(peak, rss_mb())
        seconds = time.monotonic() - t0
        time.sleep(2.0)  # let the last puts be counted
        after = rss_mb()
        peak = max(peak, after)
        counted = {
            "frames": tracker.subs[0].stats, "keyframe_masks": tracker.subs[1].stats, "keyframe_features": tracker.subs[2].stats,
            "end_of_sequence": tracker.subs[3].stats, "keyframe_request": kvl.requests.stats, "tracks_frame": fusion.subs[0].stats,
            "tracks_features": fusion.subs[1].stats, "tracks_end": fusion.subs[2].stats, "graph_delta": query.deltas.stats,
            "graph_snapshot": fusion.snapshots.stats, "vl_embed": kvl.embed.stats, "query": query.queryable.stats,
        }  # fmt: skip
        per_key = {
            k: {"sent": sent[k], "rejected": st.rejected, "dropped": st.dropped, "ok": st.rejected + st.dropped == sent[k]}
            for k, st in counted.items()
        }
        crashes = fusion.errors + tracker.errors
        client.close()
        session.close()
    finally:
        for node in reversed(nodes):
            node.close()
        stop.set()
        router.join(timeout=10)
    return {
        "payloads": n,
        "seed": seed,
        "seconds": round(seconds, 1),
        "payloads_per_s": round(n / seconds, 1),
        "kinds": dict(kinds),
        "per_key": per_key,
        "all_counted": all(v["ok"] for v in per_key.values()),
        "frame_ack_sent_uncounted": sent["frame_ack"],
        "queryable_error_replies": dict(errors_replied),
        "bad_replies": bad_replies[:20],
        "worker_errors": crashes,
        "valid_queries": {"sent": valid["sent"], "answered": valid["answered"], "failed": valid["failed"][:5]},
        "rss_mb": {"before": round(before, 1), "peak": round(peak, 1), "after": round(after, 1), "growth": round(after - before, 1)},
    }


def main() -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--valid-every", type=int, default=100)
    ap.add_argument("--json", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="tg-fuzz-") as tmp:
        res = run(args.n, args.seed, args.valid_every, Path(tmp))
    res["machine"] = {"platform": platform.platform(), "python": platform.python_version()}
    res["when"] = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=2))
    print(f"{'key':<18} {'sent':>7} {'rejected':>9} {'dropped':>8}  counted")
    for k, v in res["per_key"].items():
        print(f"{k:<18} {v['sent']:>7} {v['rejected']:>9} {v['dropped']:>8}  {'yes' if v['ok'] else 'NO'}")
    print(
        f"\n{res['payloads']} payloads in {res['seconds']} s ({res['payloads_per_s']}/s); worker errors {res['worker_errors']}; "
        f"valid queries {res['valid_queries']['answered']}/{res['valid_queries']['sent']}; "
        f"RSS {res['rss_mb']['before']} -> peak {res['rss_mb']['peak']} -> {res['rss_mb']['after']} MB"
    )
    print(f"JSON: {args.json}")
    return 0 if res["all_counted"] and not res["worker_errors"] and not res["bad_replies"] and not res["valid_queries"]["failed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
