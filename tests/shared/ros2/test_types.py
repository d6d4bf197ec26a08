"""shared.ros2.types: RIHS01 hashes against ROS 2's published values, CDR round trips, and
hostile payloads that must only ever raise RosDecodeError."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))  # sdk_offline by bare name, under any import mode

from sdk_offline import TYPES, camera_info, image, marker_array, msg_text, offline_sdk, tf_message  # noqa: E402

from shared.ros2.types import (  # noqa: E402
    TYPE_HASH_NOT_SUPPORTED,
    RosDecodeError,
    decode,
    encode,
    type_hash,
    typestore,
)

# ROS 2's own values, found independently of rosbags:
PUBLISHED_HASHES = {
    # rmw_zenoh docs/design.md (ros2/rmw_zenoh), the `chatter` key and tokens of demo_nodes_cpp.
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    # `ros2 topic info /camera/image_raw -v` output printed in ros-perception/image_pipeline,
    # image_pipeline/doc/tutorials.rst; the same bytes are in rosidl_generator_c's output for
    # Kilted in hpmicro/hpm_sdk, middleware/microros/kilted/include/sensor_msgs/sensor_msgs/msg/
    # detail/image__description.c.
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    # rosidl_generator_c output: micro-ROS/micro_ros_arduino src/visualization_msgs/msg/detail/
    # marker_array__struct.h (MarkerArray__TYPE_HASH) and, for Kilted, hpmicro/hpm_sdk
    # middleware/microros/kilted/include/visualization_msgs/visualization_msgs/msg/detail/
    # marker_array__description.c.
    "visualization_msgs/msg/MarkerArray": "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
}


@pytest.mark.parametrize("ros_type", sorted(PUBLISHED_HASHES))
def test_rihs01_hash_equals_ros2s_published_value(ros_type):
    # Unchanged definitions from Iron to Kilted: one hash for all three distributions.
    for distro in ("iron", "jazzy", "kilted"):
        assert type_hash(ros_type, distro) == PUBLISHED_HASHES[ros_type], distro
    assert type_hash(ros_type, "humble") == TYPE_HASH_NOT_SUPPORTED


def test_type_hash_of_unknown_type_names_it():
    with pytest.raises(KeyError, match="sensor_msgs/msg/NoSuchThing"):
        type_hash("sensor_msgs/msg/NoSuchThing")


def test_sdk_offline_computes_the_same_type_hashes(tmp_path):
    # The SDK hashes the .msg files sdk_offline writes, as its publisher does; equal hashes
    # mean its keys and tokens are ours too (and that the written definitions are faithful).
    with offline_sdk(tmp_path) as sdk:
        for ros_type in TYPES:
            assert sdk.type_hash(ros_type) == type_hash(ros_type), ros_type


def test_sdk_offline_definitions_reparse_to_rosbags_fields(tmp_path):
    """Every written .msg file parses back (rosbags' .msg parser, which the SDK registers
    types with) to the typestore's own field definitions."""
    from rosbags.typesys import get_types_from_msg

    with offline_sdk(tmp_path) as sdk:
        assert len(sdk.files) > len(TYPES)  # dependencies came along (Header, Time, Pose, ...)
        for ros_type, path in sdk.files.items():
            parsed = get_types_from_msg(path.read_text(), ros_type)[ros_type]
            assert parsed == typestore().fielddefs[ros_type], ros_type
    text, refs = msg_text("visualization_msgs/msg/Marker")
    assert "int32 TEXT_VIEW_FACING=9\n" in text and "geometry_msgs/Point[] points\n" in text
    assert "sensor_msgs/msg/CompressedImage" in refs


def test_image_round_trip():
    msg = image(np.random.default_rng(0))
    out = decode(encode(msg), "sensor_msgs/msg/Image")
    assert (out.height, out.width, out.encoding, out.step) == (3, 4, "rgb8", 12)
    assert out.header.frame_id == "cam" and out.header.stamp.nanosec == 123_456_789
    np.testing.assert_array_equal(out.data, msg.data)


