"""Every registered message survives shared.codec.encode/decode under every link setting.

Hypothesis builds valid instances of each message type; each is encoded, the wire form is
checked to use the link's encoding for each array kind, and the decoded message must equal
the original field by field (arrays bit for bit, same dtype and shape). JPEG is lossy: a
JPEG-encoded RGB array must equal what Pillow gives for the same image and quality, and
stay close to the original.
"""

from __future__ import annotations

import io
import typing
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from shared import SCHEMA_VERSION
from shared.arrays import ArraySpec, spec_of
from shared.codec import decode, encode
from shared.config import CodecConfig
from shared.geometry import Intrinsics, quat_to_matrix
from shared.messages import (
    REGISTRY,
    Edge,
    EmbedReply,
    EmbedRequest,
    EndOfSequence,
    Envelope,
    Frame,
    FrameAck,
    GraphDelta,
    GraphSnapshot,
    InputCounters,
    KeyframeMasks,
    KeyframeRequest,
    MaskFeatures,
    MeshChunk,
    PlaceNode,
    QueryHit,
    QueryReply,
    QueryRequest,
    RoomNode,
    SegmentNode,
    ServiceStatus,
    SnapshotRequest,
    TrackedFrame,
    TrackFeature,
    TrackFeatures,
    TrackObservation,
)
from shared.messages.poses import PoseCorrection

FAST = settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# ---------------------------------------------------------------- scalar strategies

U64 = st.integers(0, 2**64 - 1)
I64 = st.integers(-(2**63), 2**63 - 1)
NONNEG = st.integers(0, 2**63 - 1)
FROM_MINUS_ONE = st.integers(-1, 2**63 - 1)
FINITE = st.floats(allow_nan=False, allow_infinity=False)
TEXT = st.text(max_size=16)
NONBLANK = st.text(min_size=1, max_size=16).filter(lambda s: s.strip() != "")
SIDE = st.integers(1, 12)
POSITIVE = st.floats(min_value=1e-3, max_value=1e6)


def arrays(dtype: str, shape: Any, **kw: Any) -> st.SearchStrategy[np.ndarray]:
    """Arrays of ``dtype``; float elements are finite (the messages' finite specs)."""
    dt = np.dtype(dtype)
    if "elements" not in kw and dt.kind == "f":
        kw["elements"] = hnp.from_dtype(dt, allow_nan=False, allow_infinity=False)
    return hnp.arrays(dt, shape, **kw)


def vec3() -> st.SearchStrategy[np.ndarray]:
    return arrays("float64", (3,), elements=st.floats(-1e6, 1e6))


def vectors(max_len: int = 8) -> st.SearchStrategy[np.ndarray]:
    """A feature vector, float32 or float16, possibly empty."""
    return st.sampled_from(["float32", "float16"]).flatmap(
        lambda dt: arrays(dt, st.integers(0, max_len))
    )


def feature_rows(rows: int) -> st.SearchStrategy[np.ndarray]:
    return st.tuples(st.sampled_from(["float32", "float16"]), st.integers(0, 6)).flatmap(
        lambda p: arrays(p[0], (rows, p[1]))
    )


@st.composite
def rgb_images(draw: st.DrawFn, h: int, w: int) -> np.ndarray:
    """Either arbitrary bytes or a smooth gradient (what JPEG is made for)."""
    if draw(st.booleans()):
        return draw(arrays("uint8", (h, w, 3)))
    base = np.array(draw(st.lists(st.integers(16, 239), min_size=3, max_size=3)))
    slope = draw(st.integers(-3, 3))
    yy, xx = np.mgrid[:h, :w]
    return np.clip(base + slope * (xx + yy)[..., None], 0, 255).astype(np.uint8)


@st.composite
def rigid_poses(draw: st.DrawFn) -> np.ndarray:
    q = draw(
        st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
            lambda q: np.linalg.norm(q) > 0.1
        )
    )
    t = draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(np.array(q))
    T[:3, 3] = t
    return T


@st.composite
def intrinsics(draw: st.DrawFn, w: int, h: int) -> Intrinsics:
    return Intrinsics(
        fx=draw(st.floats(0.1, 5000)),
        fy=draw(st.floats(0.1, 5000)),
        cx=draw(st.floats(-1e4, 1e4)),
        cy=draw(st.floats(-1e4, 1e4)),
        width=w,
        height=h,
    )


