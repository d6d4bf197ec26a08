"""Corrections from a ROS 2 SLAM (``shared/ros2/corrections.py``): an optimised Path, or a
map -> odom jump, turned into PoseCorrections that put fusion's poses (its own PoseBook) on
the true trajectory."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.corrections.poses import PoseBook
from shared.config.ros2 import Ros2InputConfig
from shared.geometry import invert, pose_from_quat
from shared.ros2.corrections import MAX_LISTED, CorrectionBuilder, read_path
from shared.ros2.types import msg_class

T0 = 1_700_000_000 * 10**9
DT = 33_333_333
N = 120


def yaw(a: float, t) -> np.ndarray:
    return pose_from_quat(np.asarray(t, float), np.array([np.cos(a / 2), 0, 0, np.sin(a / 2)]))


def truth(i: int) -> np.ndarray:
    """The camera walks 3 cm a frame along x, turning slowly."""
    return yaw(0.004 * i, [0.03 * i, 0.2 * np.sin(0.05 * i), 1.0])


def drift(i: int) -> np.ndarray:
    """Odometry's error, world-from-world: grows with the distance walked (2 cm/m, 0.02 rad/m)."""
    d = 0.03 * i
    return yaw(0.02 * d, [0.02 * d, -0.01 * d, 0.0])


def odom(i: int) -> np.ndarray:
    return drift(i) @ truth(i)


def cfg(**kw) -> Ros2InputConfig:
    base = {"corrections": "path", "odom_frame": None, "corrections_min_period_s": 0.0}
    return Ros2InputConfig(**{**base, **kw})


def fused(b: CorrectionBuilder, corrections, n: int) -> PoseBook:
    """Fusion's view: every recorded frame added, the corrections applied in order."""
    book = PoseBook()
    for i in range(n):
        book.add(i, b._f.raw[i])
    for c in corrections:
        assert book.check(c) is None
        book.correct(c)
    return book


def err_m(book: PoseBook, i: int) -> float:
    return float(np.linalg.norm(book.estimate(i)[:3, 3] - truth(i)[:3, 3]))


def test_an_optimised_path_puts_every_frame_on_the_true_trajectory():
    b = CorrectionBuilder(cfg())
    for i in range(N):
        b.record(i, T0 + i * DT, odom(i), np.eye(4))
    nodes = list(range(0, N, 10))  # a keyframe a third of a second, stamped 4 ms off the frames
    c = b.from_path(
        np.array([T0 + i * DT + 4_000_000 for i in nodes]),
        np.stack([truth(i) for i in nodes]),
        now=0.0,
    )
    assert (
        c is not None
        and c.frames.tolist() == nodes
        and c.frame_index == N - 1
        and c.apply_after_frame == N - 1
    )
    np.testing.assert_allclose(c.poses, np.stack([truth(i) for i in nodes]), atol=1e-9)
    book = fused(b, [c], N)
    before = max(float(np.linalg.norm(odom(i)[:3, 3] - truth(i)[:3, 3])) for i in range(N))
    after = max(err_m(book, i) for i in range(N))
    assert before > 0.2 and after < before / 10, (
        before,
        after,
    )  # between nodes, only the drift of 5 frames is left
    assert max(err_m(book, i) for i in nodes) < 1e-9
    # The same path again moves nothing: nothing is sent.
    again = b.from_path(
        np.array([T0 + i * DT for i in nodes]), np.stack([truth(i) for i in nodes]), now=1.0
    )
    assert again is None and b.stats.unchanged == 1 and b.stats.sent == 1


def test_path_of_the_robot_body_goes_through_the_camera_offset():
    T_body_cam = yaw(-np.pi / 2, [0.1, 0.0, 0.3])
    b = CorrectionBuilder(cfg(corrections_body_frame="base_link"))
    for i in range(30):
        b.record(i, T0 + i * DT, odom(i), T_body_cam)
    nodes = [0, 15, 29]
    body = np.stack([truth(i) @ invert(T_body_cam) for i in nodes])
    c = b.from_path(np.array([T0 + i * DT for i in nodes]), body, now=0.0)
    np.testing.assert_allclose(c.poses, np.stack([truth(i) for i in nodes]), atol=1e-9)


