#!/usr/bin/env python3
"""A TrackGraph client written from docs/wire.md alone, with zenoh, msgpack and numpy only.

    python examples/raw_client.py --connect tcp/127.0.0.1:7447 --robot robot0 --text chair --follow 10

It joins the system's Zenoh router as a client and

1. subscribes to ``trackgraph/<robot>/graph/delta`` first, so no change is missed meanwhile;
2. asks the ``graph/snapshot`` queryable for the whole graph (a SnapshotRequest without mesh);
3. sends a text QueryRequest to the ``query`` queryable and prints the ranked segments;
4. follows the deltas for ``--follow`` seconds, keeping its own copy of the segments: a delta
   numbered ``graph_seq + 1`` is applied, an older one skipped, and a gap makes it read a new
   snapshot (docs/wire.md, GraphDelta);
5. prints what it saw (``--json``: one JSON line).

Both queryables may not be answering yet when a system is starting (no graph yet: QueryReply
``error`` says to try again; no fusion: no reply at all), so each request is retried for up to
``--wait`` seconds. Exit status 0 when the query was answered without error, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import sys
import time
import zlib

import msgpack
import numpy as np
import zenoh

SCHEMA_VERSION = 2
"""The envelope's ``v`` (docs/wire.md, Envelope)."""


# ---------------------------------------------------------------- the envelope and arrays


def nd(arr: np.ndarray) -> dict:
    """An array as the wire's ``__nd__`` map, ``raw`` encoding (little-endian, C order)."""
    arr = np.ascontiguousarray(arr)
    return {"__nd__": "raw", "dtype": arr.dtype.name, "shape": list(arr.shape), "data": arr.astype(arr.dtype.newbyteorder("<")).tobytes()}


def _array(obj: dict):
    """msgpack object hook: ``__nd__`` maps to numpy arrays (images stay maps: decoding JPEG and
    PNG needs an image library, and a graph carries none)."""
    if "__nd__" not in obj:
        return obj
    enc, shape = obj["__nd__"], tuple(obj["shape"])
    dtype = np.dtype(obj["dtype"]).newbyteorder("<")
    count = math.prod(shape)
    if enc == "raw":
        return np.frombuffer(obj["data"], dtype).reshape(shape)
    if enc == "zlib":
        return np.frombuffer(zlib.decompress(obj["data"]), dtype).reshape(shape)
    if enc == "bits":
        return np.unpackbits(np.frombuffer(obj["data"], np.uint8), count=count).astype(bool).reshape(shape)
    if enc == "rle":
        runs = np.frombuffer(obj["data"], "<u4").astype(np.int64)
        return np.repeat(np.arange(len(runs)) % 2 == 1, runs).reshape(shape)
    return obj


def pack(msg_type: str, body: dict, robot: str, seq: int) -> bytes:
    env = {"v": SCHEMA_VERSION, "type": msg_type, "robot": robot, "seq": seq, "stamp": time.time(), "body": body}
    return msgpack.packb(env, use_bin_type=True)


def unpack(payload: bytes, msg_type: str, robot: str) -> dict:
    """The body of an envelope that must carry ``msg_type`` from ``robot``."""
    env = msgpack.unpackb(payload, raw=False, object_hook=_array)
    if env.get("v") != SCHEMA_VERSION or env.get("type") != msg_type:
        raise ValueError(f"expected a version {SCHEMA_VERSION} {msg_type}, got version {env.get('v')!r} {env.get('type')!r}")
    if env.get("robot") != robot:
        raise ValueError(f"{msg_type} claims robot {env.get('robot')!r}, not {robot!r}")  # the robot-key rule
    return env["body"]


# ---------------------------------------------------------------- requests


class Client:
    def __init__(self, session: zenoh.Session, robot: str, timeout: float) -> None:
        self.session, self.robot, self.timeout = session, robot, timeout
        self.root = f"trackgraph/{robot}"
        self.seq = 0

    def ask(self, key: str, msg_type: str, body: dict, reply_type: str) -> dict:
        """The reply body; RuntimeError with the service's text for an error reply (or none)."""
        payload = pack(msg_type, body, self.robot, self.seq)
        self.seq += 1
        for reply in self.session.get(f"{self.root}/{key}", payload=payload, timeout=self.timeout):
            if reply.ok is not None:
                return unpack(reply.ok.payload.to_bytes(), reply_type, self.robot)
            raise RuntimeError(reply.err.payload.to_bytes().decode("utf-8", "replace"))
        raise TimeoutError(f"{self.root}/{key}: no reply within {self.timeout:.1f} s")

    def snapshot(self) -> dict:
        return self.ask("graph/snapshot", "SnapshotRequest", {"with_mesh": False}, "GraphSnapshot")

    def query(self, text: str, top_k: int) -> dict:
        return self.ask("query", "QueryRequest", {"text": text, "top_k": top_k}, "QueryReply")


