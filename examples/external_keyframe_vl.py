#!/usr/bin/env python3
"""A stand-in keyframe_vl service written from docs/wire.md alone, with zenoh, msgpack and numpy.

    python examples/external_keyframe_vl.py --connect tcp/127.0.0.1:7447 --robot robot0

It does what docs/wire.md asks of whoever declares ``keyframe/masks``, ``keyframe/features``
and ``vl/embed``, with the simplest perception that works:

- ``keyframe/request`` (KeyframeRequest) in, on a bounded queue and a worker thread (never in
  the Zenoh callback); for each request
  - ``keyframe/masks`` (KeyframeMasks): connected regions of quantised colour (4 levels a
    channel), largest first, small ones dropped;
  - ``keyframe/features`` (MaskFeatures): each mask's normalised 4x4x4 colour histogram;
  - a request it cannot handle is still answered on both keys, with N = 0 and ``error`` set;
- ``vl/embed`` (EmbedRequest -> EmbedReply): a text's embedding is a deterministic unit vector
  drawn from a hash of the text; an image's is its colour histogram. A request that does not
  decode is answered with a Zenoh error reply, ``bad request: ...``, as docs/wire.md's one
  error rule says;
- the liveliness token ``trackgraph/<robot>/alive/keyframe_vl``, and a ServiceStatus on
  ``trackgraph/<robot>/status/keyframe_vl`` once a second and once at stop.

``deploy/external-vl.yaml`` runs it in keyframe_vl's place (a launch file's ``command:``). Its
masks and features are crude (histograms know colour, not objects; text queries rank
segments arbitrarily): it shows that a service can be swapped by someone with only the docs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import queue
import signal
import sys
import threading
import time
import zlib

import msgpack
import numpy as np
import zenoh

SCHEMA_VERSION = 2
MODEL = "external:colour-histogram-64"
BINS = 4
"""Histogram bins a channel: 4 x 4 x 4 = 64-d features and embeddings."""
LEVELS = 4
"""Colour levels a channel for the regions."""
WORK_WIDTH = 160
"""Regions are found on an image reduced to about this width (the masks are full size)."""


# ---------------------------------------------------------------- the envelope and arrays


def nd(arr: np.ndarray, encoding: str = "raw") -> dict:
    """An array as the wire's ``__nd__`` map: ``raw`` (little-endian, C order) or ``bits``."""
    arr = np.ascontiguousarray(arr)
    head = {"dtype": arr.dtype.name, "shape": list(arr.shape)}
    if encoding == "bits":
        return {"__nd__": "bits", **head, "data": np.packbits(arr.ravel()).tobytes()}
    return {"__nd__": "raw", **head, "data": arr.astype(arr.dtype.newbyteorder("<")).tobytes()}


def _array(obj: dict):
    if "__nd__" not in obj:
        return obj
    enc, shape = obj["__nd__"], tuple(obj["shape"])
    dtype = np.dtype(obj["dtype"]).newbyteorder("<")
    if enc == "raw":
        return np.frombuffer(obj["data"], dtype).reshape(shape)
    if enc == "zlib":
        return np.frombuffer(zlib.decompress(obj["data"]), dtype).reshape(shape)
    if enc == "bits":
        return np.unpackbits(np.frombuffer(obj["data"], np.uint8), count=math.prod(shape)).astype(bool).reshape(shape)
    if enc == "rle":
        runs = np.frombuffer(obj["data"], "<u4").astype(np.int64)
        return np.repeat(np.arange(len(runs)) % 2 == 1, runs).reshape(shape)
    return Undecoded(enc)


class Undecoded:
    """An array in an encoding that needs an image decoder (jpeg, png), which this stand-in
    does not have: a request whose rgb is one is answered with ``error`` set."""

    def __init__(self, encoding: str) -> None:
        self.encoding = encoding

    def __repr__(self) -> str:
        return f"a {self.encoding} array (run the link with transport.codec.rgb: raw)"


class BadRequest(ValueError):
    """A payload that is not the message it should be."""


