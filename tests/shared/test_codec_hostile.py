"""Hostile payloads: shared.codec must raise CodecError, and nothing else, quickly and within
bounded memory, whatever arrives on the wire.

Raw payloads are built with msgpack.packb in the envelope shape documented at the top of
shared/codec.py::

    {"v": 1, "type": "Frame", "robot": "robot0", "seq": 12, "stamp": 1.7e9, "body": {...}}
    {"__nd__": "raw", "dtype": "uint8", "shape": [480, 640, 3], "data": b"..."}
"""

from __future__ import annotations

import functools
import io
import math
import struct
import time
import tracemalloc
import zlib
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from shared import SCHEMA_VERSION
from shared.codec import CodecError, decode, decode_raw, encode
from shared.config import CodecConfig
from shared.geometry import Intrinsics
from shared.messages import (
    EmbedReply,
    Envelope,
    Frame,
    KeyframeMasks,
    TrackedFrame,
    TrackFeatures,
    TrackObservation,
)

FAST = settings(max_examples=25, deadline=None, derandomize=True)

MAX_SECONDS = 1.0
MAX_PEAK_BYTES = 50 * 2**20

COMPRESSED = CodecConfig(rgb="jpeg", depth="png", masks="rle", labels="zlib")

# ---------------------------------------------------------------- builders


def make_frame(h: int = 6, w: int = 5, seed: int = 0) -> Frame:
    rng = np.random.default_rng(seed)
    return Frame(
        frame_index=3,
        time_s=0.25,
        rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth=rng.integers(0, 65536, (h, w), dtype=np.uint16),
        depth_scale=1000.0,
        intrinsics=Intrinsics(fx=500.0, fy=500.0, cx=w / 2, cy=h / 2, width=w, height=h),
        T_world_cam=np.eye(4),
    )


def make_tracked(h: int = 6, w: int = 5) -> TrackedFrame:
    ids = np.zeros((h, w), dtype=np.int32)
    ids[: h // 2] = 1
    return TrackedFrame(
        frame=make_frame(h, w),
        track_ids=ids,
        tracks=[TrackObservation(track_id=0, keyframe=True, frames_since_keyframe=0),
                TrackObservation(track_id=1, keyframe=False, frames_since_keyframe=3)],
        confidence=np.full((h, w), 200, np.uint8),
    )


def make_masks(n: int = 2, h: int = 6, w: int = 5) -> KeyframeMasks:
    rng = np.random.default_rng(1)
    return KeyframeMasks(
        frame_index=24,
        masks=rng.random((n, h, w)) > 0.5,
        boxes=rng.random((n, 4)).astype(np.float32),
        scores=rng.random(n).astype(np.float32),
    )


def enc(msg: Any, cfg: CodecConfig | None = None) -> bytes:
    return encode(msg, robot_id="robot0", seq=12, stamp=1.7e9, cfg=cfg)


def wire_body(msg: Any, cfg: CodecConfig | None = None) -> dict:
    """The body of a valid payload, undecoded (arrays still as __nd__ maps)."""
    return msgpack.unpackb(enc(msg, cfg), raw=False)["body"]


def envelope(body: Any, type_: str = "Frame", **overrides: Any) -> bytes:
    env = {"v": SCHEMA_VERSION, "type": type_, "robot": "robot0", "seq": 0, "stamp": 0.0, "body": body}
    env.update(overrides)
    return msgpack.packb(env, use_bin_type=True)


def nd(encoding: Any, dtype: Any, shape: Any, data: Any) -> dict:
    return {"__nd__": encoding, "dtype": dtype, "shape": shape, "data": data}


def frame_with(**fields: Any) -> bytes:
    """A valid Frame payload with some body fields replaced."""
    body = wire_body(make_frame())
    body.update(fields)
    return envelope(body)


def jpeg_bytes(h: int, w: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), 128, dtype=np.uint8)).save(buf, format="JPEG")
    return buf.getvalue()


