"""FrameAssembler, what goes wrong: every fault of the input is counted, logged, never raised.

Depth or TF that stops, stamps that go back (a bag loop), missing or mismatched camera info,
unknown encodings, bad poses, silent topics, bounded memory and hostile payloads, on the
synthetic scene of :mod:`live_scene`.
"""

from __future__ import annotations

import logging
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from services.ros2.live import REASONS, FrameAssembler
from shared.config.ros2 import Ros2InputConfig
from shared.ros2.types import encode

sys.path.insert(0, str(Path(__file__).parent))  # live_scene by bare name, under any import mode

from live_scene import (  # noqa: E402
    FPS,
    T0_NS,
    H,
    M,
    T_map_odom,
    T_odom_base,
    W,
    add_tf,
    assert_accounted,
    camera_info,
    check_frame,
    compressed,
    depth_m_at,
    file_bytes,
    frame_numbers,
    odometry,
    raw_image,
    rejected,
    rel,
    rgb_at,
    scene,
    stamp_of,
    tf_message,
    transform,
)


def test_tf_jumping_back_rejects_the_frames_that_would_use_it(caplog: pytest.LogCaptureFixture) -> None:
    n = 60
    s = scene(n, tf_until_s=0.5)
    # 0.5 s .. 0.8 s: odom -> base_link comes stamped 3 s in the past (a stale clock), then is good again
    for k in range(26, 40):
        t = k / 50
        st = T0_NS + round((t - 3.0) * 1e9)
        s.add(t + 0.06, s.cfg.tf_topic, tf_message(transform("odom", "base_link", st, T_odom_base(t - 3.0))))
    for k in range(10, 17):  # map -> odom keeps coming
        s.add(k / 20 + 0.061, s.cfg.tf_topic, tf_message(transform("map", "odom", T0_NS + k * 10**9 // 20, T_map_odom(k / 20))))
    add_tf(s, 0.8, rel(stamp_of(n - 1)) + 0.2)
    asm = FrameAssembler(s.cfg)
    with caplog.at_level(logging.WARNING, logger="services.ros2.live"):
        frames = s.feed(asm)
    got = frame_numbers(frames)
    lost = [i for i in range(n) if i not in got]
    # the frames between the last good sample (0.50 s) and the next one (0.80 s), and no other
    assert lost == [i for i in range(n) if 0.5 < i / FPS < 0.8], lost
    assert rejected(asm) == {"tf_backwards": len(lost), "out_of_order": 14}
    assert "TF_OLD_DATA ignoring data from the past for frame base_link" in caplog.text
    for f, i in zip(frames, got, strict=True):
        check_frame(f, i)
    assert asm.stats.resets == 0  # 0.28 s of stale stamps is no new timeline
    assert_accounted(asm)


def test_a_bag_loop_resets_the_buffers_and_frames_resume(caplog: pytest.LogCaptureFixture) -> None:
    s = scene(45)  # 1.5 s of scene
    asm = FrameAssembler(s.cfg)
    first = s.feed(asm, until=1.6)
    assert len(first) == 45
    # the bag starts again: the same stamps, arriving from 1.6 s on
    s2 = scene(90, seed=1)
    for now, k, topic, payload, ros_type in s2.events:
        if topic != s.cfg.tf_static_topic:
            s.events.append((now + 1.6, k, topic, payload, ros_type))
    with caplog.at_level(logging.WARNING, logger="services.ros2.live"):
        again = s.feed(asm)
    assert asm.stats.resets == 1
    assert "went back in time" in caplog.text and "cleared the TF buffer" in caplog.text
    got = frame_numbers(again)
    assert got and got == sorted(got) and got[-1] == 89 and got[0] > 20  # ~1 s of the loop lost to the reset
    for f, i in zip(again, got, strict=True):
        check_frame(f, i)
    assert [f.frame_index for f in first + again] == list(range(len(first) + len(again)))  # indices go on
    assert_accounted(asm)


def test_camera_info_never_comes(caplog: pytest.LogCaptureFixture) -> None:
    s = scene(4 * FPS, info=False)
    asm = FrameAssembler(s.cfg)
    first_colour = min(e[0] for e in s.events if e[2] == s.cfg.rgb_topic)
    errors = []
    for now, _, topic, payload, ros_type in sorted(s.events):
        asm.on_message(topic, payload, now, ros_type)
        assert asm.poll(now) == []
        errors.append((now, asm.error))
    last = max(e[0] for e in s.events)
    s.events.clear()
    with_error = [now for now, e in errors if e is not None]
    assert with_error and with_error[0] - first_colour <= s.cfg.camera_info_timeout_s + 0.05
    assert all(now - first_colour >= s.cfg.camera_info_timeout_s - 0.05 for now in with_error)
    assert asm.error.startswith(f"no sensor_msgs/CameraInfo on {s.cfg.camera_info_topic} after")
    held = asm.stats.pending
    assert 1 <= held <= asm.max_pending  # the newest colour images wait max_wait_s for it
    assert rejected(asm) == {"no_camera_info": 4 * FPS - held}
    assert_accounted(asm)
    assert asm.poll(last + s.cfg.max_wait_s + 0.01) == []
    assert rejected(asm) == {"no_camera_info": 4 * FPS} and asm.stats.pending == 0
    assert s.cfg.camera_info_topic in asm.silent_topics(4.2)
    # it comes after all: the error clears and frames flow
    s.add(4.2, s.cfg.camera_info_topic, camera_info(stamp_of(0)))
    asm.on_message(s.cfg.camera_info_topic, s.events[0][3], 4.2, None)
    assert asm.error is None
    assert_accounted(asm)


def test_colour_before_the_first_camera_info_waits_for_it() -> None:
    """Over a network the first colour image often beats the first CameraInfo: it is held
    (up to max_wait_s), not dropped, and becomes the first frame."""
    s = scene(10, info=False)
    first_colour = min(e[0] for e in s.events if e[2] == s.cfg.rgb_topic)
    s.add(first_colour + 0.02, s.cfg.camera_info_topic, camera_info(stamp_of(0)))
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == list(range(10))
    for i, f in enumerate(frames):
        check_frame(f, i)
    assert rejected(asm) == {} and asm.error is None
    assert_accounted(asm)
    # Later than max_wait_s, the held image is given up, and named as such.
    s = scene(10, info=False)
    s.add(first_colour + s.cfg.max_wait_s + 0.02, s.cfg.camera_info_topic, camera_info(stamp_of(0)))
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    got = frame_numbers(frames)
    assert got and got[0] > 0 and got == list(range(got[0], 10))
    assert rejected(asm) == {"no_camera_info": got[0]}
    assert_accounted(asm)


def test_unknown_encodings_are_counted() -> None:
    s = scene(4)
    topic_rgb, topic_d = s.cfg.rgb_topic, s.cfg.depth_topic
    late = 5.0
    s.add(late, topic_rgb, raw_image(np.zeros((H, W, 2), np.uint8), "yuv422", stamp_of(10)))
    s.add(late, topic_rgb, compressed(b"\x00" * 40, "rgb8; h264 compressed", stamp_of(11)))
    s.add(late, topic_rgb, compressed(b"\x00" * 40, "16UC1; compressedDepth png", stamp_of(12)))
    s.add(late, topic_d, raw_image(rgb_at(0), "rgb8", stamp_of(13)))
    s.add(late, topic_d, compressed(b"\x00" * 40, "16UC1; compressedDepth rvl", stamp_of(14)))
    s.add(late, topic_d, compressed(file_bytes(rgb_at(0), "JPEG"), "16UC1; jpeg compressed", stamp_of(15)))
    asm = FrameAssembler(s.cfg)
    assert frame_numbers(s.feed(asm)) == [0, 1, 2, 3]
    assert rejected(asm) == {"unknown_encoding": 6}
    assert "'16UC1; jpeg compressed' is not supported" in asm.error  # the standing problem, until a frame goes out
    assert_accounted(asm)


def test_size_mismatch_between_image_camera_info_and_depth(caplog: pytest.LogCaptureFixture) -> None:
    s = scene(6)
    small = np.rint(depth_m_at(0)[::2, ::2] * 1000).astype(np.uint16)
    asm = FrameAssembler(s.cfg)
    # frame 2's depth is half size (not aligned to colour); then a camera info for another size
    s.events = [e for e in s.events if not (e[2] == s.cfg.depth_topic and abs(e[0] - (rel(stamp_of(2)) + 0.035)) < 0.01)]
    s.add(rel(stamp_of(2)) + 0.035, s.cfg.depth_topic, raw_image(small, "16UC1", stamp_of(2)))
    with caplog.at_level(logging.WARNING, logger="services.ros2.live"):
        frames = s.feed(asm, until=1.0)
    assert frame_numbers(frames) == [0, 1, 3, 4, 5]
    assert rejected(asm) == {"size_mismatch": 1} and "depth is 32x24" in caplog.text and "aligned to colour" in caplog.text
    assert asm.error is None  # the frames after it were fine: no standing problem
    s.add(1.1, s.cfg.camera_info_topic, camera_info(stamp_of(6), width=W * 2, height=H * 2))
    s.add(1.11, s.cfg.rgb_topic, raw_image(rgb_at(6), "rgb8", stamp_of(6)))
    assert s.feed(asm) == []
    assert rejected(asm) == {"size_mismatch": 2} and "image is 64x48, camera info on" in asm.error
    assert_accounted(asm)


def test_out_of_order_stamps() -> None:
    s = scene(10)
    asm = FrameAssembler(s.cfg)
    assert len(s.feed(asm, until=1.0)) == 10
    s.add(1.1, s.cfg.rgb_topic, raw_image(rgb_at(3), "rgb8", stamp_of(3)))  # older than frame 9
    s.add(1.1, s.cfg.rgb_topic, raw_image(rgb_at(9), "rgb8", stamp_of(9)))  # a repeat of frame 9
    s.add(1.1, s.cfg.depth_topic, raw_image(np.zeros((H, W), np.uint16), "16UC1", stamp_of(4)))
    t_old = T0_NS + 10**8  # TF 0.1 s: older than the newest odom -> base_link by far more than tolerance
    s.add(1.1, s.cfg.tf_topic, tf_message(transform("odom", "base_link", t_old, np.eye(4))))
    assert s.feed(asm, until=1.2) == []
    assert rejected(asm) == {"out_of_order": 4}
    # arrival order shuffled within the window is no fault: frames come out in stamp order
    s2 = scene(10, seed=3)
    rng = np.random.default_rng(5)
    s2.events = [(e[0] + (rng.uniform(0, 0.05) if e[2] != s2.cfg.tf_topic else 0.0), *e[1:]) for e in s2.events]
    asm2 = FrameAssembler(s2.cfg)
    got = frame_numbers(s2.feed(asm2))
    assert got == sorted(got) and len(got) >= 7
    assert set(rejected(asm2)) <= {"superseded"}
    assert_accounted(asm)
    assert_accounted(asm2)


def test_latest_wins_supersedes_older_waiting_colours() -> None:
    s = scene(5, skip_depth={1, 2})
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == [0, 3, 4]
    assert rejected(asm) == {"superseded": 2}  # frame 3 completed while 1 and 2 still waited
    # their depth turning up later is too late: nothing is emitted out of order
    s.add(10.0, s.cfg.depth_topic, raw_image(np.zeros((H, W), np.uint16), "16UC1", stamp_of(1)))
    assert s.feed(asm) == []
    assert rejected(asm) == {"superseded": 2, "out_of_order": 1}
    assert_accounted(asm)


def test_unsupported_key_types_and_unknown_topics() -> None:
    s = scene(2)
    s.add(1.0, s.cfg.rgb_topic, M("std_msgs/msg/String")(data="hi"))
    s.add(1.0, s.cfg.tf_topic, M("std_msgs/msg/String")(data="hi"))
    s.add_raw(1.0, s.cfg.depth_topic, b"\x00\x01\x00\x00", "sensor_msgs/msg/NoSuchType")
    s.add(1.0, "/elsewhere", M("std_msgs/msg/String")(data="hi"))
    asm = FrameAssembler(s.cfg)
    assert len(s.feed(asm)) == 2
    assert rejected(asm) == {"unsupported_type": 3}
    assert "/elsewhere" not in asm.stats.received
    assert_accounted(asm)


def test_bad_poses_are_refused() -> None:
    s = scene(6, pose="odometry")
    nan = np.eye(4)
    nan[0, 3] = np.nan
    s.add(0.0, "/odom", odometry(nan, stamp_of(0) - 5 * 10**6))
    asm = FrameAssembler(s.cfg)
    assert len(s.feed(asm)) == 6
    assert rejected(asm) == {"bad_pose": 1}
    s2 = scene(3)
    s2.add(0.0, s2.cfg.tf_topic, tf_message(transform("odom", "base_link", stamp_of(0) + 1, np.eye(4), q=np.zeros(4))))
    s2.add(0.0, s2.cfg.tf_topic, tf_message(transform("odom", "odom", stamp_of(0), np.eye(4))))
    asm2 = FrameAssembler(s2.cfg)
    assert len(s2.feed(asm2)) == 3
    assert rejected(asm2) == {"bad_pose": 1, "bad_payload": 1}
    assert_accounted(asm)
    assert_accounted(asm2)


def test_frames_after_tf_stops_are_given_up() -> None:
    s = scene(30, tf_until_s=0.3)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    got = frame_numbers(frames)
    # 0.30 s is the last sample: up to 0.35 s the end sample is near enough (once max_wait_s is up)
    assert got == [i for i in range(30) if i / FPS <= 0.3 + 0.05]
    assert rejected(asm) == {"tf_missing": 30 - len(got)}
    assert asm.error.startswith("/camera/color/image_raw at stamp") and "no TF map <- camera_color_optical_frame" in asm.error
    assert_accounted(asm)


def test_tf_that_cannot_connect_names_the_frames(caplog: pytest.LogCaptureFixture) -> None:
    cfg = Ros2InputConfig(world_frame="world")  # the robot's tree is rooted at map
    s = scene(3, cfg=cfg)
    asm = FrameAssembler(cfg)
    with caplog.at_level(logging.WARNING, logger="services.ros2.live"):
        assert s.feed(asm) == []
    assert rejected(asm) == {"tf_missing": 3}
    assert asm.error.startswith("TF: no frame 'world'") and "known: base_link" in asm.error
    cfg = Ros2InputConfig(camera_frame="camera_link")
    s = scene(3, cfg=cfg)
    s.add(0.0, cfg.tf_static_topic, tf_message(transform("robot", "camera_link", stamp_of(0), np.eye(4))))
    asm = FrameAssembler(cfg)
    assert s.feed(asm) == []
    assert asm.error.startswith("TF: frames 'map' and 'camera_link' are not connected")
    assert "camera_link" in caplog.text
    assert_accounted(asm)


def test_silent_topics_say_what_is_missing() -> None:
    s = scene(60)
    s.events = [e for e in s.events if e[2] != s.cfg.depth_topic]
    asm = FrameAssembler(s.cfg)
    assert asm.silent_topics(0.0) == []
    s.feed(asm, until=2.0)
    assert asm.silent_topics(2.05) == [s.cfg.depth_topic]
    assert asm.silent_topics(3.0, after_s=0.5) == [s.cfg.rgb_topic, s.cfg.depth_topic, s.cfg.camera_info_topic, s.cfg.tf_topic]
    pose = FrameAssembler(Ros2InputConfig(pose_topic="/odom"))
    assert sorted(pose.subscriptions) == sorted([pose.cfg.rgb_topic, pose.cfg.depth_topic, pose.cfg.camera_info_topic, "/odom"])
    assert pose.silent_topics(10.0) == [] and len(pose.silent_topics(12.5)) == 4


def test_memory_stays_bounded() -> None:
    cfg = Ros2InputConfig(tf_buffer_s=1.0, max_wait_s=0.2)
    asm = FrameAssembler(cfg)
    asm.on_message(cfg.camera_info_topic, encode(camera_info(0)), 0.0)
    img = rgb_at(0)
    for k in range(600):  # 10 s of 60 Hz colour with no depth, and 120 Hz TF on 10 links
        now = k / 60
        st = T0_NS + k * 10**9 // 60
        asm.on_message(cfg.rgb_topic, encode(raw_image(img, "rgb8", st)), now)
        links = [transform("odom", f"link{j}", st + m * 10**9 // 120, np.eye(4)) for j in range(10) for m in range(2)]
        if k < 60:
            links.append(transform("odom", "gone", st, np.eye(4)))  # a publisher that stops after 1 s
        asm.on_message(cfg.tf_topic, encode(tf_message(*links)), now)
        asm.poll(now)
        assert asm.stats.pending <= asm.max_pending
    assert asm._poses.tf.sample_count() <= 10 * (cfg.tf_buffer_s + cfg.max_wait_s + 0.05) * 120
    assert "gone" not in asm._poses.tf.frames()
    assert len(asm._sync.depths) == 0 and asm.stats.rejected["no_depth"] > 0
    assert_accounted(asm)


# -- hostile input -------------------------------------------------------------------------


def _mutations(valid: list[bytes], rng: np.random.Generator, n: int) -> list[bytes]:
    out = []
    for k in range(n):
        p = bytearray(valid[k % len(valid)])
        kind = k % 5
        if kind == 0:  # random bytes, sometimes behind a valid CDR header
            p = bytearray(rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes())
            if k % 2:
                p[:4] = b"\x00\x01\x00\x00"
        elif kind == 1:  # flipped bytes
            for j in rng.integers(0, len(p), int(rng.integers(1, 8))):
                p[j] = int(rng.integers(0, 256))
        elif kind == 2:  # truncated
            p = p[: int(rng.integers(0, len(p)))]
        elif kind == 3:  # a length field blown up (the first four bytes after a 4-aligned offset)
            j = 4 + 4 * int(rng.integers(0, max(1, (len(p) - 8) // 4)))
            p[j : j + 4] = struct.pack("<I", int(rng.choice([2**31 - 1, 2**32 - 1, len(p), 0])))
        else:  # grown with junk
            p += rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        out.append(bytes(p))
    return out


@pytest.mark.parametrize("role", ["rgb", "depth", "camera_info", "tf", "tf_static", "pose"])
def test_hostile_payloads_are_counted_never_raised(role: str, caplog: pytest.LogCaptureFixture) -> None:
    kind = "odometry" if role == "pose" else "tf"
    s = scene(12, pose=kind, rgb="jpeg" if role == "rgb" else "rgb8", depth="cd32" if role == "depth" else "16UC1")
    cfg = s.cfg
    topic = {"rgb": cfg.rgb_topic, "depth": cfg.depth_topic, "camera_info": cfg.camera_info_topic, "tf": cfg.tf_topic,
             "tf_static": cfg.tf_static_topic, "pose": "/odom"}[role]  # fmt: skip
    valid = [e for e in s.events if e[2] == topic]
    rng = np.random.default_rng(123)
    n = 10_000
    hostile = _mutations([e[3] for e in valid], rng, n)
    asm = FrameAssembler(cfg, max_payload_bytes=50_000)
    frames = s.feed(asm, until=1.0)
    assert len(frames) == 12
    base = asm.stats
    ros_type = valid[0][4]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="services.ros2.live"):
        for k, p in enumerate(hostile):
            asm.on_message(topic, p, 1.0 + k * 1e-4, ros_type)
            if k % 50 == 0:
                asm.poll(1.0 + k * 1e-4)
    assert len(caplog.records) <= 12  # rate-limited: a line per reason (and a few once-warnings), not 10^4
    asm.on_message(topic, b"\x00\x01\x00\x00" + bytes(60_000), 2.0, ros_type)  # oversized: refused before parsing
    asm.poll(100.0)
    st = asm.stats
    assert st.received[topic] == base.received[topic] + n + 1
    assert_accounted(asm)
    new = {k: st.rejected[k] - base.rejected[k] for k in REASONS}
    assert new["bad_payload"] >= n // 2
    taken = st.accepted[topic] - base.accepted[topic]
    assert base.pending == 0 and taken + sum(new.values()) + st.pending == n + 1  # each one is somewhere, once