# ---------------------------------------------------------------- message strategies


@st.composite
def frames(draw: st.DrawFn) -> Frame:
    h, w = draw(SIDE), draw(SIDE)
    return Frame(
        frame_index=draw(U64),
        time_s=draw(FINITE),
        rgb=draw(rgb_images(h, w)),
        depth=draw(arrays("uint16", (h, w))),
        depth_scale=draw(POSITIVE),
        intrinsics=draw(intrinsics(w, h)),
        T_world_cam=draw(rigid_poses()),
    )


@st.composite
def end_of_sequences(draw: st.DrawFn) -> EndOfSequence:
    return EndOfSequence(
        frames_published=draw(NONNEG),
        frames_dropped=draw(NONNEG),
        last_frame_index=draw(FROM_MINUS_ONE),
        track_features_published=draw(st.none() | NONNEG),
    )


@st.composite
def tracked_frames(draw: st.DrawFn) -> TrackedFrame:
    frame = draw(frames())
    h, w = frame.depth.shape
    ids = draw(st.lists(st.integers(0, 2**31 - 1), unique=True, max_size=4))
    tracks = [
        TrackObservation(
            track_id=i,
            keyframe=draw(st.booleans()),
            frames_since_keyframe=draw(st.integers(0, 10_000)),
        )
        for i in ids
    ]
    track_ids = draw(arrays("int32", (h, w), elements=st.sampled_from([-1, *ids])))
    confidence = draw(st.none() | arrays("uint8", (h, w)))
    return TrackedFrame(frame=frame, track_ids=track_ids, tracks=tracks, keyframe=draw(st.booleans()), confidence=confidence)


@st.composite
def keyframe_requests(draw: st.DrawFn) -> KeyframeRequest:
    h, w = draw(SIDE), draw(SIDE)
    with_depth = draw(st.booleans())
    return KeyframeRequest(
        frame_index=draw(U64),
        rgb=draw(rgb_images(h, w)),
        depth=draw(arrays("uint16", (h, w))) if with_depth else None,
        depth_scale=draw(POSITIVE) if with_depth else draw(st.none() | POSITIVE),
        intrinsics=draw(st.none() | intrinsics(w, h)),
    )


@st.composite
def keyframe_masks(draw: st.DrawFn) -> KeyframeMasks:
    n, h, w = draw(st.integers(0, 4)), draw(SIDE), draw(SIDE)
    return KeyframeMasks(
        frame_index=draw(U64),
        masks=draw(arrays("bool", (n, h, w))),
        boxes=draw(arrays("float32", (n, 4))),
        scores=draw(arrays("float32", (n,))),
        error=draw(st.none() | TEXT),
    )


@st.composite
def mask_features(draw: st.DrawFn) -> MaskFeatures:
    return MaskFeatures(
        frame_index=draw(U64),
        features=draw(feature_rows(draw(st.integers(0, 4)))),
        model=draw(TEXT),
        error=draw(st.none() | TEXT),
    )


@st.composite
def track_feature(draw: st.DrawFn, track_id: int) -> TrackFeature:
    has_clip = draw(st.booleans())
    return TrackFeature(
        track_id=track_id,
        dino=draw(vectors()),
        clip=draw(vectors()) if has_clip else None,
        clip_count=draw(st.integers(1, 10_000)) if has_clip else 0,
    )


@st.composite
def track_features(draw: st.DrawFn) -> TrackFeatures:
    ids = draw(st.lists(NONNEG, unique=True, max_size=4))
    return TrackFeatures(
        frame_index=draw(U64),
        tracks=[draw(track_feature(i)) for i in ids],
        retired=draw(st.lists(I64, max_size=4)),
    )


@st.composite
def segment_nodes(draw: st.DrawFn) -> SegmentNode:
    tracks = draw(st.lists(NONNEG, unique=True, max_size=5))
    gallery_tracks = draw(st.lists(st.sampled_from(tracks), max_size=4)) if tracks else []
    lo = draw(vec3())
    extent = draw(arrays("float64", (3,), elements=st.floats(0, 1e6)))
    return SegmentNode(
        id=draw(NONNEG),
        centroid=draw(vec3()),
        bbox_min=lo,
        bbox_max=lo + extent,
        tracks=tracks,
        dino=draw(vectors()),
        gallery=draw(feature_rows(len(gallery_tracks))),
        gallery_tracks=gallery_tracks,
        gallery_weights=draw(st.just([]) | st.lists(st.floats(0, 1), min_size=len(gallery_tracks), max_size=len(gallery_tracks))),
        active=draw(st.booleans()),
        room=draw(st.none() | I64),
        num_vertices=draw(NONNEG),
    )