def png16_bytes(h: int, w: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.zeros((h, w), dtype=np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def png_declaring(width: int, height: int) -> bytes:
    """A 1x1 16-bit PNG whose IHDR is rewritten (with a valid CRC) to claim width x height."""
    data = bytearray(png16_bytes(1, 1))
    assert data[12:16] == b"IHDR"
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


@functools.lru_cache(maxsize=1)
def zlib_bomb() -> bytes:
    """About 64 KB of zlib data that inflates to 64 MiB of zeros."""
    c = zlib.compressobj(9)
    chunk = bytes(2**20)
    return b"".join([*(c.compress(chunk) for _ in range(64)), c.flush()])


def refused(payload: Any, expected: type = Frame, cfg: CodecConfig | None = None) -> CodecError:
    """Decode must raise CodecError, in under MAX_SECONDS and MAX_PEAK_BYTES of Python heap."""
    tracemalloc.start()
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    try:
        with pytest.raises(CodecError) as info:
            decode(payload, expected, cfg)
    finally:
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert elapsed < MAX_SECONDS, f"took {elapsed:.2f} s"
    assert peak < MAX_PEAK_BYTES, f"peak {peak / 2**20:.1f} MiB"
    return info.value


# ---------------------------------------------------------------- sanity of the builders


def test_builders_make_valid_payloads() -> None:
    """The hostile cases below are mutations of these; they must decode when left alone."""
    assert isinstance(decode(frame_with(), Frame).body, Frame)
    for msg in (make_frame(), make_tracked(), make_masks()):
        for cfg in (None, COMPRESSED):
            assert type(decode(enc(msg, cfg), type(msg), cfg).body) is type(msg)
    assert decode(envelope(wire_body(make_frame()), seq=2**64 - 1), Frame).seq == 2**64 - 1


# ---------------------------------------------------------------- (a) truncation


@pytest.mark.parametrize("cfg", [None, COMPRESSED], ids=["default", "compressed"])
def test_every_truncation_of_a_frame_is_refused(cfg: CodecConfig | None) -> None:
    payload = enc(make_frame(), cfg)
    assert decode(payload, Frame, cfg).body.frame_index == 3
    for n in range(len(payload)):
        with pytest.raises(CodecError):
            decode(payload[:n], Frame, cfg)


def test_trailing_bytes_are_refused() -> None:
    payload = enc(make_frame())
    for extra in (b"\x00", b"\xc0", payload):
        with pytest.raises(CodecError):
            decode(payload + extra, Frame)


# ---------------------------------------------------------------- (b) fuzzing


def decodes_or_refuses(payload: bytes, expected: type, cfg: CodecConfig | None = None) -> None:
    """CodecError, or a valid message that re-encodes and decodes to the same message."""
    try:
        env = decode(payload, expected, cfg)
    except CodecError:
        return
    assert isinstance(env, Envelope)
    assert type(env.body) is expected
    again = decode(encode(env.body, robot_id=env.robot_id, seq=env.seq, stamp=env.stamp), expected)
    assert again.body.model_dump_json() == env.body.model_dump_json()


VALID_PAYLOADS: list[tuple[type, CodecConfig | None, bytes]] = [
    (Frame, None, enc(make_frame())),
    (Frame, COMPRESSED, enc(make_frame(), COMPRESSED)),
    (TrackedFrame, COMPRESSED, enc(make_tracked(), COMPRESSED)),
    (KeyframeMasks, COMPRESSED, enc(make_masks(), COMPRESSED)),
    (KeyframeMasks, None, enc(make_masks())),
]


@FAST
@given(data=st.binary(max_size=300))
def test_random_bytes(data: bytes) -> None:
    decodes_or_refuses(data, Frame)
    try:
        env = decode_raw(data)
    except CodecError:
        return
    assert isinstance(env, dict) and isinstance(env["body"], dict)


@pytest.mark.parametrize("index", range(len(VALID_PAYLOADS)))
@FAST
@given(data=st.data())
def test_byte_flips(index: int, data: st.DataObject) -> None:
    expected, cfg, payload = VALID_PAYLOADS[index]
    buf = bytearray(payload)
    flips = data.draw(
        st.lists(st.tuples(st.integers(0, len(buf) - 1), st.integers(0, 255)), min_size=1, max_size=8)
    )
    for pos, byte in flips:
        buf[pos] = byte
    decodes_or_refuses(bytes(buf), expected, cfg)


@FAST
@given(data=st.data())
def test_byte_flips_in_a_header(data: st.DataObject) -> None:
    """Flips concentrated in the first bytes hit the envelope and array headers."""
    _, cfg, payload = VALID_PAYLOADS[1]
    buf = bytearray(payload)
    for pos, byte in data.draw(st.lists(st.tuples(st.integers(0, 80), st.integers(0, 255)), min_size=1, max_size=4)):
        buf[pos] = byte
    decodes_or_refuses(bytes(buf), Frame, cfg)


WIRE_SCALARS = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=16)
)

ND_MAPS = st.fixed_dictionaries(
    {
        "__nd__": st.sampled_from(["raw", "zlib", "jpeg", "png", "bits", "rle", "gzip"]) | WIRE_SCALARS,
        "dtype": st.sampled_from(["bool", "uint8", "uint16", "int32", "float32", "float64", "object", ">f8"])
        | WIRE_SCALARS,
        "shape": st.lists(st.integers(-2, 2**40) | WIRE_SCALARS, max_size=5) | WIRE_SCALARS,
        "data": st.binary(max_size=64) | WIRE_SCALARS,
    }
)