def unpack(payload: bytes, msg_type: str, robot: str) -> dict:
    try:
        env = msgpack.unpackb(payload, raw=False, object_hook=_array)
    except ValueError as exc:
        raise BadRequest(f"not a valid msgpack payload ({exc})") from None
    if not isinstance(env, dict) or env.get("v") != SCHEMA_VERSION or env.get("type") != msg_type:
        got = (env.get("v"), env.get("type")) if isinstance(env, dict) else type(env).__name__
        raise BadRequest(f"expected a version {SCHEMA_VERSION} {msg_type} envelope, got {got!r}")
    if env.get("robot") != robot:
        raise BadRequest(f"{msg_type} claims robot {env.get('robot')!r}; this key is robot {robot!r}")
    if not isinstance(env.get("body"), dict):
        raise BadRequest(f"{msg_type}: the body must be a map")
    return env["body"]


class Publisher:
    """One key's publisher, numbering its envelopes."""

    def __init__(self, session: zenoh.Session, key: str, msg_type: str, robot: str) -> None:
        # BLOCK, as docs/wire.md says: DROP would lose large fragmented messages.
        self.pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self.msg_type, self.robot, self.seq = msg_type, robot, 0

    def put(self, body: dict) -> None:
        env = {"v": SCHEMA_VERSION, "type": self.msg_type, "robot": self.robot, "seq": self.seq, "stamp": time.time(), "body": body}
        self.pub.put(msgpack.packb(env, use_bin_type=True))
        self.seq += 1


# ---------------------------------------------------------------- perception