def test_ids_grow_thresholds_hold_and_the_period_batches():
    b = CorrectionBuilder(cfg(corrections_min_period_s=1.0, corrections_min_m=0.02))
    for i in range(N):
        b.record(i, T0 + i * DT, odom(i), np.eye(4))
    st = np.array([T0, T0 + 60 * DT])
    P = np.stack([truth(0), truth(60)])
    c1 = b.from_path(st, P, now=10.0)
    assert c1.correction_id == T0 + 60 * DT
    # 1 cm more: below corrections_min_m, nothing goes out.
    nudge = P.copy()
    nudge[:, 0, 3] += 0.01
    assert b.from_path(st, nudge, now=12.0) is None and b.stats.unchanged == 1
    # 10 cm within the period: held, then sent by due() once the period is over, with a newer id.
    moved = P.copy()
    moved[:, 0, 3] += 0.1
    assert b.from_path(st, moved, now=10.5) is None
    assert b.due(10.9) is None
    c2 = b.due(11.0)
    assert c2 is not None and c2.correction_id == c1.correction_id + 1 and b.stats.sent == 2
    # Paths that match no frame are counted.
    assert b.from_path(np.array([T0 - 10**9]), P[:1], now=20.0) is None and b.stats.unmatched == 1


def test_a_long_run_lists_at_most_max_listed_frames():
    b = CorrectionBuilder(cfg())
    n = MAX_LISTED + 500
    for i in range(n):
        b.record(i, T0 + i * DT, yaw(0.0, [0.01 * i, 0, 0]), np.eye(4))
    st = np.array([T0 + i * DT for i in range(n)])
    c = b.from_path(st, np.stack([yaw(0.0, [0.01 * i + 0.1, 0, 0]) for i in range(n)]), now=0.0)
    assert len(c.frames) == MAX_LISTED and c.frames[0] == 0 and c.frames[-1] == n - 1


