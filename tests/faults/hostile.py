"""Hostile payloads for every key a TrackGraph service subscribes to or answers, and the
harness that sends them into a running system while valid traffic flows.

Every payload is built so that it can never decode as the message its key expects (each kind
says why), so a service that rejects everything it should counts exactly what was sent:

* ``random``: random bytes (a msgpack parse error or a non-envelope);
* ``scalar``: valid msgpack that is not a map (an int, a string, a list, nil);
* ``envelope``: the right type name in a broken envelope (schema version, seq, stamp, body);
* ``bad_array``: the right type and field names, the first field a forbidden array
  (unlisted dtype, a shape that does not match its bytes, or a declared 10^10 bytes);
* ``extra_key``: the right type and fields plus a key the schema forbids;
* ``confused``: a valid message of another type;
* ``truncated``: a strict prefix of a valid or near-valid payload (msgpack maps are counted,
  so a prefix never parses);
* ``oversized``: a string over ``max_string_bytes``, or a multi-megabyte random blob.

Used by ``tests/faults/test_hostile_traffic.py`` (10^4 payloads) and ``benchmarks/fuzz.py``
(10^5).
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterator
from dataclasses import dataclass

import msgpack

from shared import SCHEMA_VERSION
from shared.codec import encode
from shared.messages.base import type_name
from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame
from shared.messages.graph import GraphDelta, SnapshotRequest
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures, TrackFeatures
from shared.messages.rpc import EmbedRequest, QueryRequest
from shared.procfs import status_mb
from shared.topics import Topics

SUBSCRIBED = {
    "frames": Frame,
    "end_of_sequence": EndOfSequence,
    "frame_ack": FrameAck,
    "keyframe_request": KeyframeRequest,
    "keyframe_masks": KeyframeMasks,
    "keyframe_features": MaskFeatures,
    "tracks_frame": TrackedFrame,
    "tracks_features": TrackFeatures,
    "tracks_end": EndOfSequence,
    "graph_delta": GraphDelta,
}
"""Topic attribute -> the message its subscribers expect."""

QUERYABLE = {"graph_snapshot": SnapshotRequest, "vl_embed": EmbedRequest, "query": QueryRequest}
"""Queryable topic attribute -> the request it expects."""

KINDS = ("random", "scalar", "envelope", "bad_array", "extra_key", "confused", "truncated", "oversized")
WEIGHTS = (14, 10, 14, 20, 14, 10, 16, 2)
"""Relative frequency of each kind: oversized payloads are megabytes each, so they are rare."""

MAX_STRING = 2**20
"""The codec's default ``max_string_bytes``; one byte more is refused."""


@dataclass(frozen=True)
class Payload:
    key: str
    """Topic attribute name (``Topics.<key>``)."""
    kind: str
    data: bytes


def _env(type_: str, body_: dict, **over) -> dict:
    env = {"v": SCHEMA_VERSION, "type": type_, "robot": "robot0", "seq": 1, "stamp": 1.0, "body": body_}
    env.update(over)
    return env


def _garbage(rng: random.Random, depth: int = 0):
    pick = rng.randrange(9 if depth < 3 else 6)
    if pick == 0:
        return rng.randrange(-(2**63), 2**63)
    if pick == 1:
        return rng.choice([math.nan, math.inf, -math.inf, -1.0, 1e308, 0.5])
    if pick == 2:
        return "".join(rng.choice("abc\u00e9\u4e2d\x00 ") for _ in range(rng.randrange(20)))
    if pick == 3:
        return rng.randbytes(rng.randrange(40))
    if pick == 4:
        return rng.choice([None, True, False])
    if pick == 5:
        return -rng.randrange(1, 1000)
    if pick == 6:
        return [_garbage(rng, depth + 1) for _ in range(rng.randrange(4))]
    if pick == 7:
        return {str(rng.randrange(100)): _garbage(rng, depth + 1) for _ in range(rng.randrange(3))}
    return {"__nd__": "raw", "dtype": "uint8", "shape": [rng.randrange(1, 9)], "data": rng.randbytes(rng.randrange(9))}