def regions(rgb: np.ndarray) -> tuple[np.ndarray, int]:
    """(h, w) int label of the connected region of equal quantised colour of each pixel of the
    image reduced by the returned step; union-find by hooking and pointer jumping, in numpy."""
    step = max(1, rgb.shape[1] // WORK_WIDTH)
    small = rgb[::step, ::step]
    h, w = small.shape[:2]
    q = (small.astype(np.int32) * LEVELS) // 256
    colour = (q[..., 0] * LEVELS + q[..., 1]) * LEVELS + q[..., 2]
    idx = np.arange(h * w).reshape(h, w)
    same_x = colour[:, 1:] == colour[:, :-1]
    same_y = colour[1:, :] == colour[:-1, :]
    a = np.concatenate([idx[:, 1:][same_x], idx[1:, :][same_y]])
    b = np.concatenate([idx[:, :-1][same_x], idx[:-1, :][same_y]])
    parent = np.arange(h * w)
    while True:
        pa, pb = parent[a], parent[b]
        differ = pa != pb
        if not differ.any():
            break
        np.minimum.at(parent, np.maximum(pa[differ], pb[differ]), np.minimum(pa[differ], pb[differ]))
        while True:  # pointer jumping: every pixel points at its root
            nxt = parent[parent]
            if np.array_equal(nxt, parent):
                break
            parent = nxt
    return parent.reshape(h, w), step


def segment(rgb: np.ndarray, min_area_frac: float, max_masks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, H, W) bool masks, (N, 4) float32 boxes, (N,) float32 scores, largest region first."""
    H, W = rgb.shape[:2]
    labels, step = regions(rgb)
    ids, counts = np.unique(labels, return_counts=True)
    frac = counts / labels.size
    keep = (frac >= min_area_frac) & (frac <= 0.95)
    order = np.argsort(-counts[keep], kind="stable")[:max_masks]
    ids, frac = ids[keep][order], frac[keep][order]
    # Back to full size: each full-resolution pixel takes the label of its reduced pixel.
    full = np.repeat(np.repeat(labels, step, axis=0), step, axis=1)[:H, :W]
    if full.shape != (H, W):
        full = np.pad(full, ((0, H - full.shape[0]), (0, W - full.shape[1])), mode="edge")
    masks = full[None] == ids[:, None, None]
    boxes = np.zeros((len(ids), 4), np.float32)
    for i, m in enumerate(masks):
        ys, xs = np.nonzero(m)
        boxes[i] = (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
    return masks, boxes, frac.astype(np.float32)


def histogram(pixels: np.ndarray) -> np.ndarray:
    """(64,) float32 unit colour histogram of (P, 3) uint8 pixels."""
    q = (pixels.astype(np.int32) * BINS) // 256
    h = np.bincount((q[:, 0] * BINS + q[:, 1]) * BINS + q[:, 2], minlength=BINS**3).astype(np.float32)
    n = float(np.linalg.norm(h))
    return h / n if n > 0 else np.full(BINS**3, 1 / math.sqrt(BINS**3), np.float32)


def text_embedding(text: str) -> np.ndarray:
    seed = int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")
    v = np.random.default_rng(seed).standard_normal(BINS**3).astype(np.float32)
    return v / np.linalg.norm(v)


# ---------------------------------------------------------------- the service


class Counters:
    def __init__(self, name: str) -> None:
        self.name = name
        self.received = self.processed = self.rejected = self.dropped = 0


class Service:
    def __init__(self, session: zenoh.Session, robot: str, min_area_frac: float, max_masks: int) -> None:
        self.session, self.robot = session, robot
        self.min_area_frac, self.max_masks = min_area_frac, max_masks
        root = f"trackgraph/{robot}"
        self.masks_pub = Publisher(session, f"{root}/keyframe/masks", "KeyframeMasks", robot)
        self.features_pub = Publisher(session, f"{root}/keyframe/features", "MaskFeatures", robot)
        self.status_pub = Publisher(session, f"{root}/status/keyframe_vl", "ServiceStatus", robot)
        self.requests = Counters("keyframe_request")
        self.embeds = Counters("vl_embed")
        self.published = {"keyframe_masks": 0, "keyframe_features": 0}
        self.failed = 0
        self.replies = 0
        self.latencies: list[float] = []
        self.started = time.monotonic()
        self.inbox: queue.Queue[bytes] = queue.Queue(maxsize=8)
        self.stop = threading.Event()
        self.lock = threading.Lock()
        self.worker = threading.Thread(target=self._work, name="keyframes", daemon=True)
        self.worker.start()
        self.sub = session.declare_subscriber(f"{root}/keyframe/request", self._on_request)
        self.queryable = session.declare_queryable(f"{root}/vl/embed", self._on_embed)
        self.token = session.liveliness().declare_token(f"{root}/alive/keyframe_vl")

    # -------------------------------------------------------- keyframes

    def _on_request(self, sample: zenoh.Sample) -> None:
        try:
            self.inbox.put_nowait(sample.payload.to_bytes())
        except queue.Full:  # fifo: the newest is dropped and counted
            with self.lock:
                self.requests.dropped += 1

    def _work(self) -> None:
        while not self.stop.is_set():
            try:
                payload = self.inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                body = unpack(payload, "KeyframeRequest", self.robot)
                frame_index = body["frame_index"]
                if not isinstance(frame_index, int) or isinstance(frame_index, bool) or frame_index < 0:
                    raise BadRequest(f"KeyframeRequest.frame_index must be a non-negative integer, got {frame_index!r}")
            except (BadRequest, KeyError) as exc:
                with self.lock:
                    self.requests.rejected += 1
                print(f"keyframe/request refused: {exc}", file=sys.stderr, flush=True)
                continue
            with self.lock:
                self.requests.received += 1
            t0 = time.perf_counter()
            self._answer(frame_index, body)
            with self.lock:
                self.requests.processed += 1
                self.latencies = (self.latencies + [1000 * (time.perf_counter() - t0)])[-100:]

    def _answer(self, frame_index: int, body: dict) -> None:
        rgb = body.get("rgb")
        hw = tuple(rgb.shape[:2]) if isinstance(rgb, np.ndarray) and rgb.ndim == 3 else (0, 0)
        try:
            if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
                got = repr(rgb) if isinstance(rgb, Undecoded) else type(rgb).__name__
                raise ValueError(f"KeyframeRequest.rgb: expected a raw (H, W, 3) uint8 array, got {got}")
            masks, boxes, scores = segment(rgb, self.min_area_frac, self.max_masks)
        except Exception as exc:  # noqa: BLE001 - answer the tracker, keep serving
            self._failed(frame_index, hw, f"{type(exc).__name__}: {exc}")
            return
        self.masks_pub.put({"frame_index": frame_index, "masks": nd(masks, "bits"), "boxes": nd(boxes), "scores": nd(scores), "error": None})
        feats = np.stack([histogram(rgb[m]) for m in masks]) if len(masks) else np.zeros((0, BINS**3), np.float32)
        self.features_pub.put({"frame_index": frame_index, "features": nd(feats.astype(np.float32)), "model": MODEL, "error": None})
        with self.lock:
            self.published["keyframe_masks"] += 1
            self.published["keyframe_features"] += 1

    def _failed(self, frame_index: int, hw: tuple[int, int], why: str) -> None:
        print(f"keyframe {frame_index} failed: {why}", file=sys.stderr, flush=True)
        empty = np.zeros((0, *hw), bool)
        self.masks_pub.put({"frame_index": frame_index, "masks": nd(empty, "bits"), "boxes": nd(np.zeros((0, 4), np.float32)),
                            "scores": nd(np.zeros(0, np.float32)), "error": why})  # fmt: skip
        self.features_pub.put({"frame_index": frame_index, "features": nd(np.zeros((0, BINS**3), np.float32)), "model": MODEL, "error": why})
        with self.lock:
            self.failed += 1
            self.published["keyframe_masks"] += 1
            self.published["keyframe_features"] += 1

    # -------------------------------------------------------- embeddings

    def _on_embed(self, query: zenoh.Query) -> None:
        # A histogram or a hash takes microseconds: answering here does not stall the session.
        try:
            if query.payload is None:
                raise BadRequest("expected a EmbedRequest")
            body = unpack(query.payload.to_bytes(), "EmbedRequest", self.robot)
            text, image = body.get("text"), body.get("image")
            if (text is None) == (image is None):
                raise BadRequest("EmbedRequest: give exactly one of text or image")
            if text is not None and (not isinstance(text, str) or not text.strip()):
                raise BadRequest("EmbedRequest.text: a non-blank string")
            if image is not None and not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3):
                raise BadRequest(f"EmbedRequest.image: expected a raw (H, W, 3) uint8 array, got {image!r}"[:300])
        except (BadRequest, ValueError) as exc:
            with self.lock:
                self.embeds.rejected += 1
            prefix = "empty request" if query.payload is None else "bad request"
            query.reply_err(f"{prefix}: {exc}".encode())
            return
        with self.lock:
            self.embeds.received += 1
        if text is not None:
            vec, error = text_embedding(text), None
        elif image.size == 0:
            vec, error = None, "EmbedRequest.image: the image has no pixels"
        else:
            vec, error = histogram(image.reshape(-1, 3)), None
        reply = {"embedding": None if vec is None else nd(vec), "model": MODEL, "error": error}
        with self.lock:
            seq, self.replies = self.replies, self.replies + 1
        env = {"v": SCHEMA_VERSION, "type": "EmbedReply", "robot": self.robot, "seq": seq, "stamp": time.time(), "body": reply}
        query.reply(query.key_expr, msgpack.packb(env, use_bin_type=True))
        with self.lock:
            self.embeds.processed += 1

    # -------------------------------------------------------- status

    def report(self, state: str) -> None:
        with self.lock:
            lat = sorted(self.latencies)
            inputs = [{"name": c.name, "received": c.received, "processed": c.processed, "rejected": c.rejected,
                       "dropped": c.dropped, "queue_depth": self.inbox.qsize() if c is self.requests else 0}
                      for c in (self.requests, self.embeds)]  # fmt: skip
            body = {
                "service": "keyframe_vl", "pid": os.getpid(), "state": state, "uptime_s": time.monotonic() - self.started,
                "inputs": inputs, "published": dict(self.published), "errors": self.failed,
                "latency_p50_ms": lat[len(lat) // 2] if lat else None,
                "latency_p99_ms": lat[min(len(lat) - 1, int(0.99 * len(lat)))] if lat else None,
                "figures": {"processed": self.requests.processed, "failed": self.failed, "model": MODEL},
            }  # fmt: skip
        self.status_pub.put(body)

    def close(self) -> None:
        self.stop.set()
        self.sub.undeclare()
        self.queryable.undeclare()
        self.worker.join(timeout=5)
        self.report("stopped")
        self.token.undeclare()


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
    ap.add_argument("--min-area", type=float, default=0.004, help="smallest mask, as a share of the image")
    ap.add_argument("--max-masks", type=int, default=40, help="most masks a keyframe")
    args = ap.parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = open_session(args.connect)
    service = Service(session, args.robot, args.min_area, args.max_masks)
    print(f"external keyframe_vl up on {args.connect} for robot {args.robot} ({MODEL})", flush=True)
    try:
        while not stop.wait(1.0):
            service.report("running")
    finally:
        service.close()
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