WIRE_VALUES = st.recursive(
    WIRE_SCALARS | ND_MAPS,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4),
    max_leaves=12,
)


@FAST
@given(
    body=st.dictionaries(
        st.sampled_from(["frame_index", "rgb", "depth", "depth_scale", "intrinsics", "T_world_cam", "x"]),
        WIRE_VALUES,
    ),
    seq=WIRE_SCALARS,
    stamp=WIRE_SCALARS,
)
def test_structured_garbage(body: dict, seq: Any, stamp: Any) -> None:
    decodes_or_refuses(envelope(body, seq=seq, stamp=stamp), Frame)


@FAST
@given(field=st.sampled_from(["rgb", "depth", "T_world_cam", "depth_scale", "intrinsics"]), value=WIRE_VALUES)
def test_one_field_replaced_by_garbage(field: str, value: Any) -> None:
    decodes_or_refuses(frame_with(**{field: value}), Frame)


# ---------------------------------------------------------------- (c) refused arrays and envelopes

HUGE = [100_000, 100_000, 10]
GOOD_RGB = {"dtype": "uint8", "shape": [6, 5, 3]}


def _rle(runs: list[int]) -> bytes:
    return np.asarray(runs, dtype="<u4").tobytes()


ARRAY_CASES: dict[str, Callable[[], dict]] = {
    # sizes declared far beyond the limits
    "raw-huge-float64": lambda: nd("raw", "float64", HUGE, b"\x00" * 8),
    "zlib-huge": lambda: nd("zlib", "float64", HUGE, zlib.compress(b"\x00" * 64)),
    "bits-huge": lambda: nd("bits", "bool", HUGE, b"\x00"),
    "rle-huge": lambda: nd("rle", "bool", HUGE, _rle([100_000 * 100_000 * 10 % 2**32])),
    "png-huge-declared": lambda: nd("png", "uint16", [100_000, 100_000], png_declaring(100_000, 100_000)),
    "jpeg-huge-declared": lambda: nd("jpeg", "uint8", [100_000, 100_000, 3], jpeg_bytes(4, 4)),
    "shape-overflows-uint64": lambda: nd("raw", "uint8", [2**64 - 1, 2**64 - 1], b""),
    "zero-count-absurd-dim": lambda: nd("raw", "uint8", [0, 2**63], b""),
    # raw / zlib data that does not match the declared shape
    "raw-short": lambda: nd("raw", "uint8", [6, 5, 3], b"\x00" * 89),
    "raw-long": lambda: nd("raw", "uint8", [6, 5, 3], b"\x00" * 91),
    "zlib-bomb": lambda: nd("zlib", "uint8", [1024], zlib_bomb()),
    "zlib-bomb-1MiB-declared": lambda: nd("zlib", "uint8", [2**20], zlib_bomb()),
    "zlib-short": lambda: nd("zlib", "uint8", [6, 5, 3], zlib.compress(b"\x00" * 89)),
    "zlib-truncated": lambda: nd("zlib", "uint8", [6, 5, 3], zlib.compress(b"\x00" * 90)[:-4]),
    "zlib-garbage": lambda: nd("zlib", "uint8", [6, 5, 3], b"not zlib at all"),
    # images whose header disagrees with the declaration, or lies about its size
    "jpeg-smaller-than-declared": lambda: nd("jpeg", "uint8", [6, 5, 3], jpeg_bytes(4, 4)),
    "jpeg-larger-than-declared": lambda: nd("jpeg", "uint8", [6, 5, 3], jpeg_bytes(16, 16)),
    "jpeg-transposed": lambda: nd("jpeg", "uint8", [6, 5, 3], jpeg_bytes(5, 6)),
    "jpeg-declares-uint16": lambda: nd("jpeg", "uint16", [6, 5, 3], jpeg_bytes(6, 5)),
    "jpeg-declares-2d": lambda: nd("jpeg", "uint8", [6, 5], jpeg_bytes(6, 5)),
    "jpeg-truncated": lambda: nd("jpeg", "uint8", [6, 5, 3], jpeg_bytes(6, 5)[:40]),
    "jpeg-is-a-png": lambda: nd("jpeg", "uint8", [6, 5, 3], png16_bytes(6, 5)),
    "png-header-5000x5000": lambda: nd("png", "uint16", [5000, 5000], png_declaring(5000, 5000)),
    "png-header-huge-declared-small": lambda: nd("png", "uint16", [6, 5], png_declaring(60_000, 60_000)),
    "png-header-differs": lambda: nd("png", "uint16", [6, 5], png16_bytes(5, 6)),
    "png-8bit": lambda: nd("png", "uint16", [6, 5], _png8(6, 5)),
    "png-declares-uint8": lambda: nd("png", "uint8", [6, 5], png16_bytes(6, 5)),
    "png-garbage": lambda: nd("png", "uint16", [6, 5], b"\x89PNG\r\n\x1a\n garbage"),
    # zstd2d depth: the declaration bounds what is inflated, whatever the zstd frame claims
    "zstd2d-huge-declared": lambda: nd("zstd2d", "uint16", [100_000, 100_000], _zstd(b"\x00" * 64)),
    "zstd2d-bomb": lambda: nd("zstd2d", "uint16", [6, 5], _zstd(b"\x00" * 2**24)),
    "zstd2d-short": lambda: nd("zstd2d", "uint16", [6, 5], _zstd(b"\x00" * 59)),
    "zstd2d-long": lambda: nd("zstd2d", "uint16", [6, 5], _zstd(b"\x00" * 61)),
    "zstd2d-truncated": lambda: nd("zstd2d", "uint16", [6, 5], _zstd(bytes(range(60)))[:-3]),
    "zstd2d-garbage": lambda: nd("zstd2d", "uint16", [6, 5], b"not zstd at all"),
    "zstd2d-declares-uint8": lambda: nd("zstd2d", "uint8", [6, 5], _zstd(b"\x00" * 30)),
    "zstd2d-declares-3d": lambda: nd("zstd2d", "uint16", [6, 5, 1], _zstd(b"\x00" * 60)),
    # masks
    "rle-sum-short": lambda: nd("rle", "bool", [10], _rle([3, 4])),
    "rle-sum-long": lambda: nd("rle", "bool", [10], _rle([3, 4, 5])),
    "rle-sum-wraps-uint32": lambda: nd("rle", "bool", [10], _rle([2**32 - 1, 2**32 - 1, 12])),
    "rle-too-many-runs": lambda: nd("rle", "bool", [10], _rle([0] * 11 + [10])),
    "rle-ragged-bytes": lambda: nd("rle", "bool", [10], b"\x0a\x00\x00\x00\x00"),
    "rle-not-bool": lambda: nd("rle", "uint8", [10], _rle([10])),
    "bits-short": lambda: nd("bits", "bool", [10], b"\xff"),
    "bits-long": lambda: nd("bits", "bool", [10], b"\xff\xff\xff"),
    "bits-not-bool": lambda: nd("bits", "uint8", [10], b"\xff\xff"),
    # dtypes that must never cross the wire
    **{
        f"dtype-{d!r}": (lambda d=d: nd("raw", d, [1], b"\x00" * 8))
        for d in ["object", ">f8", "<f8", "U10", "V8", "float128", "complex128", "M8[ns]", "O", "f8", "", 5, None]
    },
    "dtype-bytes": lambda: nd("raw", b"float64", [1], b"\x00" * 8),
    # shapes
    **{
        f"shape-{s!r}": (lambda s=s: nd("raw", "uint8", s, b"\x00"))
        for s in [[-1], [True], [1.0], [1.5], ["1"], [None], [1, 1, 1, 1, 1], "1", 1, None, {"a": 1}, [[1]]]
    },
    # the array map itself
    "data-is-str": lambda: nd("raw", "uint8", [3], "abc"),
    "data-is-list": lambda: nd("raw", "uint8", [3], [1, 2, 3]),
    "data-is-none": lambda: nd("raw", "uint8", [0], None),
    "extra-key": lambda: {**nd("raw", "uint8", [1], b"\x00"), "order": "F"},
    "missing-data": lambda: {"__nd__": "raw", "dtype": "uint8", "shape": [1]},
    "only-marker": lambda: {"__nd__": "raw"},
    "unknown-encoding": lambda: nd("gzip", "uint8", [1], b"\x00"),
    "encoding-none": lambda: nd(None, "uint8", [1], b"\x00"),
}