@st.composite
def place_nodes(draw: st.DrawFn) -> PlaceNode:
    return PlaceNode(
        id=draw(NONNEG),
        position=draw(vec3()),
        radius=draw(st.floats(0, 1e6)),
        room=draw(st.none() | I64),
    )


@st.composite
def room_nodes(draw: st.DrawFn) -> RoomNode:
    return RoomNode(id=draw(NONNEG), centroid=draw(vec3()), name=draw(TEXT))


@st.composite
def edges(draw: st.DrawFn) -> Edge:
    return Edge(
        kind=draw(st.sampled_from(["segment_place", "place_place", "place_room", "room_building"])),
        source=draw(NONNEG),
        target=draw(NONNEG),
    )


@st.composite
def mesh_chunks(draw: st.DrawFn) -> MeshChunk:
    v = draw(st.integers(0, 6))
    f = draw(st.integers(0, 4)) if v else 0
    return MeshChunk(
        vertices=draw(arrays("float32", (v, 3))),
        colors=draw(arrays("uint8", (v, 3))),
        faces=draw(arrays("int32", (f, 3), elements=st.integers(0, max(v - 1, 0)))),
        segment_ids=draw(arrays("int32", (v,))),
    )


def _graph_common(draw: st.DrawFn) -> dict:
    return dict(
        graph_seq=draw(NONNEG),
        frame_index=draw(FROM_MINUS_ONE),
        segments=draw(st.lists(segment_nodes(), max_size=3)),
        places=draw(st.lists(place_nodes(), max_size=3)),
        rooms=draw(st.lists(room_nodes(), max_size=2)),
        edges=draw(st.lists(edges(), max_size=3)),
        mesh=draw(st.none() | mesh_chunks()),
    )


@st.composite
def graph_deltas(draw: st.DrawFn) -> GraphDelta:
    return GraphDelta(
        **_graph_common(draw),
        removed_segments=draw(st.lists(I64, max_size=3)),
        removed_places=draw(st.lists(I64, max_size=3)),
        removed_rooms=draw(st.lists(I64, max_size=3)),
        removed_edges=draw(st.lists(edges(), max_size=2)),
    )


@st.composite
def graph_snapshots(draw: st.DrawFn) -> GraphSnapshot:
    return GraphSnapshot(**_graph_common(draw))


@st.composite
def text_or_image(draw: st.DrawFn) -> dict:
    if draw(st.booleans()):
        return {"text": draw(NONBLANK)}
    h, w = draw(SIDE), draw(SIDE)
    return {"image": draw(rgb_images(h, w))}


@st.composite
def embed_requests(draw: st.DrawFn) -> EmbedRequest:
    return EmbedRequest(**draw(text_or_image()))


@st.composite
def embed_replies(draw: st.DrawFn) -> EmbedReply:
    return EmbedReply(
        embedding=draw(st.none() | vectors()),
        model=draw(TEXT),
        error=draw(st.none() | TEXT),
    )


@st.composite
def query_requests(draw: st.DrawFn) -> QueryRequest:
    near = draw(st.booleans())
    return QueryRequest(
        **draw(text_or_image()),
        top_k=draw(st.none() | st.integers(1, 2**31)),
        room=draw(st.none() | I64),
        center=draw(vec3()) if near else None,
        radius=draw(POSITIVE) if near else None,
        gallery=draw(st.sampled_from([None, "max", "mean"])),
    )


@st.composite
def query_hits(draw: st.DrawFn) -> QueryHit:
    return QueryHit(
        segment=draw(I64),
        score=draw(FINITE),
        centroid=draw(vec3()),
        bbox_min=draw(vec3()),
        bbox_max=draw(vec3()),
        room=draw(st.none() | I64),
        best_track=draw(st.none() | I64),
    )


@st.composite
def query_replies(draw: st.DrawFn) -> QueryReply:
    return QueryReply(
        hits=draw(st.lists(query_hits(), max_size=3)),
        graph_seq=draw(FROM_MINUS_ONE),
        error=draw(st.none() | TEXT),
    )