def _bad_array(rng: random.Random) -> dict:
    return rng.choice(
        [
            {"__nd__": "raw", "dtype": "object", "shape": [2], "data": b"\x00" * 16},
            {"__nd__": "raw", "dtype": "float32", "shape": [3, 3], "data": b"\x00" * 35},
            {"__nd__": "raw", "dtype": "uint8", "shape": [100_000, 100_000, 1], "data": b""},
            {"__nd__": "zlib", "dtype": "uint8", "shape": [4], "data": rng.randbytes(12)},
            {"__nd__": "jpeg", "dtype": "uint8", "shape": [8, 8, 3], "data": rng.randbytes(64)},
            {"__nd__": "bogus", "dtype": "uint8", "shape": [1], "data": b"\x00"},
            {"__nd__": "raw", "dtype": "uint8", "shape": [-4], "data": b""},
        ]
    )


def valid_samples() -> dict[str, bytes]:
    """One small valid payload per simple message type, for type confusion and truncation."""
    return {
        "FrameAck": encode(FrameAck(frame_index=3, service="fusion"), robot_id="robot0", seq=1, stamp=1.0),
        "EndOfSequence": encode(EndOfSequence(frames_published=1, frames_dropped=0, last_frame_index=0), robot_id="robot0", seq=1, stamp=1.0),
        "SnapshotRequest": encode(SnapshotRequest(), robot_id="robot0", seq=1, stamp=1.0),
    }


def _confused(rng: random.Random, expected: str, samples: dict[str, bytes]) -> bytes:
    return samples[rng.choice([name for name in samples if name != expected])]


def make_payload(rng: random.Random, key: str, expected: type, samples: dict[str, bytes]) -> Payload:
    """One hostile payload for ``key`` (whose subscribers expect ``expected``)."""
    want = type_name(expected)
    fields = list(expected.model_fields)
    kind = rng.choices(KINDS, WEIGHTS)[0]
    if kind == "random":
        data = rng.randbytes(rng.randrange(0, 512))
        if data[:1] and 0x80 <= data[0] <= 0x8F or data[:1] in (b"\xde", b"\xdf"):
            data = b"\xc1" + data  # never a map header: 0xc1 is msgpack's one unused byte
    elif kind == "scalar":
        data = msgpack.packb(rng.choice([0, -1, "frame", [1, 2, 3], None, 3.5, b"\x00\x01"]), use_bin_type=True)
    elif kind == "envelope":
        body = {f: _garbage(rng) for f in fields}
        broken = rng.choice([{"v": SCHEMA_VERSION + 1}, {"seq": -1}, {"stamp": math.nan}, {"body": [1]}, {"robot": 7}, {"v": "1"}])
        data = msgpack.packb(_env(want, body, **broken), use_bin_type=True)
    elif kind == "bad_array":
        body = {f: _garbage(rng) for f in fields}
        body[fields[0]] = _bad_array(rng)
        data = msgpack.packb(_env(want, body), use_bin_type=True)
    elif kind == "extra_key":
        body = {f: _garbage(rng) for f in fields}
        body["__unexpected__"] = 1
        data = msgpack.packb(_env(want, body), use_bin_type=True)
    elif kind == "confused":
        data = _confused(rng, want, samples)
    elif kind == "truncated":
        whole = rng.choice([_confused(rng, want, samples), samples.get(want) or msgpack.packb(_env(want, {}), use_bin_type=True)])
        data = whole[: rng.randrange(len(whole))]
    else:  # oversized
        if rng.random() < 0.5:
            body = {f: _garbage(rng) for f in fields}
            body[fields[0]] = "x" * (MAX_STRING + 1)
            data = msgpack.packb(_env(want, body), use_bin_type=True)
        else:
            data = b"\xc1" + rng.randbytes(rng.randrange(2, 6) * 2**20)
    return Payload(key, kind, data)


def payloads(n: int, seed: int = 0, keys: dict[str, type] | None = None) -> Iterator[Payload]:
    """``n`` hostile payloads spread over ``keys`` (default: every subscribed key), seeded."""
    rng = random.Random(seed)
    keys = keys or SUBSCRIBED
    names = sorted(keys)
    samples = valid_samples()
    for _ in range(n):
        key = rng.choice(names)
        yield make_payload(rng, key, keys[key], samples)


def key_expr(topics: Topics, key: str) -> str:
    return getattr(topics, key)


def rss_mb() -> float:
    """This process's resident memory (VmRSS), MB."""
    return status_mb("VmRSS") or 0.0