def _zstd(raw: bytes) -> bytes:
    import zstandard

    return zstandard.ZstdCompressor(level=1).compress(raw)


def _png8(h: int, w: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.zeros((h, w), dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


OVER_LIMIT = {"raw-huge-float64", "zlib-huge", "bits-huge", "rle-huge", "png-huge-declared", "zstd2d-huge-declared",
              "jpeg-huge-declared", "shape-overflows-uint64"}


def reason_word(case: str) -> str:
    """A word the refusal must contain, so that a check that went missing is not masked by
    a later, accidental failure (numpy's reshape, Pillow) that also ends in CodecError."""
    if case in OVER_LIMIT:
        return "max_array_bytes"
    if case == "zero-count-absurd-dim":
        return ""
    if case.startswith("raw-"):
        return "needs 90 bytes"
    if case in ("extra-key", "missing-data", "only-marker"):
        return "array map has keys"
    if case.startswith(("unknown-encoding", "encoding-")):
        return "encoding"
    if case == "png-header-huge-declared-small":
        return "png"
    return case.split("-")[0]


@pytest.mark.parametrize("case", sorted(ARRAY_CASES, key=str))
def test_hostile_array_is_refused(case: str) -> None:
    array = ARRAY_CASES[case]()
    payload = frame_with(rgb=array)
    assert reason_word(case) in str(refused(payload))
    # also refused wherever it sits: deep inside a list in an unrelated message
    refused(envelope({"embedding": [[array]]}, "EmbedReply"), EmbedReply)


def test_huge_declared_shape_is_refused_before_allocation() -> None:
    """The 800 GB declaration is refused from the header alone, naming the limit."""
    err = refused(frame_with(rgb=nd("raw", "float64", HUGE, b"\x00" * 8)))
    assert "max_array_bytes" in str(err)
    err = refused(frame_with(rgb=nd("zlib", "float64", HUGE, zlib.compress(b"\x00" * 8))))
    assert "max_array_bytes" in str(err)


def test_zlib_bomb_is_not_inflated() -> None:
    assert len(zlib_bomb()) < 2**17  # the bomb itself is small...
    err = refused(frame_with(rgb=nd("zlib", "uint8", [1024], zlib_bomb())))
    assert "zlib" in str(err)


def test_png_header_over_max_image_pixels() -> None:
    """A 50 MB declaration is within max_array_bytes, but the PNG's 25 Mpx exceed max_image_pixels."""
    cfg = CodecConfig()
    assert 5000 * 5000 * 2 <= cfg.max_array_bytes and 5000 * 5000 > cfg.max_image_pixels
    err = refused(frame_with(depth=nd("png", "uint16", [5000, 5000], png_declaring(5000, 5000))))
    assert "max_image_pixels" in str(err)


def test_limits_follow_the_config() -> None:
    """A smaller CodecConfig refuses what the default accepts."""
    payload = enc(make_frame())
    decode(payload, Frame)
    refused(payload, cfg=CodecConfig(max_payload_bytes=len(payload) - 1))
    refused(payload, cfg=CodecConfig(max_array_bytes=6 * 5 * 3 - 1))
    refused(payload, cfg=CodecConfig(max_ndim=2))
    refused(payload, cfg=CodecConfig(max_items=4))
    refused(payload, cfg=CodecConfig(max_string_bytes=4))
    # max_items bounds every list and map, with TrackFeatures' 7 keys as the largest map here
    at_limit = enc(TrackFeatures(frame_index=0, tracks=[], retired=list(range(7))))
    assert decode(at_limit, TrackFeatures, CodecConfig(max_items=7)).body.retired == list(range(7))
    over = enc(TrackFeatures(frame_index=0, tracks=[], retired=list(range(8))))
    assert "max_array_len" in str(refused(over, TrackFeatures, CodecConfig(max_items=7)))
    assert "max_map_len" in str(refused(at_limit, TrackFeatures, CodecConfig(max_items=6)))
    jpeg = enc(make_frame(), COMPRESSED)
    decode(jpeg, Frame, COMPRESSED)
    refused(jpeg, cfg=CodecConfig(max_image_pixels=6 * 5 - 1))


def test_many_small_arrays_cannot_amplify_memory() -> None:
    limit = 2**20
    cfg = CodecConfig(max_array_bytes=limit)
    array = nd("rle", "bool", [limit], _rle([limit]))
    payload = envelope({"model": "m", "embedding": [array] * 16}, "EmbedReply")
    assert len(payload) < 1024
    tracemalloc.start()
    try:
        with pytest.raises(CodecError):
            decode(payload, EmbedReply, cfg)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 * limit, f"a {len(payload)}-byte payload made the decoder allocate {peak / 2**20:.0f} MiB"


def _with(**overrides: Any) -> Callable[[], bytes]:
    def build() -> bytes:
        env = {"v": SCHEMA_VERSION, "type": "Frame", "robot": "r", "seq": 0, "stamp": 0.0,
               "body": wire_body(make_frame())}
        env.update(overrides)
        return msgpack.packb(env, use_bin_type=True)

    return build


def _without(key: str) -> Callable[[], bytes]:
    def build() -> bytes:
        env = {"v": SCHEMA_VERSION, "type": "Frame", "robot": "r", "seq": 0, "stamp": 0.0,
               "body": wire_body(make_frame())}
        del env[key]
        return msgpack.packb(env, use_bin_type=True)

    return build


ENVELOPE_CASES: dict[str, Callable[[], Any]] = {
    "schema-version-2": _with(v=SCHEMA_VERSION + 1),
    "schema-version-0": _with(v=0),
    "schema-version-str": _with(v=str(SCHEMA_VERSION)),
    "schema-version-none": _with(v=None),
    "type-other-message": lambda: enc(EmbedReply(model="m")),
    "type-unknown": _with(type="Bogus"),
    "type-not-str": _with(type=5),
    "robot-not-str": _with(robot=5),
    "robot-none": _with(robot=None),
    "seq-negative": _with(seq=-1),
    "seq-bool": _with(seq=True),
    "seq-float": _with(seq=1.0),
    "seq-str": _with(seq="1"),
    "stamp-nan": _with(stamp=math.nan),
    "stamp-inf": _with(stamp=math.inf),
    "stamp-str": _with(stamp="now"),
    "stamp-none": _with(stamp=None),
    "body-list": _with(body=[]),
    "body-none": _with(body=None),
    "body-str": _with(body="Frame"),
    "body-is-an-array": _with(body=nd("raw", "uint8", [1], b"\x00")),
    **{f"missing-{k}": _without(k) for k in ["v", "type", "robot", "seq", "stamp", "body"]},
    "envelope-list": lambda: msgpack.packb([SCHEMA_VERSION, "Frame", "r", 0, 0.0, {}]),
    "envelope-int": lambda: msgpack.packb(1),
    "envelope-str": lambda: msgpack.packb("Frame"),
    "envelope-nil": lambda: msgpack.packb(None),
    "envelope-bin": lambda: msgpack.packb(b"\x00" * 16, use_bin_type=True),
    "envelope-is-an-array": lambda: msgpack.packb(nd("raw", "uint8", [1], b"\x00")),
    "empty-payload": lambda: b"",
    "int-map-key": lambda: msgpack.packb({1: 2, "v": 1}),
    "ext-type": lambda: msgpack.packb({"v": msgpack.ExtType(1, b"x")}),
    "depth-bomb-lists": lambda: b"\x91" * 100_000 + b"\xc0",
    "depth-bomb-maps": lambda: b"\x81\xa1a" * 100_000 + b"\xc0",
    "depth-bomb-in-body": lambda: envelope(None).replace(b"\xc0", b"\x91" * 100_000 + b"\xc0"),
    "array32-claims-4G-items": lambda: b"\xdd\xff\xff\xff\xff",
    "map32-claims-4G-items": lambda: b"\xdf\xff\xff\xff\xff",
    "bin32-claims-4GB": lambda: b"\xc6\xff\xff\xff\xff" + b"\x00" * 16,
    "str32-claims-4GB": lambda: b"\xdb\xff\xff\xff\xff" + b"a" * 16,
    "array-of-1M-nils": lambda: b"\xdd\x00\x0f\x42\x41" + b"\xc0" * 1_000_001,
}


@pytest.mark.parametrize("case", sorted(ENVELOPE_CASES))
def test_hostile_envelope_is_refused(case: str) -> None:
    refused(ENVELOPE_CASES[case]())


@pytest.mark.parametrize("payload", ["a str", None, 12, [b"\x80"], {"v": 1}], ids=repr)
def test_payload_that_is_not_bytes(payload: Any) -> None:
    refused(payload)
    with pytest.raises(CodecError):
        decode_raw(payload)


def test_bytes_like_payloads_are_accepted() -> None:
    payload = enc(make_frame())
    for p in (bytearray(payload), memoryview(payload)):
        assert decode(p, Frame).body.frame_index == 3


def test_wrong_expected_type_names_both() -> None:
    err = refused(enc(make_frame()), EmbedReply)
    assert "EmbedReply" in str(err) and "Frame" in str(err)


def test_schema_version_error_names_versions() -> None:
    err = refused(envelope(wire_body(make_frame()), v=SCHEMA_VERSION + 1))
    assert str(SCHEMA_VERSION + 1) in str(err)


# ---------------------------------------------------------------- (d) type-confused bodies


def _frame_body(**fields: Any) -> dict:
    body = wire_body(make_frame())
    body.update(fields)
    return body


def _pose(T: np.ndarray) -> dict:
    return nd("raw", "float64", [4, 4], np.ascontiguousarray(T, dtype="<f8").tobytes())


def _nan_pose() -> dict:
    T = np.eye(4)
    T[0, 3] = np.nan
    return _pose(T)


def _segment(**fields: Any) -> dict:
    seg = {
        "id": 1, "centroid": [0.0, 0.0, 0.0], "bbox_min": [0.0, 0.0, 0.0], "bbox_max": [1.0, 1.0, 1.0],
        "tracks": [1, 2], "dino": nd("raw", "float32", [2], b"\x00" * 8),
        "gallery": nd("raw", "float32", [1, 2], b"\x00" * 8), "gallery_tracks": [1], "active": True,
    }
    seg.update(fields)
    return seg


def _masks_body(**fields: Any) -> dict:
    body = wire_body(make_masks())
    body.update(fields)
    return body


CONFUSED: dict[str, tuple[Callable[[], bytes], type, tuple[str, ...]]] = {
    "rgb-is-a-str": (lambda: frame_with(rgb="not an image"), Frame, ("Frame", "rgb")),
    "rgb-is-a-map": (lambda: frame_with(rgb={"a": 1}), Frame, ("Frame", "rgb")),
    "rgb-is-float32": (
        lambda: frame_with(rgb=nd("raw", "float32", [6, 5, 3], b"\x00" * 360)), Frame, ("Frame", "rgb")),
    "rgb-2d": (lambda: frame_with(rgb=nd("raw", "uint8", [6, 5], b"\x00" * 30)), Frame, ("Frame", "rgb")),
    "rgb-list-out-of-uint8-range": (lambda: frame_with(rgb=[[[300, 0, 0]]]), Frame, ("Frame", "rgb")),
    "rgb-list-negative": (lambda: frame_with(rgb=[[[-1, 0, 0]]]), Frame, ("Frame", "rgb")),
    "rgb-list-beyond-int64": (lambda: frame_with(rgb=[[[2**64 - 1, 0, 0]]]), Frame, ("Frame", "rgb")),
    "pose-nan": (lambda: frame_with(T_world_cam=_nan_pose()), Frame, ("Frame", "T_world_cam")),
    "pose-scaled": (lambda: frame_with(T_world_cam=_pose(2 * np.eye(4))), Frame, ("Frame", "T_world_cam")),
    "pose-reflection": (
        lambda: frame_with(T_world_cam=_pose(np.diag([-1.0, 1.0, 1.0, 1.0]))), Frame, ("Frame", "T_world_cam")),
    "pose-bad-last-row": (
        lambda: frame_with(T_world_cam=_pose(np.eye(4) + np.eye(4, k=-3))), Frame, ("Frame", "T_world_cam")),
    "pose-3x4": (
        lambda: frame_with(T_world_cam=nd("raw", "float64", [3, 4], b"\x00" * 96)), Frame, ("Frame", "T_world_cam")),
    "pose-float32": (
        lambda: frame_with(T_world_cam=nd("raw", "float32", [4, 4], np.eye(4, dtype="<f4").tobytes())),
        Frame, ("Frame", "T_world_cam")),
    "pose-str": (lambda: frame_with(T_world_cam="identity"), Frame, ("Frame", "T_world_cam")),
    "depth-shape-differs": (
        lambda: frame_with(depth=nd("raw", "uint16", [5, 6], b"\x00" * 60)), Frame, ("Frame", "depth")),
    "ground-truth-on-the-wire": (
        lambda: frame_with(instances=nd("raw", "int32", [5, 6], b"\x00" * 120)), Frame, ("Frame", "instances")),
    "intrinsics-size-differs": (
        lambda: frame_with(intrinsics={"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "width": 6, "height": 5}),
        Frame, ("Frame", "intrinsics")),
    "intrinsics-nan-focal": (
        lambda: frame_with(intrinsics={"fx": math.nan, "fy": 1.0, "cx": 0.0, "cy": 0.0, "width": 5, "height": 6}),
        Frame, ("Frame", "intrinsics.fx")),
    "intrinsics-extra-key": (
        lambda: frame_with(intrinsics={"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "width": 5, "height": 6, "k1": 0.1}),
        Frame, ("Frame", "intrinsics.k1")),
    "depth-scale-zero": (lambda: frame_with(depth_scale=0.0), Frame, ("Frame", "depth_scale")),
    "depth-scale-str": (lambda: frame_with(depth_scale="mm"), Frame, ("Frame", "depth_scale")),
    "frame-index-negative": (lambda: frame_with(frame_index=-1), Frame, ("Frame", "frame_index")),
    "unknown-field": (lambda: frame_with(bogus=1), Frame, ("Frame", "bogus")),
    "missing-field": (
        lambda: envelope({k: v for k, v in wire_body(make_frame()).items() if k != "depth_scale"}),
        Frame, ("Frame", "depth_scale")),
    "tracked-frame-nan-pose": (
        lambda: envelope({**wire_body(make_tracked()), "frame": _frame_body(T_world_cam=_nan_pose())}, "TrackedFrame"),
        TrackedFrame, ("TrackedFrame", "frame.T_world_cam")),
    "tracked-frame-ids-shape": (
        lambda: envelope({**wire_body(make_tracked()), "track_ids": nd("raw", "int32", [2, 2], b"\x00" * 16)},
                         "TrackedFrame"),
        TrackedFrame, ("TrackedFrame", "track_ids")),
    "tracked-frame-confidence-shape": (
        lambda: envelope({**wire_body(make_tracked()), "confidence": nd("raw", "uint8", [2, 2], b"\x00" * 4)},
                         "TrackedFrame"),
        TrackedFrame, ("TrackedFrame", "confidence")),
    "masks-boxes-count": (
        lambda: envelope(_masks_body(boxes=nd("raw", "float32", [1, 4], b"\x00" * 16)), "KeyframeMasks"),
        KeyframeMasks, ("KeyframeMasks", "boxes")),
    "masks-scores-count": (
        lambda: envelope(_masks_body(scores=nd("raw", "float32", [3], b"\x00" * 12)), "KeyframeMasks"),
        KeyframeMasks, ("KeyframeMasks", "scores")),
    "masks-nan-box": (
        lambda: envelope(_masks_body(boxes=nd("raw", "float32", [2, 4], np.full(8, np.nan, "<f4").tobytes())),
                         "KeyframeMasks"),
        KeyframeMasks, ("KeyframeMasks", "boxes")),
    "masks-not-bool": (
        lambda: envelope(_masks_body(masks=nd("raw", "uint8", [2, 6, 5], b"\x01" * 60)), "KeyframeMasks"),
        KeyframeMasks, ("KeyframeMasks", "masks")),
    "segment-gallery-rows": (
        lambda: envelope({"graph_seq": 0, "frame_index": 0, "segments": [_segment(gallery_tracks=[1, 2])]},
                         "GraphDelta"),
        None, ("GraphDelta", "segments.0", "gallery")),
    "segment-centroid-nan": (
        lambda: envelope({"graph_seq": 0, "frame_index": 0, "segments": [_segment(centroid=[0.0, math.nan, 0.0])]},
                         "GraphDelta"),
        None, ("GraphDelta", "segments.0.centroid")),
    "segment-bbox-inverted": (
        lambda: envelope({"graph_seq": 0, "frame_index": 0, "segments": [_segment(bbox_min=[2.0, 0.0, 0.0])]},
                         "GraphSnapshot"),
        None, ("GraphSnapshot", "segments.0", "bbox_min")),
    "mesh-face-out-of-range": (
        lambda: envelope({"graph_seq": 0, "frame_index": 0, "mesh": {
            "vertices": nd("raw", "float32", [1, 3], b"\x00" * 12), "colors": nd("raw", "uint8", [1, 3], b"\x00" * 3),
            "faces": nd("raw", "int32", [1, 3], np.array([0, 0, 1], "<i4").tobytes()),
            "segment_ids": nd("raw", "int32", [1], b"\x00" * 4)}}, "GraphSnapshot"),
        None, ("GraphSnapshot", "mesh", "faces")),
    "embed-text-and-image": (
        lambda: envelope({"text": "chair", "image": nd("raw", "uint8", [1, 1, 3], b"\x00" * 3)}, "EmbedRequest"),
        None, ("EmbedRequest", "text", "image")),
    "query-center-without-radius": (
        lambda: envelope({"text": "chair", "center": [0.0, 0.0, 0.0]}, "QueryRequest"),
        None, ("QueryRequest", "center", "radius")),
    "query-gallery-literal": (
        lambda: envelope({"text": "chair", "gallery": "median"}, "QueryRequest"),
        None, ("QueryRequest", "gallery")),
    "track-feature-clip-count": (
        lambda: envelope({"frame_index": 0, "tracks": [
            {"track_id": 1, "dino": nd("raw", "float32", [1], b"\x00" * 4), "clip_count": 2}]}, "TrackFeatures"),
        None, ("TrackFeatures", "tracks.0", "clip")),
    "embedding-list-of-str": (
        lambda: envelope({"embedding": ["a", "b"]}, "EmbedReply"), EmbedReply, ("EmbedReply", "embedding")),
}


@pytest.mark.parametrize("case", sorted(CONFUSED))
def test_type_confused_body_names_message_and_field(case: str) -> None:
    from shared.messages import REGISTRY

    build, expected, words = CONFUSED[case]
    payload = build()
    expected = expected or REGISTRY[msgpack.unpackb(payload)["type"]]
    err = refused(payload, expected)
    text = str(err)
    assert text.startswith(f"{expected.__name__}."), text
    for word in words:
        assert word in text, f"{word!r} not in {text!r}"


def test_zstd2d_bomb_is_not_inflated_past_its_declaration() -> None:
    """A 16 MiB zstd frame declared as 6x5 depth: refused, and the reader never holds more
    than the declared 60 bytes and one more."""
    bomb = _zstd(b"\x00" * 2**24)
    assert len(bomb) < 2**12
    err = refused(frame_with(depth=nd("zstd2d", "uint16", [6, 5], bomb)))
    assert "zstd2d" in str(err) and "61+ bytes" in str(err)