def test_marker_array_round_trip():
    msg = marker_array()
    payload = encode(msg)
    assert payload[:4] == b"\x00\x01\x00\x00"  # little-endian plain CDR, as ROS 2 sends
    out = decode(payload, "visualization_msgs/msg/MarkerArray")
    assert [m.id for m in out.markers] == [0, 1, 2]
    assert out.markers[1].text == "armchair #1"
    assert [(p.x, p.y, p.z) for p in out.markers[2].points] == [(j, -j, 0.25 * j) for j in range(4)]
    assert out.markers[0].color.a == pytest.approx(0.8)
    assert encode(out) == payload


def test_decode_refuses_bad_payloads():
    good = encode(image(np.random.default_rng(1)))
    cases = {
        "truncated": good[: len(good) // 2],
        "header only": good[:4],
        "no header": good[:3],
        "empty": b"",
        "garbage": bytes(range(7, 250)),
        "wrong header": b"\x00\x07\x00\x00" + good[4:],  # XCDR2 / unknown encapsulation
        "big-endian header": b"\x00\x00\x00\x00" + good[4:],  # LE body read as BE: absurd lengths
    }
    for what, payload in cases.items():
        with pytest.raises(RosDecodeError, match="sensor_msgs/msg/Image"):
            decode(payload, "sensor_msgs/msg/Image")
            pytest.fail(what)
    with pytest.raises(RosDecodeError, match="exceeds the limit"):
        decode(good, "sensor_msgs/msg/Image", max_bytes=len(good) - 1)
    assert decode(good, "sensor_msgs/msg/Image", max_bytes=len(good)).width == 4


def _mutations(rng: np.random.Generator, valid: list[tuple[str, bytes]], n: int):
    """``n`` hostile (type, payload) pairs: random bytes of 0-512, and valid payloads with
    flipped bytes, cuts, insertions, duplicated runs and poisoned length fields."""
    types = [t for t, _ in valid]
    for i in range(n):
        mode = i % 6
        if mode == 0:
            yield types[i % len(types)], rng.integers(0, 256, size=int(rng.integers(0, 513)), dtype=np.uint8).tobytes()
            continue
        ros_type, base = valid[int(rng.integers(len(valid)))]
        b = bytearray(base)
        if mode == 1:  # flip a few bytes (past the header, to reach the parser)
            for _ in range(int(rng.integers(1, 6))):
                b[int(rng.integers(4, len(b)))] = int(rng.integers(256))
        elif mode == 2:  # truncate
            b = b[: int(rng.integers(4, len(b)))]
        elif mode == 3:  # insert junk
            at = int(rng.integers(4, len(b)))
            b[at:at] = rng.integers(0, 256, size=int(rng.integers(1, 16)), dtype=np.uint8).tobytes()
        elif mode == 4:  # a 4-byte-aligned field (a sequence or string length) becomes huge
            at = 4 + 4 * int(rng.integers(0, (len(b) - 8) // 4))
            b[at : at + 4] = int(rng.choice([0xFFFFFFFF, 0x7FFFFFFF, 0x80000000, len(b) * 8])).to_bytes(4, "little")
        else:  # duplicate a run, then cut the tail
            at = int(rng.integers(4, len(b)))
            b = (b + b[at:])[: int(rng.integers(4, 2 * len(b)))]
        yield ros_type, bytes(b)


def test_hostile_payloads_only_raise_ros_decode_error():
    rng = np.random.default_rng(2024)
    valid = [
        ("sensor_msgs/msg/Image", encode(image(rng, 6, 5))),
        ("sensor_msgs/msg/CameraInfo", encode(camera_info())),
        ("tf2_msgs/msg/TFMessage", encode(tf_message())),
    ]
    t0 = time.perf_counter()
    outcomes = {"decoded": 0, "refused": 0}
    for ros_type, payload in _mutations(rng, valid, 10_000):
        try:
            decode(payload, ros_type, max_bytes=4096)
            outcomes["decoded"] += 1
        except RosDecodeError:
            outcomes["refused"] += 1
        except Exception as e:  # noqa: BLE001 - the point of the test: name the payload
            pytest.fail(f"{ros_type}: {len(payload)}-byte payload {payload[:48].hex()}... raised {type(e).__name__}: {e}")
    elapsed = time.perf_counter() - t0
    assert sum(outcomes.values()) == 10_000
    assert outcomes["refused"] > 5_000  # the mutations mostly break the messages
    assert elapsed < 5.0, f"10^4 hostile payloads took {elapsed:.2f} s"
