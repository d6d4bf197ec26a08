"""Bad sequences fail with a DatasetError that names the file (and for bags, the topic)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import CAMERA_FRAME, camera_info_msg, image_msg, scene_messages, write_messages
from dataset_fixtures import (
    H,
    Scene,
    W,
    row,
    save_png16,
    save_rgb,
    write_hm3d,
    write_replica,
    write_scannetpp,
    write_tum,
)
from PIL import Image

from shared.config.source import RosbagConfig, SourceConfig
from shared.datasets import DatasetError, open_sequence


def raises_naming(*parts: object) -> pytest.RaisesContext:
    """DatasetError whose message contains every part, in order."""
    return pytest.raises(DatasetError, match=".*".join(re.escape(str(p)) for p in parts))


@pytest.fixture
def replica(scene: Scene, tmp_path: Path) -> Path:
    return write_replica(scene, tmp_path / "replica")


def bad_pose_line(path: Path, lineno: int, T: np.ndarray) -> None:
    lines = path.read_text().splitlines()
    lines[lineno - 1] = row(T)
    path.write_text("\n".join(lines) + "\n")


# -- Replica ---------------------------------------------------------------------------------


def test_replica_missing_traj(replica: Path) -> None:
    (replica / "traj.txt").unlink()
    with raises_naming(replica / "traj.txt", "not found"):
        open_sequence(replica)


def test_replica_fewer_poses_than_frames(replica: Path) -> None:
    traj = replica / "traj.txt"
    traj.write_text("\n".join(traj.read_text().splitlines()[:3]) + "\n")
    with raises_naming(traj, "3 poses"):
        open_sequence(replica)


def test_replica_missing_results_folder(tmp_path: Path) -> None:
    with raises_naming(tmp_path / "results", "folder not found"):
        open_sequence(tmp_path)


def test_replica_missing_depth(replica: Path) -> None:
    (replica / "results" / "depth000003.png").unlink()
    with raises_naming(replica / "results" / "depth000003.png", "not found"):
        open_sequence(replica)


@pytest.mark.parametrize("value", [np.nan, 2.0], ids=["nan", "scaled"])
def test_replica_bad_pose(replica: Path, scene: Scene, value: float) -> None:
    T = scene.poses[2].copy()
    T[0, 0] = value
    bad_pose_line(replica / "traj.txt", 3, T)
    reader = open_sequence(replica)  # only that frame is refused, when it is read
    reader.frame(1)
    with raises_naming(f"{replica / 'traj.txt'}:3", "pose"):
        reader.frame(2)


def test_replica_truncated_image(replica: Path) -> None:
    jpg = replica / "results" / "frame000001.jpg"
    jpg.write_bytes(jpg.read_bytes()[: jpg.stat().st_size // 2])
    reader = open_sequence(replica)
    reader.frame(0)
    with raises_naming(jpg, "truncated"):
        reader.frame(1)


def test_replica_zero_byte_image(replica: Path) -> None:
    jpg = replica / "results" / "frame000002.jpg"
    jpg.write_bytes(b"")
    with raises_naming(jpg, "empty"):
        open_sequence(replica).frame(2)


def test_replica_depth_of_wrong_size(replica: Path) -> None:
    depth = replica / "results" / "depth000001.png"
    save_png16(depth, np.ones((H // 2, W // 2)))
    with raises_naming(depth, f"{W // 2}x{H // 2}", "frame000001.jpg"):
        open_sequence(replica).frame(1)


def test_replica_8bit_depth(replica: Path) -> None:
    depth = replica / "results" / "depth000000.png"
    Image.fromarray(np.ones((H, W), np.uint8)).save(depth)
    with raises_naming(depth, "16-bit"):
        open_sequence(replica).frame(0)


def test_replica_image_size_against_default_intrinsics(replica: Path) -> None:
    (replica / "intrinsics.json").unlink()
    with raises_naming(replica / "results" / "frame000000.jpg", "Replica defaults", "1200x680"):
        open_sequence(replica).frame(0)


def test_replica_bad_intrinsics_json(replica: Path) -> None:
    (replica / "intrinsics.json").write_text('{"fx": 1, "fy": 1, "cx": 0}')
    with raises_naming(replica / "intrinsics.json", "missing key"):
        open_sequence(replica)


def test_replica_instances_of_wrong_size(scene: Scene, tmp_path: Path) -> None:
    root = write_replica(scene, tmp_path, instances=np.zeros((5, H, W), np.int64))
    bad = root / "instances" / "instance000000.png"
    save_png16(bad, np.zeros((3, 3)))
    with raises_naming(bad, "3x3"):
        open_sequence(root).instances(0)


# -- ScanNet++ -------------------------------------------------------------------------------


@pytest.fixture
def snpp(scene: Scene, tmp_path: Path) -> Path:
    return write_scannetpp(scene, tmp_path / "scene")


def test_scannetpp_missing_images_txt(snpp: Path) -> None:
    path = snpp / "iphone" / "colmap" / "images.txt"
    path.unlink()
    with raises_naming(path, "not found"):
        open_sequence(snpp, "scannetpp")


def test_scannetpp_missing_depth_folder(snpp: Path) -> None:
    for p in (snpp / "iphone" / "depth").iterdir():
        p.unlink()
    (snpp / "iphone" / "depth").rmdir()
    with raises_naming(snpp / "iphone" / "depth", "folder not found"):
        open_sequence(snpp, "scannetpp")


def test_scannetpp_unsupported_camera(snpp: Path) -> None:
    path = snpp / "iphone" / "colmap" / "cameras.txt"
    path.write_text("1 OPENCV_FISHEYE 64 48 30 30 32 24 0 0 0 0\n")
    with raises_naming(f"{path}:1", "OPENCV_FISHEYE"):
        open_sequence(snpp, "scannetpp")


def test_scannetpp_zero_quaternion(snpp: Path) -> None:
    path = snpp / "iphone" / "colmap" / "images.txt"
    lines = path.read_text().splitlines()
    parts = lines[2].split()
    parts[1:5] = ["0", "0", "0", "0"]
    lines[2] = " ".join(parts)
    path.write_text("\n".join(lines) + "\n")
    with raises_naming(f"{path}:3", "quaternion"):
        open_sequence(snpp, "scannetpp")


def test_scannetpp_missing_colour_image(snpp: Path) -> None:
    path = snpp / "iphone" / "rgb" / "frame_000020.jpg"
    path.unlink()
    with raises_naming(path, "not found"):
        open_sequence(snpp, "scannetpp")


def test_scannetpp_depth_aspect_mismatch(snpp: Path) -> None:
    path = snpp / "iphone" / "depth" / "frame_000000.png"
    save_png16(path, np.ones((H, H)))
    with raises_naming(path, "aspect ratio"):
        open_sequence(snpp, "scannetpp")


def test_scannetpp_one_depth_of_another_size(snpp: Path) -> None:
    path = snpp / "iphone" / "depth" / "frame_000030.png"
    save_png16(path, np.ones((H * 2, W * 2)))
    with raises_naming(path, f"{2 * W}x{2 * H}"):
        open_sequence(snpp, "scannetpp").frame(3)


# -- HM3D ------------------------------------------------------------------------------------


@pytest.fixture
def hm3d(scene: Scene, tmp_path: Path) -> Path:
    return write_hm3d(scene, tmp_path / "walk")


def test_hm3d_missing_pose_folder(tmp_path: Path, scene: Scene) -> None:
    root = tmp_path / "walk"
    save_rgb(root / "rgb" / "0.png", scene.rgb[0])
    save_png16(root / "depth" / "0.png", np.ones((H, W)))
    with raises_naming(root / "pose", "folder not found"):
        open_sequence(root, "hm3d")


def test_hm3d_fewer_poses_than_frames(hm3d: Path) -> None:
    (hm3d / "pose" / "20.txt").unlink()
    with raises_naming(hm3d / "pose", "4 poses for 5 frames"):
        open_sequence(hm3d, "hm3d")


def test_hm3d_depth_count_mismatch(hm3d: Path) -> None:
    (hm3d / "depth" / "5.png").unlink()
    with raises_naming(hm3d / "depth", "4 depth images"):
        open_sequence(hm3d, "hm3d")


def test_hm3d_non_rigid_pose(hm3d: Path) -> None:
    path = hm3d / "pose" / "10.txt"
    path.write_text(row(np.diag([1.0, 1.0, 2.0, 1.0])))
    with raises_naming(path, "rigid"):
        open_sequence(hm3d, "hm3d")


def test_hm3d_short_pose_file(hm3d: Path) -> None:
    path = hm3d / "pose" / "15.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with raises_naming(path, "found 12"):
        open_sequence(hm3d, "hm3d")


# -- TUM -------------------------------------------------------------------------------------


@pytest.fixture
def tum(scene: Scene, tmp_path: Path) -> Path:
    return write_tum(scene, tmp_path / "rgbd_dataset_freiburg1_xyz")


def test_tum_missing_groundtruth(tum: Path) -> None:
    (tum / "groundtruth.txt").unlink()
    with raises_naming(tum / "groundtruth.txt", "not found"):
        open_sequence(tum, "tum")


def test_tum_malformed_groundtruth(tum: Path) -> None:
    path = tum / "groundtruth.txt"
    lines = path.read_text().splitlines()
    lines[4] = " ".join(lines[4].split()[:6])
    path.write_text("\n".join(lines) + "\n")
    with raises_naming(f"{path}:5", "found 6 numbers"):
        open_sequence(tum, "tum")


def test_tum_nothing_associates(tum: Path) -> None:
    (tum / "depth.txt").write_text("# nothing near the colour stamps\n1.0 depth/x.png\n")
    with raises_naming(tum / "rgb.txt", "no colour frame"):
        open_sequence(tum, "tum")


def test_tum_listed_image_missing(tum: Path) -> None:
    first = sorted((tum / "rgb").iterdir())[0]
    first.unlink()
    with raises_naming(first, "not found"):
        open_sequence(tum, "tum").frame(0)


# -- ROS bags --------------------------------------------------------------------------------


def _cfg(cfg: RosbagConfig, **changes: object) -> SourceConfig:
    return SourceConfig(rosbag=cfg.model_copy(update=changes))


def test_rosbag_unknown_topic_lists_available(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene)
    bag = write_messages(tmp_path / "bag", msgs)
    with raises_naming(bag, "'/camera/rgb'", "available topics", "/odom (nav_msgs/msg/Odometry)"):
        open_sequence(bag, "rosbag", _cfg(cfg, rgb_topic="/camera/rgb"))
    with raises_naming(bag, "pose topic '/vins/odometry'"):
        open_sequence(bag, "rosbag", _cfg(cfg, pose_topic="/vins/odometry"))


def test_rosbag_missing_bag(tmp_path: Path) -> None:
    with raises_naming(tmp_path / "nope", "not found"):
        open_sequence(tmp_path / "nope", "rosbag")


def test_rosbag_pose_topic_of_wrong_type(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene)
    bag = write_messages(tmp_path / "bag", msgs)
    with raises_naming(bag, cfg.camera_info_topic, "sensor_msgs/msg/CameraInfo"):
        open_sequence(bag, "rosbag", _cfg(cfg, pose_topic=cfg.camera_info_topic))


def test_rosbag_unknown_tf_frame(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene, pose="tf")
    bag = write_messages(tmp_path / "bag", msgs)
    with raises_naming(bag, "world_frame 'world'", "TF frames", CAMERA_FRAME):
        open_sequence(bag, "rosbag", _cfg(cfg, world_frame="world"))


def test_rosbag_no_pose_source(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene)
    bag = write_messages(tmp_path / "bag", [m for m in msgs if m[0] != "/odom"])
    with raises_naming(bag, "'/tf'", "not in the bag"):
        open_sequence(bag, "rosbag", _cfg(cfg, pose_topic=None))


def test_rosbag_zero_size_image(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene)
    msgs = [m for m in msgs if m[0] != cfg.rgb_topic]
    st = int(scene.times[0] * 1e9)
    msgs.append((cfg.rgb_topic, "sensor_msgs/msg/Image", st, image_msg(np.zeros((0, 0, 3), np.uint8), "rgb8", st)))
    bag = write_messages(tmp_path / "bag", msgs)
    with raises_naming(bag, cfg.rgb_topic, "zero-size"):
        open_sequence(bag, "rosbag", _cfg(cfg))


def test_rosbag_unsupported_encoding(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene)
    msgs = [
        (t, ty, st, image_msg(scene.rgb[0].astype(np.uint16), "rgb16", st)) if t == cfg.rgb_topic else (t, ty, st, m)
        for t, ty, st, m in msgs
    ]
    bag = write_messages(tmp_path / "bag", msgs)
    with raises_naming(bag, cfg.rgb_topic, "'rgb16'"):
        open_sequence(bag, "rosbag", _cfg(cfg)).frame(0)


def test_rosbag_camera_info_size_mismatch(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene)
    st = msgs[0][2]
    msgs[0] = (cfg.camera_info_topic, msgs[0][1], st, camera_info_msg(scene, st, width=640, height=480))
    bag = write_messages(tmp_path / "bag", msgs)
    with raises_naming(bag, cfg.camera_info_topic, "640x480", cfg.rgb_topic, f"{W}x{H}"):
        open_sequence(bag, "rosbag", _cfg(cfg))


def test_rosbag_depth_of_wrong_size(scene: Scene, tmp_path: Path) -> None:
    cfg, msgs = scene_messages(scene)
    msgs = [
        (t, ty, st, image_msg(np.ones((H // 2, W // 2), np.uint16), "16UC1", st)) if t == cfg.depth_topic else (t, ty, st, m)
        for t, ty, st, m in msgs
    ]
    bag = write_messages(tmp_path / "bag", msgs)
    with raises_naming(bag, cfg.depth_topic, f"{W // 2}x{H // 2}"):
        open_sequence(bag, "rosbag", _cfg(cfg)).frame(0)


def test_rosbag_frames_without_pose_are_skipped(scene: Scene, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cfg, msgs = scene_messages(scene)
    odom = [m for m in msgs if m[0] == "/odom"]
    bag = write_messages(tmp_path / "bag", [m for m in msgs if m not in odom[3:]])
    reader = open_sequence(bag, "rosbag", _cfg(cfg))
    assert len(reader) == 3
    assert "2 without a pose from /odom" in caplog.text