def test_a_map_odom_jump_is_spread_over_the_frames_since_the_last_one():
    b = CorrectionBuilder(cfg(corrections="map_odom", odom_frame="odom"))
    M0 = yaw(0.3, [1.0, 2.0, 0.0])  # where the SLAM put odom at the start
    lookups = {}

    def lookup(target, source, stamp):
        return lookups[stamp]

    for i in range(N):
        lookups[T0 + i * DT] = (
            invert(M0) @ yaw(0.0, [0.02 * i, 0, 0]) @ yaw(0.3, [1.0, 2.0, 0.0])
        )  # odom <- cam
        # TF's world <- cam with a stale map -> odom; frames go out at M0 @ odom pose.
        pose = b.place(i, T0 + i * DT, "cam", M0 @ lookups[T0 + i * DT], lookup)
        np.testing.assert_allclose(pose, M0 @ lookups[T0 + i * DT], atol=1e-12)
    # The SLAM finds the robot 12 cm further along x than odometry says: map -> odom jumps.
    fix = yaw(0.0, [0.12, 0, 0])
    c = b.from_map_odom(fix @ M0, T0 + N * DT, now=0.0)
    assert c is not None and c.frames.tolist() == list(range(N))
    share = np.array(
        [np.linalg.norm(c.poses[i][:3, 3] - (M0 @ lookups[T0 + i * DT])[:3, 3]) for i in range(N)]
    )
    assert share[0] == pytest.approx(0.0, abs=1e-9) and share[-1] == pytest.approx(0.12, abs=1e-9)
    assert np.all(np.diff(share) > 0)  # grows along the way, by distance walked
    np.testing.assert_allclose(share[N // 2], 0.12 * (N // 2) / (N - 1), atol=1e-6)
    # The same map -> odom again: nothing; frames after it are fused with the fix, like fusion's PoseBook.
    assert b.from_map_odom(fix @ M0, T0 + N * DT + 1, now=1.0) is None
    book = fused(b, [c], N)
    lookups[T0 + N * DT] = invert(M0) @ yaw(0.0, [0.02 * N, 0, 0]) @ yaw(0.3, [1.0, 2.0, 0.0])
    raw = b.place(N, T0 + N * DT, "cam", fix @ M0 @ lookups[T0 + N * DT], lookup)
    np.testing.assert_allclose(
        raw, M0 @ lookups[T0 + N * DT], atol=1e-12
    )  # odometry pose, not TF's new one
    np.testing.assert_allclose(
        book.add(N, raw), fix @ M0 @ lookups[T0 + N * DT], atol=1e-9
    )  # placed once, not twice


def test_frames_tf_cannot_place_are_counted_and_go_out_as_they_came():
    b = CorrectionBuilder(cfg(corrections="map_odom", odom_frame="odom"))
    assert b.place(0, T0, "cam", np.eye(4), lambda *a: None) is None
    assert b.stats.unplaced == 1 and b.frames == 0


def M(name: str):
    return msg_class(name)


def path_msg(frame: str, poses: list[tuple[int, np.ndarray]], pose_frame: str = ""):
    def stamp(ns):
        return M("builtin_interfaces/msg/Time")(sec=ns // 10**9, nanosec=ns % 10**9)

    def ps(ns, T, q=None):
        from shared.geometry import matrix_to_quat

        w, x, y, z = matrix_to_quat(T[:3, :3]) if q is None else q
        return M("geometry_msgs/msg/PoseStamped")(
            header=M("std_msgs/msg/Header")(stamp=stamp(ns), frame_id=pose_frame),
            pose=M("geometry_msgs/msg/Pose")(position=M("geometry_msgs/msg/Point")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                             orientation=M("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)),
        )  # fmt: skip

    return M("nav_msgs/msg/Path")(
        header=M("std_msgs/msg/Header")(stamp=stamp(T0), frame_id=frame),
        poses=[ps(n, T) for n, T in poses],
    )


def test_read_path_names_what_is_wrong():
    st, P, head = read_path(path_msg("map", [(T0, truth(3)), (T0 + DT, truth(4))]), "map")
    assert st.tolist() == [T0, T0 + DT] and head == T0
    np.testing.assert_allclose(P, np.stack([truth(3), truth(4)]), atol=1e-9)
    with pytest.raises(
        ValueError, match="header.frame_id is 'odom'; expected the world frame 'map'"
    ):
        read_path(path_msg("odom", [(T0, truth(0))]), "map")
    with pytest.raises(ValueError, match=r"poses\[0\].header.frame_id"):
        read_path(path_msg("map", [(T0, truth(0))], pose_frame="odom"), "map")
    bad = path_msg("map", [(T0, truth(0))])
    bad.poses[0].pose.orientation.w = float("nan")
    with pytest.raises(
        ValueError, match=r"poses\[0\].pose is not a finite position and unit quaternion"
    ):
        read_path(bad, "map")
    assert len(read_path(path_msg("", []), "map")[0]) == 0


def test_config_refuses_what_cannot_work():
    with pytest.raises(ValueError, match="map_odom' needs odom_frame"):
        Ros2InputConfig(corrections="map_odom", odom_frame=None)
    with pytest.raises(ValueError, match="needs poses from TF"):
        Ros2InputConfig(corrections="path", pose_topic="/odom")
    Ros2InputConfig(corrections="path", pose_topic="/odom", odom_frame=None)
    with pytest.raises(ValueError, match="nothing to build corrections from"):
        CorrectionBuilder(Ros2InputConfig())