@st.composite
def service_statuses(draw: st.DrawFn) -> ServiceStatus:
    small = st.integers(0, 2**31)
    rate = st.floats(0, 1e6, allow_nan=False)
    inputs = draw(st.lists(st.builds(InputCounters, name=NONBLANK, received=small, processed=small, rejected=small,
                                     dropped=small, rate_hz=rate, queue_depth=small), max_size=4))  # fmt: skip
    return ServiceStatus(
        service=draw(NONBLANK), pid=draw(small), state=draw(st.sampled_from(["starting", "running", "finished", "stopped"])),
        uptime_s=draw(rate), inputs=inputs, published=draw(st.dictionaries(NONBLANK, small, max_size=3)),
        rate_hz=draw(rate), latency_p50_ms=draw(st.none() | rate), latency_p99_ms=draw(st.none() | rate),
        frames_done=draw(st.none() | small), frames_expected=draw(st.none() | small), errors=draw(small),
        figures=draw(st.dictionaries(NONBLANK, st.none() | st.booleans() | small | TEXT, max_size=3)),
    )  # fmt: skip


@st.composite
def pose_corrections(draw: st.DrawFn) -> PoseCorrection:
    frames = sorted(draw(st.sets(st.integers(0, 10_000), min_size=1, max_size=6)))
    return PoseCorrection(
        correction_id=draw(NONNEG), frame_index=frames[-1] + draw(st.integers(0, 100)), frames=np.asarray(frames, np.int64),
        poses=np.stack([draw(rigid_poses()) for _ in frames]), apply_after_frame=draw(st.none() | NONNEG),
    )  # fmt: skip


STRATEGIES: dict[type[BaseModel], st.SearchStrategy] = {
    PoseCorrection: pose_corrections(),
    ServiceStatus: service_statuses(),
    Frame: frames(),
    EndOfSequence: end_of_sequences(),
    FrameAck: st.builds(FrameAck, frame_index=NONNEG, service=st.text(min_size=1, max_size=32)),
    TrackedFrame: tracked_frames(),
    KeyframeRequest: keyframe_requests(),
    KeyframeMasks: keyframe_masks(),
    MaskFeatures: mask_features(),
    TrackFeatures: track_features(),
    GraphDelta: graph_deltas(),
    GraphSnapshot: graph_snapshots(),
    SnapshotRequest: st.builds(SnapshotRequest, with_mesh=st.booleans()),
    EmbedRequest: embed_requests(),
    EmbedReply: embed_replies(),
    QueryRequest: query_requests(),
    QueryReply: query_replies(),
}

CONFIGS = {
    "default": CodecConfig(),
    "all-raw": CodecConfig(rgb="raw", depth="raw", masks="bits", labels="raw"),
    "jpeg90-png-rle-zlib": CodecConfig(rgb="jpeg", jpeg_quality=90, depth="png", masks="rle", labels="zlib"),
    "jpeg90-zstd-rle-zlib": CodecConfig(rgb="jpeg", jpeg_quality=90, depth="zstd", masks="rle", labels="zlib"),
    "raw-zstd9-bits-raw": CodecConfig(rgb="raw", depth="zstd", zstd_level=9, masks="bits", labels="raw"),
    "jpeg50-png9-bits-raw": CodecConfig(
        rgb="jpeg", jpeg_quality=50, depth="png", png_level=9, masks="bits", labels="raw"
    ),
}

JPEG_MAX_MEAN_ABS_ERROR = 128.0
"""Loose bound: channels swapped or inverted would exceed it. Hypothesis finds tiny 0/255
checkerboards that JPEG at quality 50 legitimately smears past 70, so the exact Pillow
reference below is the tight check."""

# ---------------------------------------------------------------- comparison


def field_spec(field: FieldInfo) -> ArraySpec | None:
    """The ArraySpec of a field, also when the field is ``Annotated[...] | None``."""
    spec = spec_of(field.metadata)
    for arg in typing.get_args(field.annotation):
        spec = spec or spec_of(list(getattr(arg, "__metadata__", ())))
    return spec


