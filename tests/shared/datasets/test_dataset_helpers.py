"""Building blocks of the readers: time association, TF chaining, ROS image decoding, COLMAP."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from bag_fixtures import image_msg, write_rosbag
from dataset_fixtures import Scene, rotation

from shared.config.source import SourceConfig
from shared.datasets import DatasetError, open_sequence
from shared.datasets.colmap import read_cameras
from shared.datasets.files import natural_key
from shared.datasets.rosimage import decode_colour, decode_depth
from shared.datasets.tf import TfBuffer, slerp
from shared.datasets.timestamps import associate, nearest
from shared.geometry import invert, pose_from_quat


def test_associate_is_one_to_one_and_closest_first() -> None:
    a = np.array([0.0, 0.010, 0.100, 0.500])
    b = np.array([0.012, 0.001, 0.115, 0.9])
    # 0.010 takes 0.012 (2 ms) before 0.0 could; 0.0 still gets 0.001; 0.500 has nothing.
    assert associate(a, b, 0.02) == [(0, 1), (1, 0), (2, 2)]
    assert associate(np.array([0.0, 0.001]), np.array([0.0005]), 0.02) == [(0, 0)]
    assert associate(np.array([]), np.array([1.0]), 0.02) == []


def test_nearest_allows_sharing_and_respects_the_limit() -> None:
    ref = np.array([0.0, 0.01, 0.02, 0.5])
    np.testing.assert_array_equal(nearest(np.array([0.004, 0.006, 0.3, 0.51, -1.0]), ref, 0.02), [0, 1, -1, 3, -1])
    np.testing.assert_array_equal(nearest(np.array([0.1]), np.array([0.11]), 0.02), [0])
    np.testing.assert_array_equal(nearest(np.array([0.1]), np.array([]), 0.02), [-1])


def _q(R: np.ndarray) -> np.ndarray:
    from dataset_fixtures import matrix_to_quat

    return matrix_to_quat(R)


def test_tf_interpolates_and_chains_through_a_common_ancestor() -> None:
    tf = TfBuffer()
    R0, R1 = rotation([0, 0, 1], 0.0), rotation([0, 0, 1], 0.4)
    tf.add("odom", "base", 1000, np.zeros(3), _q(R0), static=False)
    tf.add("odom", "base", 3000, np.array([2.0, 0, 0]), _q(R1), static=False)
    tf.add("/base", "cam", 0, np.array([0, 0, 1.0]), _q(np.eye(3)), static=True)
    tf.add("odom", "map_marker", 0, np.array([5.0, 0, 0]), _q(np.eye(3)), static=True)
    T = tf.lookup("odom", "cam", 2000, max_gap_ns=10)
    assert T is not None
    np.testing.assert_allclose(T[:3, :3], rotation([0, 0, 1], 0.2), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1.0, 0, 1.0], atol=1e-12)
    # target below the root: T_marker_cam = inv(T_odom_marker) @ T_odom_cam
    T2 = tf.lookup("map_marker", "cam", 2000, max_gap_ns=10)
    np.testing.assert_allclose(T2, invert(pose_from_quat(np.array([5.0, 0, 0]), np.array([1.0, 0, 0, 0]))) @ T)
    assert tf.lookup("odom", "cam", 3005, max_gap_ns=10) is not None  # just past the end
    assert tf.lookup("odom", "cam", 3100, max_gap_ns=10) is None  # too far past the end
    with pytest.raises(LookupError, match="not connected"):
        tf.add("elsewhere", "lost", 0, np.zeros(3), _q(np.eye(3)), static=True)
        tf.lookup("odom", "lost", 2000, 10)


def test_slerp_takes_the_short_way() -> None:
    q0 = np.array([1.0, 0, 0, 0])
    q1 = -_q(rotation([1, 0, 0], 0.6))  # same rotation, opposite sign
    mid = slerp(q0, q1, 0.5)
    R = pose_from_quat(np.zeros(3), mid)[:3, :3]
    np.testing.assert_allclose(R, rotation([1, 0, 0], 0.3), atol=1e-12)


def test_decode_raw_images() -> None:
    a = np.arange(24, dtype=np.uint8).reshape(2, 4, 3)
    np.testing.assert_array_equal(decode_colour(image_msg(a, "rgb8", 0, pad=3), "w"), a)
    np.testing.assert_array_equal(decode_colour(image_msg(a, "bgr8", 0), "w"), a[:, :, ::-1])
    g = a[:, :, 0]
    np.testing.assert_array_equal(decode_colour(image_msg(g, "mono8", 0), "w"), np.repeat(g[:, :, None], 3, 2))
    d = np.array([[1, 300], [65535, 0]], dtype=np.uint16)
    big = SimpleNamespace(encoding="16UC1", height=2, width=2, step=4, is_bigendian=1, data=d.astype(">u2").view(np.uint8).reshape(-1))
    out, scale = decode_depth(big, 1000.0, "w")
    np.testing.assert_array_equal(out, d)
    f = np.array([[1.2344, np.nan], [-1.0, 70.0]], dtype=np.float32)
    out, scale = decode_depth(image_msg(f, "32FC1", 0), 5000.0, "w")
    assert scale == 1000.0
    np.testing.assert_array_equal(out, [[1234, 0], [0, 0]])  # NaN, negative, beyond 65.5 m: no reading
    with pytest.raises(DatasetError, match="w: .* needs"):
        decode_colour(SimpleNamespace(encoding="rgb8", height=2, width=4, step=12, is_bigendian=0, data=np.zeros(5, np.uint8)), "w")
    with pytest.raises(DatasetError, match="w: compressedDepth data of 0 bytes has no image"):
        decode_depth(SimpleNamespace(format="16UC1; compressedDepth png", data=b""), 1000.0, "w")


def test_colmap_models_and_distortion(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "cameras.txt"
    path.write_text("# c\n1 SIMPLE_PINHOLE 640 480 500 320 240\n2 OPENCV 640 480 500 501 320 240 0.1 0 0 0\n")
    with caplog.at_level(logging.WARNING):
        cams = read_cameras(path)
    assert (cams[1].fx, cams[1].fy, cams[1].cx, cams[1].cy) == (500, 500, 319.5, 239.5)
    assert cams[2].fy == 501 and "distortion" in caplog.text


def test_natural_sort() -> None:
    names = ["10.png", "2.png", "frame_1.png", "1.png"]
    assert [n for n in sorted(names, key=lambda n: natural_key(Path(n)))] == ["1.png", "2.png", "10.png", "frame_1.png"]


def test_rosbag_reader_closes(scene: Scene, tmp_path: Path) -> None:
    cfg = write_rosbag(scene, tmp_path / "bag")
    with open_sequence(tmp_path / "bag", "rosbag", SourceConfig(rosbag=cfg)) as reader:
        reader.frame(0)
    reader.close()  # twice is fine
    assert len(reader) == 5 and reader.pose(1).shape == (4, 4)
    with pytest.raises(DatasetError, match="closed"):
        reader.frame(0)
