"""``trackgraph source --ros2`` with ``ros2.input.corrections``: the SLAM's loop closures, as
a nav_msgs/Path or a map -> odom jump on the robot's topics, go out on ``poses/correction``,
and frames go out at their odometry pose so fusion counts each jump once."""

from __future__ import annotations

import numpy as np

from services.ros2.session import Ros2SourceSession
from shared.config import TrackGraphConfig
from shared.messages.frames import Frame
from shared.messages.poses import PoseCorrection
from shared.ros2.wire import InProcessRosWire
from shared.runtime.bus import InProcessBus
from shared.topics import Topics
from tests.services.ros2.test_ros2_source_session import (
    CAM,
    T0_NS,
    M,
    camera_info,
    header,
    image,
    step,
)

DT = 33_333_333


def transform(stamp_ns: int, parent: str, child: str, x: float):
    return M("geometry_msgs/msg/TransformStamped")(
        header=header(stamp_ns, parent), child_frame_id=child,
        transform=M("geometry_msgs/msg/Transform")(translation=M("geometry_msgs/msg/Vector3")(x=x, y=0.0, z=1.0),
                                                   rotation=M("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)),
    )  # fmt: skip


def stamp(ns: int):
    return M("builtin_interfaces/msg/Time")(sec=ns // 10**9, nanosec=ns % 10**9)


def path(poses: list[tuple[int, float]]):
    def ps(ns, x):
        return M("geometry_msgs/msg/PoseStamped")(
            header=M("std_msgs/msg/Header")(stamp=stamp(ns), frame_id="map"),
            pose=M("geometry_msgs/msg/Pose")(position=M("geometry_msgs/msg/Point")(x=x, y=0.0, z=1.0),
                                             orientation=M("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)),
        )  # fmt: skip

    return M("nav_msgs/msg/Path")(header=M("std_msgs/msg/Header")(stamp=stamp(poses[-1][0]), frame_id="map"),
                                  poses=[ps(n, x) for n, x in poses])  # fmt: skip


def rig(clock, mode: str):
    bus = InProcessBus(clock=clock)
    wire = InProcessRosWire()
    cfg = TrackGraphConfig.model_validate(
        {"ros2": {"input": {"corrections": mode, "corrections_min_period_s": 0.0}}}
    )
    s = Ros2SourceSession(bus, wire, cfg, clock=clock)
    frames: list[Frame] = []
    corrections: list[PoseCorrection] = []
    topics = Topics(cfg.robot_id)
    bus.subscribe(topics.frames, Frame, lambda env: frames.append(env.body))
    bus.subscribe(topics.poses_correction, PoseCorrection, lambda env: corrections.append(env.body))
    return s, bus, wire, cfg, frames, corrections


def send(wire, cfg, i: int, map_odom_x: float) -> None:
    inp = cfg.ros2.input
    st = T0_NS + i * DT
    tf = wire.publisher(inp.tf_topic, "tf2_msgs/msg/TFMessage")
    tf.put(
        M("tf2_msgs/msg/TFMessage")(
            transforms=[
                transform(st, "map", "odom", map_odom_x),
                transform(st, "odom", CAM, 0.1 * i),
            ]
        )
    )
    wire.publisher(inp.camera_info_topic, "sensor_msgs/msg/CameraInfo").put(camera_info(st))
    wire.publisher(inp.depth_topic, "sensor_msgs/msg/Image").put(image(st, i, depth=True))
    wire.publisher(inp.rgb_topic, "sensor_msgs/msg/Image").put(image(st, i))


def walk(s, bus, wire, cfg, clock, frames, map_odom_x: float = 0.0, settle: bool = True) -> None:
    """Frames ``frames`` sent and taken; ``settle``: then long enough for the last to be final."""
    for i in frames:
        send(wire, cfg, i, map_odom_x)
        step(s, bus, clock)
    if settle:
        step(s, bus, clock, 1.0)


def test_a_map_odom_jump_goes_out_as_a_correction_and_frames_keep_their_odometry_pose(clock):
    s, bus, wire, cfg, frames, corrections = rig(clock, "map_odom")
    try:
        walk(s, bus, wire, cfg, clock, range(10), settle=False)
        assert corrections == []
        walk(s, bus, wire, cfg, clock, range(10, 14), 0.25)  # the SLAM closes a loop: map -> odom jumps 25 cm
        assert [f.frame_index for f in frames] == list(range(14))
        # Every frame at its odometry pose (map -> odom of the first frame): the jump is not in them.
        for f in frames:
            np.testing.assert_allclose(
                f.T_world_cam[:3, 3], [0.1 * f.frame_index, 0.0, 2.0], atol=1e-6
            )
        assert len(corrections) == 1
        c = corrections[0]
        last = int(c.frames[-1])
        assert c.apply_after_frame == c.frame_index == last >= 9
        np.testing.assert_allclose(c.poses[-1][:3, 3], [0.1 * last + 0.25, 0.0, 2.0], atol=1e-6)
        # the first frame keeps its pose
        np.testing.assert_allclose(c.poses[0][:3, 3], [0.0, 0.0, 2.0], atol=1e-6)
        rep = s.book.report().figures["corrections"]
        assert rep["sent"] == 1 and rep["last_id"] == c.correction_id and rep["unplaced"] == 0
    finally:
        s.close()


def test_an_optimised_path_goes_out_as_a_correction_and_a_bad_one_is_counted(clock):
    s, bus, wire, cfg, frames, corrections = rig(clock, "path")
    try:
        walk(s, bus, wire, cfg, clock, range(10))
        assert len(frames) == 10
        pub = wire.publisher(cfg.ros2.input.corrections_path_topic, "nav_msgs/msg/Path")
        # the SLAM stretches the walk
        pub.put(path([(T0_NS + i * DT, 0.1 * i + 0.05 * i) for i in (0, 4, 9)]))
        step(s, bus, clock)
        assert len(corrections) == 1
        c = corrections[0]
        assert c.frames.tolist() == [0, 4, 9] and c.correction_id == T0_NS + 9 * DT
        np.testing.assert_allclose(c.poses[:, 0, 3], [0.0, 0.6, 1.35], atol=1e-6)
        bad = path([(T0_NS, 0.0)])
        bad.header.frame_id = "odom"
        pub.put(bad)
        step(s, bus, clock)
        rep = s.book.report()
        assert len(corrections) == 1 and rep.figures["corrections"]["rejected"] == 1
    finally:
        s.close()


def test_without_corrections_nothing_is_subscribed_or_changed(clock):
    s, bus, wire, cfg, frames, corrections = rig(clock, "none")
    try:
        walk(s, bus, wire, cfg, clock, range(3), 0.5)
        assert corrections == [] and "corrections" not in s.book.report().figures
        np.testing.assert_allclose(
            frames[2].T_world_cam[:3, 3], [0.7, 0.0, 2.0], atol=1e-6
        )  # TF's pose as it came
    finally:
        s.close()