def expected_encoding(spec: ArraySpec | None, arr: np.ndarray, cfg: CodecConfig) -> str:
    kind = spec.kind if spec is not None else "plain"
    if kind == "rgb" and cfg.rgb == "jpeg" and arr.size:
        return "jpeg"
    if kind == "depth" and cfg.depth == "png" and arr.size:
        return "png"
    if kind == "depth" and cfg.depth == "zstd" and arr.size:
        return "zstd2d"
    if kind == "mask":
        return cfg.masks
    if kind == "label" and cfg.labels == "zlib":
        return "zlib"
    return "raw"


def jpeg_reference(img: np.ndarray, quality: int) -> np.ndarray:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=quality)
    return np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"))


def assert_wire(wire: Any, value: Any, cfg: CodecConfig, path: str, spec: ArraySpec | None = None) -> None:
    """Each array in the undecoded body uses the link's encoding for its kind."""
    if isinstance(value, np.ndarray):
        assert isinstance(wire, dict) and "__nd__" in wire, path
        assert wire["__nd__"] == expected_encoding(spec, value, cfg), path
        assert wire["dtype"] == value.dtype.name, path
        assert wire["shape"] == list(value.shape), path
    elif isinstance(value, BaseModel):
        assert isinstance(wire, dict), path
        assert set(wire) == set(type(value).model_fields), path
        for name, field in type(value).model_fields.items():
            assert_wire(wire[name], getattr(value, name), cfg, f"{path}.{name}", field_spec(field))
    elif isinstance(value, list):
        assert isinstance(wire, list) and len(wire) == len(value), path
        for i, (w, v) in enumerate(zip(wire, value, strict=True)):
            assert_wire(w, v, cfg, f"{path}[{i}]")


def assert_same(got: Any, want: Any, cfg: CodecConfig, path: str, spec: ArraySpec | None = None) -> None:
    """Field-by-field equality; arrays bit for bit except JPEG-encoded RGB."""
    if isinstance(want, np.ndarray):
        assert isinstance(got, np.ndarray), path
        assert got.dtype == want.dtype, f"{path}: dtype {got.dtype} != {want.dtype}"
        assert got.shape == want.shape, f"{path}: shape {got.shape} != {want.shape}"
        if expected_encoding(spec, want, cfg) == "jpeg":
            np.testing.assert_array_equal(got, jpeg_reference(want, cfg.jpeg_quality), err_msg=path)
            err = np.abs(got.astype(np.int16) - want.astype(np.int16)).mean()
            assert err <= JPEG_MAX_MEAN_ABS_ERROR, f"{path}: JPEG mean abs error {err}"
        else:
            assert np.ascontiguousarray(got).tobytes() == np.ascontiguousarray(want).tobytes(), path
    elif isinstance(want, BaseModel):
        assert type(got) is type(want), path
        for name, field in type(want).model_fields.items():
            assert_same(getattr(got, name), getattr(want, name), cfg, f"{path}.{name}", field_spec(field))
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), path
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            assert_same(g, w, cfg, f"{path}[{i}]")
    else:
        assert type(got) is type(want), f"{path}: {type(got).__name__} != {type(want).__name__}"
        assert got == want, f"{path}: {got!r} != {want!r}"


# ---------------------------------------------------------------- tests


def test_every_registered_message_has_a_strategy() -> None:
    assert set(STRATEGIES) == set(REGISTRY.values())
    assert len(REGISTRY) >= 14


@pytest.mark.parametrize("cfg_name", sorted(CONFIGS))
@pytest.mark.parametrize("type_name", sorted(REGISTRY))
@FAST
@given(data=st.data())
def test_roundtrip(type_name: str, cfg_name: str, data: st.DataObject) -> None:
    cls = REGISTRY[type_name]
    cfg = CONFIGS[cfg_name]
    msg = data.draw(STRATEGIES[cls], label="message")
    robot = data.draw(TEXT, label="robot_id")
    seq = data.draw(U64, label="seq")
    stamp = data.draw(FINITE, label="stamp")

    payload = encode(msg, robot_id=robot, seq=seq, stamp=stamp, cfg=cfg)
    assert isinstance(payload, bytes)

    raw = msgpack.unpackb(payload, raw=False)
    assert raw["type"] == type_name and raw["v"] == SCHEMA_VERSION
    assert_wire(raw["body"], msg, cfg, type_name)

    env = decode(payload, cls, cfg)
    assert isinstance(env, Envelope)
    assert (env.robot_id, env.seq, env.stamp) == (robot, seq, stamp)
    assert type(env.seq) is int and type(env.stamp) is float
    assert env.schema_version == SCHEMA_VERSION
    assert_same(env.body, msg, cfg, type_name)


