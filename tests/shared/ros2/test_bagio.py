"""shared.ros2.bagio: a synthetic sequence written as a ROS 2 bag reads back, through the
in-process RosbagReader and as the raw stream a player sends, as the sequence itself."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from shared.config.source import RosbagConfig
from shared.datasets import open_sequence
from shared.datasets.base import DatasetError
from shared.datasets.rosbag import RosbagReader
from shared.datasets.tf import TfBuffer
from shared.ros2 import bagio
from shared.ros2.bagio import (
    BagError,
    BagMessage,
    PlaySchedule,
    bag_custom_data,
    bag_duration_ns,
    bag_source_sequence,
    bag_topics,
    latched_topics,
    play_times,
    read_bag_messages,
    write_sequence_bag,
)
from shared.ros2.types import decode

N_FRAMES = 12
SEQ_HZ = 30.0


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny synthetic sequence (80x60, 12 frames; about 1.5 s to generate)."""
    from shared.synth import generate, preset_config

    out = tmp_path_factory.mktemp("seq") / "tiny"
    cfg = preset_config("small", {"camera": {"width": 80, "height": 60, "frames": N_FRAMES}, "gt": {"point_spacing": 0.1}})
    generate(cfg, 0, out, progress=False)
    return out


@pytest.fixture(scope="module")
def bag(seq: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sequence as a default bag (Jazzy, MCAP, raw rgb8, depth in mm, 30 Hz)."""
    out = tmp_path_factory.mktemp("bags") / "tiny_bag"
    summary = write_sequence_bag(seq, out)
    assert summary.path == out and summary.frames == N_FRAMES
    return out


def _seq_frames(seq: Path) -> list:
    with open_sequence(seq, "replica") as r:
        return [r.frame(i) for i in range(len(r))]


def _stamp_ns(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


# -- what the bag holds --------------------------------------------------------------------------


def test_bag_reads_back_as_the_sequence(seq: Path, bag: Path) -> None:
    frames = _seq_frames(seq)
    scale = frames[0].depth_scale
    assert scale == 6553.5  # the synthetic layout: the bag's millimetres are a rounding of it
    with RosbagReader(bag, RosbagConfig()) as r:
        assert len(r) == len(frames) == N_FRAMES
        assert r.intrinsics == frames[0].intrinsics
        assert r.depth_scale == 1000.0
        for i, g in enumerate(frames):
            f = r.frame(i)
            np.testing.assert_allclose(f.T_world_cam, g.T_world_cam, rtol=0, atol=1e-9)
            np.testing.assert_array_equal(f.rgb, g.rgb)
            np.testing.assert_array_equal(f.depth, np.rint(g.depth * (1000.0 / scale)).astype(np.uint16))
            assert np.abs(f.depth / 1000.0 - g.depth / scale).max() <= 0.0005 + 1e-12
            assert np.array_equal(f.depth == 0, g.depth == 0)  # no reading stays no reading
            assert f.time_s == pytest.approx(bagio.EPOCH_NS * 1e-9 + i / SEQ_HZ, abs=1e-6)


def test_depth_in_sequence_units_is_lossless(seq: Path, tmp_path: Path) -> None:
    summary = write_sequence_bag(seq, tmp_path / "b", depth_units="sequence", storage="sqlite3", max_frames=3)
    assert summary.depth_scale == 6553.5 and summary.frames == 3 and summary.storage == "sqlite3"
    assert bag_custom_data(summary.path)[bagio.CUSTOM_DEPTH_SCALE] == "6553.5"
    frames = _seq_frames(seq)
    with RosbagReader(summary.path, RosbagConfig(depth_scale=summary.depth_scale)) as r:
        assert len(r) == 3
        for i in range(3):
            f = r.frame(i)
            assert f.depth_scale == 6553.5
            np.testing.assert_array_equal(f.depth, frames[i].depth)


def test_tf_chain_is_the_sequence_pose(seq: Path, bag: Path) -> None:
    frames = _seq_frames(seq)
    tf, stamps, map_odom, static = TfBuffer(), [], [], []
    for m in read_bag_messages(bag, topics=["/tf", "/tf_static", "/camera/color/image_raw"]):
        msg = decode(m.payload, m.ros_type)
        if m.topic == "/camera/color/image_raw":
            assert msg.header.frame_id == "camera_color_optical_frame"
            stamps.append(_stamp_ns(msg))
            continue
        for t in msg.transforms:
            tr, q = t.transform.translation, t.transform.rotation
            tf.add(t.header.frame_id, t.child_frame_id, _stamp_ns(t), np.array([tr.x, tr.y, tr.z]),
                   np.array([q.w, q.x, q.y, q.z]), static=m.topic == "/tf_static")  # fmt: skip
            if m.topic == "/tf_static":
                static.append((t.header.frame_id, t.child_frame_id))
            elif t.child_frame_id == "odom":
                assert t.header.frame_id == "map"
                map_odom.append(_stamp_ns(t))
    assert static == [("base_link", "camera_link"), ("camera_link", "camera_color_optical_frame")]
    assert {"map", "odom", "base_link", "camera_link", "camera_color_optical_frame"} == tf.frames()
    # Localisation at the camera's rate (bagio.MAP_ODOM_EVERY): every frame, so a live
    # consumer can interpolate each frame's pose as soon as its TF is in.
    assert map_odom == stamps[:: bagio.MAP_ODOM_EVERY]
    for st, g in zip(stamps, frames, strict=True):
        T = tf.lookup("map", "camera_color_optical_frame", st, 0)
        np.testing.assert_allclose(T, g.T_world_cam, rtol=0, atol=1e-9)
    # The static chain is a real mount (a rotation, not only the optical one), and odom is not map.
    assert not np.allclose(tf.lookup("base_link", "camera_color_optical_frame", stamps[0], 0), bagio.T_LINK_OPTICAL)
    assert not np.allclose(tf.lookup("map", "base_link", stamps[3], 0), tf.lookup("odom", "base_link", stamps[3], 0))


def test_messages_come_in_record_order_with_every_topic(bag: Path) -> None:
    msgs = list(read_bag_messages(bag))
    topics = bag_topics(bag)
    assert topics == {
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/camera/color/camera_info": "sensor_msgs/msg/CameraInfo",
        "/camera/color/image_raw": "sensor_msgs/msg/Image",
        "/camera/aligned_depth_to_color/image_raw": "sensor_msgs/msg/Image",
    }
    count = {t: sum(m.topic == t for m in msgs) for t in topics}
    assert count == {"/tf_static": 1, "/tf": N_FRAMES + 1, "/camera/color/camera_info": N_FRAMES,
                     "/camera/color/image_raw": N_FRAMES, "/camera/aligned_depth_to_color/image_raw": N_FRAMES}  # fmt: skip
    times = [m.time_ns for m in msgs]
    assert times == sorted(times) and len(set(times)) == len(times)
    assert msgs[0].topic == "/tf_static" and msgs[0].time_ns == bagio.EPOCH_NS
    assert all(m.ros_type == topics[m.topic] for m in msgs)
    assert all(m.payload[:4] == b"\x00\x01\x00\x00" for m in msgs)  # little-endian CDR as stored
    assert bag_duration_ns(bag) == times[-1] - times[0]
    # Each message is recorded a little after its stamp, and before the next frame's stamp.
    period = round(1e9 / SEQ_HZ)
    for m in msgs:
        if m.topic.startswith("/camera"):
            lag = m.time_ns - _stamp_ns(decode(m.payload, m.ros_type))
            assert 0 < lag < period // 2, (m.topic, lag)
    info = [decode(m.payload, m.ros_type) for m in msgs if m.topic == "/camera/color/camera_info"]
    assert [_stamp_ns(i) for i in info] == [bagio.EPOCH_NS + round(k * 1e9 / SEQ_HZ) for k in range(N_FRAMES)]
    assert {i.header.frame_id for i in info} == {"camera_color_optical_frame"}
    # Filtering keeps the order and only the topics asked for.
    depth = list(read_bag_messages(bag, topics=["/camera/aligned_depth_to_color/image_raw"]))
    assert [m.time_ns for m in depth] == [m.time_ns for m in msgs if m.topic == "/camera/aligned_depth_to_color/image_raw"]
    assert {m.payload for m in depth} == {m.payload for m in msgs if m.topic == "/camera/aligned_depth_to_color/image_raw"}


def test_tf_static_is_latched_and_the_sequence_is_named(seq: Path, bag: Path) -> None:
    assert latched_topics(bag) == {"/tf_static"}
    assert bag_source_sequence(bag) == seq.resolve()
    moved = bag.parent / "moved_seq_bag"
    shutil.copytree(bag, moved)
    meta = moved / "metadata.yaml"
    meta.write_text(meta.read_text().replace(str(seq.resolve()), str(seq.parent / "gone")))
    assert bag_source_sequence(moved) is None


def test_rate_and_distro_and_compressed_colour(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "jpeg_humble"
    summary = write_sequence_bag(seq, out, distro="humble", rate_hz=15.0, compressed_rgb=True, max_frames=4)
    assert summary.storage == "sqlite3"  # Humble's default storage
    assert summary.topics["/camera/color/image_raw/compressed"] == ("sensor_msgs/msg/CompressedImage", 4)
    assert "/camera/color/image_raw" not in summary.topics
    assert summary.duration_s == pytest.approx(3 / 15.0 + 0.5 / 15.0, abs=1e-3)  # ends with the extra odometry sample
    frames = _seq_frames(seq)
    with RosbagReader(out, RosbagConfig(rgb_topic="/camera/color/image_raw/compressed")) as r:
        assert len(r) == 4
        for i in range(4):
            f = r.frame(i)
            assert f.time_s == pytest.approx(bagio.EPOCH_NS * 1e-9 + i / 15.0, abs=1e-6)
            np.testing.assert_allclose(f.T_world_cam, frames[i].T_world_cam, rtol=0, atol=1e-9)
            err = np.abs(f.rgb.astype(int) - frames[i].rgb.astype(int))
            assert err.mean() < 4.0 and f.rgb.shape == frames[i].rgb.shape, err.mean()


# -- playing -------------------------------------------------------------------------------------


def test_due_times_follow_record_time_over_rate(bag: Path) -> None:
    msgs = list(read_bag_messages(bag))
    first = msgs[0].time_ns
    for rate in (1.0, 2.0):
        due = list(play_times(read_bag_messages(bag), 100.0, rate=rate))
        assert [m.time_ns for _, m in due] == [m.time_ns for m in msgs]
        assert due[0][0] == 100.0
        np.testing.assert_allclose([d for d, _ in due], [100.0 + (m.time_ns - first) * 1e-9 / rate for m in msgs], rtol=0, atol=1e-9)
    sched = PlaySchedule.of_bag(bag, rate=2.0)
    assert sched.first_ns == first
    assert sched.due_at(msgs[-1], 5.0) == pytest.approx(5.0 + bag_duration_ns(bag) * 1e-9 / 2, abs=1e-9)
    assert sched.due_at(first + 1_000_000_000, 0.0) == pytest.approx(0.5)
    assert list(play_times([], 0.0)) == []
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rate"):
            PlaySchedule(first, bad)
        with pytest.raises(ValueError, match="rate"):
            play_times(msgs, 0.0, rate=bad)


def test_bag_message_repr_leaves_out_the_payload() -> None:
    m = BagMessage("/tf", "tf2_msgs/msg/TFMessage", 5, b"\x00" * 1000)
    assert "payload" not in repr(m) and "/tf" in repr(m)


# -- refusals ------------------------------------------------------------------------------------


def test_read_errors_name_the_bag(bag: Path, tmp_path: Path) -> None:
    missing = tmp_path / "nope"
    for call in (bag_topics, bag_duration_ns, lambda p: list(read_bag_messages(p))):
        with pytest.raises(BagError, match=f"{missing}: ROS 2 bag not found"):
            call(missing)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    with pytest.raises(BagError, match=f"{broken}: cannot open as a ROS 2 bag"):
        read_bag_messages(broken)
    not_a_bag = tmp_path / "plain"
    not_a_bag.mkdir()
    with pytest.raises(BagError, match="cannot open"):
        bag_topics(not_a_bag)
    with pytest.raises(BagError, match=r"'/odom'.*not in the bag; available topics: .*/camera/color/camera_info \(sensor_msgs/msg/CameraInfo\)"):
        read_bag_messages(bag, topics=["/tf", "/odom"])
    assert issubclass(BagError, DatasetError)  # commands report it as bad input


def test_refuses_a_non_empty_output_and_overwrites_only_a_bag(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(BagError, match=f"{out}: output folder exists and is not empty"):
        write_sequence_bag(seq, out, max_frames=2)
    with pytest.raises(BagError, match="not a ROS 2 bag"):
        write_sequence_bag(seq, out, max_frames=2, overwrite=True)
    assert (out / "keep.txt").read_text() == "mine"
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(BagError, match="not a folder"):
        write_sequence_bag(seq, f)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert write_sequence_bag(seq, empty, max_frames=2).frames == 2
    assert write_sequence_bag(seq, empty, max_frames=3, overwrite=True).frames == 3
    assert bag_topics(empty)["/tf"] == "tf2_msgs/msg/TFMessage"
    assert sum(m.topic == "/camera/color/image_raw" for m in read_bag_messages(empty)) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "file", "out"]  # no temporary folder left
    with pytest.raises(ValueError, match="rate_hz"):
        write_sequence_bag(seq, tmp_path / "x", rate_hz=0)
    with pytest.raises(ValueError, match="storage"):
        write_sequence_bag(seq, tmp_path / "x", storage="bag")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="distro"):
        write_sequence_bag(seq, tmp_path / "x", distro="foxy")
    assert not (tmp_path / "x").exists()


def test_a_failure_leaves_no_partial_bag(seq: Path, tmp_path: Path) -> None:
    broken = tmp_path / "seq"
    shutil.copytree(seq, broken)
    (broken / "results" / "depth000003.png").write_bytes(b"not a png")
    out = tmp_path / "bags" / "b"
    with pytest.raises(DatasetError, match="depth000003"):
        write_sequence_bag(broken, out)
    assert not out.exists()
    assert list(out.parent.iterdir()) == []


# -- mapping a bag -------------------------------------------------------------------------------


@pytest.mark.slow
def test_mapping_the_bag_scores_as_mapping_the_sequence(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``trackgraph map`` of the small preset as a bag vs as a folder: instance AP50 within
    0.02. The simulated perception reads the sequence's ground truth, named in the config
    (a bag carries none)."""
    from services.cli import main
    from shared.config.base import save_resolved
    from shared.config.root import load_config
    from shared.synth import run_synth

    root = Path(__file__).resolve().parents[3]
    seq = tmp_path / "small"
    run_synth("small", 0, seq, progress=False)
    bag = tmp_path / "small_bag"
    write_sequence_bag(seq, bag)
    config = root / "deploy" / "configs" / "synthetic.yaml"
    gt_config = tmp_path / "synthetic_gt.yaml"
    save_resolved(load_config(config).with_ground_truth(seq), gt_config)

    ap50 = {}
    for name, args in (("seq", [str(seq), "--config", str(config)]), ("bag", [str(bag), "--dataset", "rosbag", "--config", str(gt_config)])):
        out = tmp_path / f"map_{name}"
        assert main(["map", *args, "--out", str(out), "--json"]) == 0
        assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames"] == 120
        assert main(["eval", "instances", "--pred", str(out), "--gt", str(seq), "--json"]) == 0
        ap50[name] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["ap50"]
    assert ap50["seq"] > 0.5, ap50
    assert abs(ap50["bag"] - ap50["seq"]) <= 0.02, ap50
