"""compressedDepth (compressed_depth_image_transport) decoding, compressed-image checks and the
decompression-bomb limit of shared.datasets.rosimage, and a bag whose depth is compressedDepth."""

from __future__ import annotations

import io
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import T_, _header, scene_messages, write_messages
from dataset_fixtures import Scene
from PIL import Image

from shared.config.source import RosbagConfig, SourceConfig
from shared.datasets import DatasetError, open_sequence
from shared.datasets.rosimage import (
    MAX_PIXELS,
    UnsupportedEncodingError,
    compressed_format,
    decode_colour,
    decode_depth,
    depth_scale_of,
    image_size,
    peek_size,
)


def _png(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


def _msg(data: bytes, fmt: str):
    return T_["sensor_msgs/msg/CompressedImage"](header=_header(0, "cam"), format=fmt, data=np.frombuffer(data, np.uint8))


def _inverse_depth(depth_m: np.ndarray, depth_max: float = 10.0, z0: float = 100.0) -> tuple[bytes, float, float]:
    """compressed_depth_image_transport's 32FC1 encoder (toInvDepth), in float32 as it is."""
    a = np.float32(z0 * (z0 + 1.0))
    b = np.float32(1.0 - a / np.float32(depth_max))
    d = depth_m.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(d < depth_max, a / d + b, 0)  # NaN compares false: 0, as in C++
    inv = np.where(np.isfinite(inv) & (inv > 0), inv, 0).astype(np.uint16)
    return _png(inv), float(a), float(b)


def test_16uc1_compressed_depth_is_the_png_itself() -> None:
    d = (np.arange(6 * 8, dtype=np.uint16).reshape(6, 8) * 997) % 9000
    d[0, 0] = 0
    for fmt in ("16UC1; compressedDepth png", "16UC1; compressedDepth"):  # newer, and pre-RVL publishers
        msg = _msg(struct.pack("<iff", 0, 0.0, 0.0) + _png(d), fmt)
        out, scale = decode_depth(msg, 5000.0, "w")
        np.testing.assert_array_equal(out, d)
        assert out.dtype == np.uint16 and scale == 5000.0 == depth_scale_of(msg, 5000.0)
        assert peek_size(msg, "depth", "w") == (8, 6)


def test_32fc1_compressed_depth_undoes_the_inverse_depth_quantisation() -> None:
    d = np.array([[2.0, 1.234, 0.5, np.nan], [9.99, 12.0, 0.0, 3.3]], dtype=np.float32)
    png, a, b = _inverse_depth(d)
    assert (a, b) == (10100.0, -1009.0)
    msg = _msg(struct.pack("<iff", 0, a, b) + png, "32FC1; compressedDepth png")
    out, scale = decode_depth(msg, 5000.0, "w")
    assert scale == 1000.0 == depth_scale_of(msg, 5000.0)
    # 2 m: value 4041, 10100 / (4041 + 1009) = 2.000 exactly; 1.234 m: value 7175 -> 1.23411 m;
    # 9.99 m: value 2 -> 9.990 m (coarse so far out); 3.3 m: value 2051 -> 3.30065 m.
    # NaN, 0 and beyond depth_max (10 m) were coded 0: no reading.
    np.testing.assert_array_equal(out, [[2000, 1234, 500, 0], [9990, 0, 0, 3301]])
    # the quantisation step is d^2 / A: 0.4 mm at 2 m
    rng = np.random.default_rng(0)
    many = rng.uniform(0.3, 6.0, (20, 30)).astype(np.float32)
    png, a, b = _inverse_depth(many)
    out, _ = decode_depth(_msg(struct.pack("<iff", 0, a, b) + png, "32FC1; compressedDepth"), 1000.0, "w")
    assert np.abs(out / 1000.0 - many).max() <= many.max() ** 2 / a + 0.0005


def test_plain_16bit_png_depth_from_the_compressed_transport() -> None:
    d = np.full((4, 5), 1234, np.uint16)
    out, scale = decode_depth(_msg(_png(d), "16UC1; png compressed "), 1000.0, "w")
    np.testing.assert_array_equal(out, d)
    assert scale == 1000.0
    with pytest.raises(UnsupportedEncodingError, match="w: .*'16UC1; jpeg compressed'.* not supported"):
        decode_depth(_msg(b"\xff\xd8junk", "16UC1; jpeg compressed"), 1000.0, "w")


def test_compressed_depth_errors_name_where_and_what() -> None:
    head = struct.pack("<iff", 0, 10100.0, -1009.0)
    with pytest.raises(DatasetError, match="topic /d: compressedDepth data of 12 bytes has no image after its 12-byte header"):
        decode_depth(_msg(head, "16UC1; compressedDepth png"), 1000.0, "topic /d")
    with pytest.raises(DatasetError, match="topic /d: unreadable compressed image"):
        decode_depth(_msg(head + b"\x89PNG\r\n\x1a\nnot really", "16UC1; compressedDepth png"), 1000.0, "topic /d")
    with pytest.raises(DatasetError, match="topic /d: expected a 16-bit single-channel depth image PNG, got mode L"):
        decode_depth(_msg(head + _png(np.zeros((3, 3), np.uint8)), "16UC1; compressedDepth png"), 1000.0, "topic /d")
    with pytest.raises(UnsupportedEncodingError, match="topic /d: compressedDepth rvl is not supported"):
        decode_depth(_msg(head + b"\x00" * 20, "16UC1; compressedDepth rvl"), 1000.0, "topic /d")
    with pytest.raises(UnsupportedEncodingError, match="topic /d: '8UC1; compressedDepth' is not a depth encoding"):
        decode_depth(_msg(head + b"\x00" * 20, "8UC1; compressedDepth"), 1000.0, "topic /d")
    nan_head = struct.pack("<iff", 0, float("nan"), 0.0)
    with pytest.raises(DatasetError, match="topic /d: compressedDepth header has invalid quantisation"):
        decode_depth(_msg(nan_head + _png(np.ones((2, 2), np.uint16)), "32FC1; compressedDepth"), 1000.0, "topic /d")
    with pytest.raises(UnsupportedEncodingError, match="topic /c: .* is compressed depth, not a colour image"):
        decode_colour(_msg(head + _png(np.ones((2, 2), np.uint16)), "16UC1; compressedDepth"), "topic /c")


def test_compressed_format_strings() -> None:
    def fmt(f: str) -> tuple[str, str]:
        return compressed_format(_msg(b"", f))

    assert fmt("bgr8; jpeg compressed bgr8") == ("bgr8", "jpeg")
    assert fmt("rgb8; png compressed rgb8") == ("rgb8", "png")
    assert fmt("jpeg") == ("", "jpeg") and fmt("JPG") == ("", "jpeg")
    assert fmt("32FC1; compressedDepth") == ("32fc1", "compressedDepth png")
    assert fmt("16UC1; compressedDepth rvl") == ("16uc1", "compressedDepth rvl")
    assert fmt("h264") == ("", "h264") and fmt("") == ("", "") and fmt("bgr8; compressed bgr8") == ("bgr8", "")
    with pytest.raises(UnsupportedEncodingError, match="w: compressed format 'h264' is not supported"):
        decode_colour(_msg(b"\x00" * 10, "h264"), "w")
    # only the JPEG and PNG parsers see the bytes, whatever the format claims
    tiff = io.BytesIO()
    Image.fromarray(np.zeros((2, 2, 3), np.uint8)).save(tiff, format="TIFF")
    with pytest.raises(UnsupportedEncodingError, match="'rgb8; tiff compressed' is not supported"):
        decode_colour(_msg(tiff.getvalue(), "rgb8; tiff compressed"), "w")
    with pytest.raises(DatasetError, match="w: unreadable compressed image"):
        decode_colour(_msg(tiff.getvalue(), "rgb8; png compressed"), "w")
    # no format at all: the bytes' own signature says it
    a = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    np.testing.assert_array_equal(decode_colour(_msg(_png(a), ""), "w"), a)
    assert image_size(_msg(_png(a), "png"), "w") == (3, 2) == peek_size(_msg(_png(a), "png"), "colour", "w")


def _png_header_only(width: int, height: int, bit_depth: int = 8, colour_type: int = 2) -> bytes:
    """A PNG whose IHDR claims ``width`` x ``height``, with one tiny (wrong) IDAT."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b"")


def _jpeg_claiming(width: int, height: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(buf, format="JPEG")
    data = bytearray(buf.getvalue())
    k = data.index(b"\xff\xc0")  # baseline SOF0: length (2), precision (1), height (2), width (2)
    data[k + 5 : k + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def test_decompression_bombs_are_refused_from_the_header() -> None:
    assert MAX_PIXELS == 4096 * 4096
    t = time.perf_counter()
    with pytest.raises(DatasetError, match=r"topic /c: compressed image claims 5000x5000 pixels, more than the limit of 16777216"):
        decode_colour(_msg(_png_header_only(5000, 5000), "rgb8; png compressed bgr8"), "topic /c")
    with pytest.raises(DatasetError, match="topic /c: compressed image claims 20000x1000 pixels"):
        decode_colour(_msg(_jpeg_claiming(20000, 1000), "rgb8; jpeg compressed bgr8"), "topic /c")
    with pytest.raises(DatasetError, match="topic /c: compressed image claims 5000x5000 pixels"):
        peek_size(_msg(_png_header_only(5000, 5000), "png"), "colour", "topic /c")
    bomb = struct.pack("<iff", 0, 0.0, 0.0) + _png_header_only(4097, 4097, bit_depth=16, colour_type=0)
    with pytest.raises(DatasetError, match="topic /d: compressed image claims 4097x4097 pixels"):
        decode_depth(_msg(bomb, "16UC1; compressedDepth png"), 1000.0, "topic /d")
    # Pillow's own limit (far above ours) is reported the same way
    with pytest.raises(DatasetError, match="topic /c: compressed image refused|topic /c: compressed image claims"):
        decode_colour(_msg(_png_header_only(60000, 60000), "png"), "topic /c")
    assert time.perf_counter() - t < 1.0  # nothing was decoded
    # at the limit itself the header passes; the bogus IDAT then fails as a broken image
    with pytest.raises(DatasetError, match="unreadable compressed image"):
        decode_colour(_msg(_png_header_only(4096, 4096), "png"), "topic /c")


def test_rosbag_reader_reads_compressed_depth(scene: Scene, tmp_path: Path) -> None:
    """The bag reader's depth path is decode_depth: compressedDepth bags now read."""
    cfg, msgs = scene_messages(scene, pose="odometry")
    out = []
    for topic, msgtype, st, msg in msgs:
        if topic == cfg.depth_topic:
            d = np.rint(scene.depth_m[len([m for m in out if m[0] == topic])] * 1000).astype(np.uint16)
            data = struct.pack("<iff", 0, 0.0, 0.0) + _png(d)
            msg = T_["sensor_msgs/msg/CompressedImage"](header=msg.header, format="16UC1; compressedDepth png",
                                                        data=np.frombuffer(data, np.uint8))  # fmt: skip
            msgtype = "sensor_msgs/msg/CompressedImage"
        out.append((topic, msgtype, st, msg))
    write_messages(tmp_path / "bag", out)
    with open_sequence(tmp_path / "bag", "rosbag", SourceConfig(rosbag=RosbagConfig(pose_topic="/odom"))) as r:
        assert len(r) == len(scene.times)
        for i in range(len(r)):
            f = r.frame(i)
            np.testing.assert_array_equal(f.depth, np.rint(scene.depth_m[i] * 1000).astype(np.uint16))
            assert f.depth_scale == 1000.0
