"""FrameAssembler, what goes right: the robot's live ROS 2 messages (as CDR payloads) to frames.

The synthetic scene of :mod:`live_scene` is fed with jittered stamps and shuffled arrival,
and every frame out is checked against the ground truth: poses from TF or a pose topic,
every colour and depth encoding.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import pytest

from services.ros2.live import FrameAssembler
from shared.config.ros2 import Ros2InputConfig

sys.path.insert(0, str(Path(__file__).parent))  # live_scene by bare name, under any import mode

from live_scene import (  # noqa: E402
    FPS,
    FX,
    T0_NS,
    T_world_cam,
    add_tf,
    assert_accounted,
    check_frame,
    depth_m_at,
    frame_numbers,
    odometry,
    pose_stamped,
    rejected,
    rel,
    rgb_at,
    scene,
    stamp_of,
)

# -- the happy paths -----------------------------------------------------------------------


def test_tf_chain_gives_interpolated_poses_intrinsics_and_depth() -> None:
    s = scene(30)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert [f.frame_index for f in frames] == list(range(30))
    assert frame_numbers(frames) == list(range(30))
    for i, f in enumerate(frames):
        check_frame(f, i)
        np.testing.assert_array_equal(f.rgb, rgb_at(i))
        np.testing.assert_array_equal(f.depth, np.rint(depth_m_at(i) * 1000).astype(np.uint16))
        assert f.depth_scale == 1000.0
    assert rejected(asm) == {}
    st = asm.stats
    assert st.emitted == 30 and st.pending == 0 and asm.last_stamp_s == pytest.approx(stamp_of(29) / 1e9)
    assert st.as_dict()["received"][s.cfg.rgb_topic] == 30
    assert asm.error is None
    assert_accounted(asm)


def test_frames_wait_for_lagging_tf_and_leave_at_once_when_it_comes() -> None:
    s = scene(3, tf_until_s=-0.05)  # TF starts, then nothing for the frames yet
    asm = FrameAssembler(s.cfg)
    assert s.feed(asm, until=0.12) == []
    assert asm.stats.pending == 3
    add_tf(s, 0.0, 0.2, arrival_lag=0.0)  # TF for the frames arrives 0.12 s late, well within max_wait_s
    for e in s.events:
        asm.on_message(e[2], e[3], 0.13, e[4])
    s.events.clear()
    frames = asm.poll(0.13)
    assert frame_numbers(frames) == [0, 1, 2]
    for i, f in enumerate(frames):
        check_frame(f, i)
    assert_accounted(asm)


@pytest.mark.parametrize("kind", ["odometry", "posestamped"])
def test_pose_topic_gives_the_nearest_pose_within_slop(kind: str, caplog: pytest.LogCaptureFixture) -> None:
    s = scene(20, pose=kind)
    # the pose topic's frame_id differs from world_frame once: a single warning, poses still used
    s.add(0.0, "/odom", odometry(T_world_cam(-1.0), T0_NS - 10**9, frame_id="odom") if kind == "odometry"
          else pose_stamped(T_world_cam(-1.0), T0_NS - 10**9))  # fmt: skip
    asm = FrameAssembler(s.cfg)
    with caplog.at_level(logging.WARNING, logger="services.ros2.live"):
        frames = s.feed(asm)
    assert frame_numbers(frames) == list(range(20))
    for i, f in enumerate(frames):
        # the pose sample is stamped within 3 ms of the colour: that sample's pose, not interpolated
        np.testing.assert_allclose(f.T_world_cam, T_world_cam(rel(stamp_of(i))), atol=0.01)
        assert f.intrinsics.fx == FX
    assert rejected(asm) == {}
    assert ("taken as world_frame" in caplog.text) == (kind == "odometry")
    assert_accounted(asm)


@pytest.mark.parametrize("rgb", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "jpeg", "png"])
def test_colour_encodings(rgb: str) -> None:
    s = scene(3, rgb=rgb)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == [0, 1, 2], rejected(asm)
    for i, f in enumerate(frames):
        want = rgb_at(i)
        if rgb == "mono8":
            want = np.repeat(want[:, :, :1], 3, axis=2)
        if rgb == "jpeg":
            assert np.abs(f.rgb.astype(int) - want).mean() < 3
        else:
            np.testing.assert_array_equal(f.rgb, want)
        check_frame(f, i)


@pytest.mark.parametrize("depth", ["16UC1", "32FC1", "cd16", "cd32"])
def test_depth_encodings(depth: str) -> None:
    s = scene(3, depth=depth)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    assert frame_numbers(frames) == [0, 1, 2], rejected(asm)
    for i, f in enumerate(frames):
        want = depth_m_at(i)
        assert f.depth_scale == 1000.0 and f.depth.dtype == np.uint16
        assert (f.depth == 0).tolist() == (want == 0).tolist()  # holes stay holes
        # inverse-depth quantisation (32FC1 compressedDepth) is d^2 / 10100 m: under 1 mm at 3 m
        np.testing.assert_allclose(f.depth_m(), want, atol=0.0011 if depth == "cd32" else 0.0006)


def test_compressed_colour_and_compressed_depth_over_the_key_types() -> None:
    """Under rmw_zenoh the key's type wins over the configured one."""
    s = scene(3, rgb="jpeg", depth="cd16", cfg=Ros2InputConfig())  # config says raw Image for both
    asm = FrameAssembler(s.cfg)
    assert frame_numbers(s.feed(asm)) == [0, 1, 2]
    # without the key's type, the configured (raw Image) one is tried and the payload fails
    s = scene(1, rgb="jpeg", cfg=Ros2InputConfig())
    s.events = [(e[0], e[1], e[2], e[3], None if e[2] == s.cfg.rgb_topic else e[4]) for e in s.events]
    asm = FrameAssembler(s.cfg)
    assert s.feed(asm) == [] and rejected(asm) == {"bad_payload": 1}


# -- faults --------------------------------------------------------------------------------


def test_depth_stops_for_5_s_then_returns() -> None:
    gap = set(range(30, 30 + 5 * FPS))
    n = 30 + 5 * FPS + 30
    s = scene(n, skip_depth=gap)
    asm = FrameAssembler(s.cfg)
    frames = s.feed(asm)
    got = frame_numbers(frames)
    assert got[:30] == list(range(30)) and got[30:] == list(range(30 + 5 * FPS, n))
    r = rejected(asm)
    # each colour without depth waits max_wait_s and is given up; the last few before depth
    # returns are dropped the moment a newer frame completes instead
    assert r.get("no_depth", 0) + r.get("superseded", 0) == len(gap) and r["no_depth"] >= len(gap) - 20
    assert set(r) <= {"no_depth", "superseded"}
    assert [f.frame_index for f in frames] == list(range(len(frames)))
    assert_accounted(asm)