def retry(what, wait_s: float, again=lambda result: False):
    """Call ``what`` until it neither raises TimeoutError nor ``again(result)``, for ``wait_s``."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            result = what()
            if not again(result) or time.monotonic() >= deadline:
                return result
        except TimeoutError:
            if time.monotonic() >= deadline:
                raise
        time.sleep(0.5)


# ---------------------------------------------------------------- the replica


class Segments:
    """Segment ids and centroids at one graph version, kept by snapshots and deltas."""

    def __init__(self) -> None:
        self.graph_seq = -1
        self.segments: dict[int, list[float]] = {}
        self.applied = self.skipped = self.gaps = self.snapshots = 0

    def load(self, snap: dict) -> None:
        self.graph_seq = int(snap["graph_seq"])
        self.segments = {int(s["id"]): [float(v) for v in s["centroid"]] for s in snap.get("segments", [])}
        self.snapshots += 1

    def apply(self, delta: dict) -> bool:
        """Apply a delta; False if there is a gap (a snapshot is needed)."""
        seq = int(delta["graph_seq"])
        if seq <= self.graph_seq:
            self.skipped += 1  # already in the snapshot
            return True
        if seq != self.graph_seq + 1:
            self.gaps += 1
            return False
        for s in delta.get("segments", []):
            self.segments[int(s["id"])] = [float(v) for v in s["centroid"]]
        for sid in delta.get("removed_segments", []):
            self.segments.pop(int(sid), None)
        self.graph_seq = seq
        self.applied += 1
        return True


def open_session(endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the router's endpoint")
    ap.add_argument("--robot", default="robot0", help="robot id: the keys are trackgraph/<robot>/...")
    ap.add_argument("--text", default="chair", help="the text query")
    ap.add_argument("--top-k", type=int, default=5)
    ap.add_argument("--follow", type=float, default=5.0, help="seconds to follow graph/delta")
    ap.add_argument("--wait", type=float, default=60.0, help="seconds to keep asking a system that is starting")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for one reply")
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args(argv)

    session = open_session(args.connect)
    client = Client(session, args.robot, args.timeout)
    deltas: queue.Queue[bytes] = queue.Queue(maxsize=10_000)

    def on_delta(sample: zenoh.Sample) -> None:
        # Never work inside a Zenoh callback: hand the bytes over and return.
        try:
            deltas.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            pass

    sub = session.declare_subscriber(f"{client.root}/graph/delta", on_delta)
    replica = Segments()
    out: dict = {"connect": args.connect, "robot": args.robot}
    try:
        replica.load(retry(client.snapshot, args.wait))
        out["snapshot"] = {"graph_seq": replica.graph_seq, "segments": len(replica.segments)}

        reply = retry(lambda: client.query(args.text, args.top_k), args.wait, again=lambda r: bool(r.get("error")) and "try again" in r["error"])
        hits = [{"segment": int(h["segment"]), "score": round(float(h["score"]), 4), "centroid": [round(float(v), 3) for v in h["centroid"]]}
                for h in reply.get("hits", [])]  # fmt: skip
        out["query"] = {"text": args.text, "graph_seq": reply.get("graph_seq"), "error": reply.get("error"), "hits": hits}

        received, first_seq = 0, None
        deadline = time.monotonic() + args.follow
        while (left := deadline - time.monotonic()) > 0:
            try:
                payload = deltas.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            try:
                delta = unpack(payload, "GraphDelta", args.robot)
            except (ValueError, KeyError, TypeError) as exc:  # msgpack errors are ValueErrors
                print(f"skipped a bad graph/delta: {exc}", file=sys.stderr)
                continue
            received += 1
            first_seq = first_seq if first_seq is not None else int(delta["graph_seq"])
            if not replica.apply(delta):
                replica.load(retry(client.snapshot, args.wait))
        out["deltas"] = {"received": received, "applied": replica.applied, "skipped": replica.skipped, "gaps": replica.gaps,
                         "first_seq": first_seq, "last_seq": replica.graph_seq}  # fmt: skip
        out["segments"] = len(replica.segments)
    except (RuntimeError, TimeoutError) as exc:
        out["error"] = str(exc)
    finally:
        sub.undeclare()
        session.close()

    if args.json:
        print(json.dumps(out))
    else:
        if "snapshot" in out:
            print(f"snapshot: graph version {out['snapshot']['graph_seq']}, {out['snapshot']['segments']} segments")
        if "query" in out:
            q = out["query"]
            print(f"query {q['text']!r} (graph version {q['graph_seq']}): " + (f"refused: {q['error']}" if q["error"] else f"{len(q['hits'])} hits"))
            for rank, h in enumerate(q["hits"], 1):
                print(f"  {rank}. segment {h['segment']}  score {h['score']:.3f}  at {h['centroid']}")
        if "deltas" in out:
            d = out["deltas"]
            print(f"followed graph/delta for {args.follow:.0f} s: {d['received']} deltas, {d['applied']} applied, {d['gaps']} gaps; "
                  f"now at version {d['last_seq']} with {out['segments']} segments")  # fmt: skip
        if "error" in out:
            print(f"error: {out['error']}", file=sys.stderr)
    ok = "error" not in out and not out.get("query", {}).get("error")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