def test_jpeg_of_a_smooth_image_is_close() -> None:
    yy, xx = np.mgrid[:12, :12]
    img = np.stack([40 + 8 * xx, 60 + 8 * yy, 200 - 5 * (xx + yy)], axis=-1).astype(np.uint8)
    req = EmbedRequest(image=img)
    cfg = CodecConfig(rgb="jpeg", jpeg_quality=90)
    got = decode(encode(req, robot_id="r", seq=0, stamp=0.0, cfg=cfg), EmbedRequest, cfg).body.image
    assert got.dtype == np.uint8 and got.shape == img.shape
    assert np.abs(got.astype(int) - img.astype(int)).mean() < 4.0


def test_decode_default_config_matches_encode_default_config() -> None:
    """encode/decode without cfg use CodecConfig() (labels and rgb raw: a robot's loopback)."""
    h, w = 3, 4
    frame = Frame(
        frame_index=1,
        rgb=np.arange(h * w * 3, dtype=np.uint8).reshape(h, w, 3),
        depth=np.arange(h * w, dtype=np.uint16).reshape(h, w),
        depth_scale=1000.0,
        intrinsics=Intrinsics(fx=1, fy=1, cx=0, cy=0, width=w, height=h),
        T_world_cam=np.eye(4),
    )
    tracked = TrackedFrame(frame=frame, track_ids=np.full((h, w), -1, dtype=np.int32), tracks=[])
    payload = encode(tracked, robot_id="robot0", seq=7, stamp=1.5)
    body = msgpack.unpackb(payload)["body"]
    assert body["frame"]["rgb"]["__nd__"] == "raw"
    assert body["track_ids"]["__nd__"] == "raw"
    env = decode(payload, TrackedFrame)
    assert_same(env.body, tracked, CodecConfig(), "TrackedFrame")


@pytest.mark.parametrize("shape", [(680, 1200), (1, 1), (1, 9), (9, 1), (7, 13)])
def test_zstd2d_depth_is_bit_exact(shape):
    """Noise, zeros (no reading), the uint16 extremes and steps of either sign, mod 2^16."""
    from shared.codec import _decode_array, _encode_array

    rng = np.random.default_rng(3)
    cfg = CodecConfig(depth="zstd")
    spec = ArraySpec(dtypes=("uint16",), shape=(None, None), kind="depth")
    for depth in (rng.integers(0, 2**16, shape, dtype=np.uint16), np.zeros(shape, np.uint16), np.full(shape, 65535, np.uint16),
                  (np.indices(shape).sum(0) % 2 * 65535).astype(np.uint16)):  # fmt: skip
        wire = _encode_array(depth, spec, cfg)
        assert wire["__nd__"] == "zstd2d"
        back = _decode_array(wire, cfg)
        assert back.dtype == np.uint16 and back.shape == shape and np.array_equal(back, depth)
    # a receiver set to another depth encoding still decodes it
    assert np.array_equal(_decode_array(_encode_array(depth, spec, cfg), CodecConfig(depth="png")), depth)


def test_a_data_map_may_use_the_array_marker_as_a_key() -> None:
    """Found by the round trip above (a status figure named ``__nd__`` decoded as a broken
    array): a map of the message's own keeps every string key, the marker and the escape
    prefix included, and still travels as a plain map."""
    from shared.messages.status import ServiceStatus

    figures = {"__nd__": None, "__nd_esc__": 1, "__nd_esc____nd__": [2, 3], "__nd_x": {"__nd__": "raw"}, "frames": 4}
    status = ServiceStatus(service="fusion", pid=1, state="running", uptime_s=0.0, inputs=[], published={}, rate_hz=0.0, errors=0, figures=figures, stale_s=0.0)
    payload = encode(status, robot_id="robot0", seq=1, stamp=2.0)
    wire = msgpack.unpackb(payload)["body"]["figures"]
    assert "__nd__" not in wire and wire["__nd_esc____nd__"] is None and wire["__nd_esc____nd_esc__"] == 1
    assert decode(payload, ServiceStatus).body.figures == figures
