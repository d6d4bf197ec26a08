"""``trackgraph source --ros2`` as a session: ROS 2 messages in through a wire, TrackGraph
frames out on a bus, paced by the pipeline's acks with the newest frame winning; the fault
cases the issue names, counted in the status and logged."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from services.ros2.session import Ros2SourceSession
from shared.config import TrackGraphConfig
from shared.messages.frames import EndOfSequence, Frame, FrameAck
from shared.ros2.types import encode, msg_class
from shared.ros2.wire import InProcessRosWire
from shared.runtime.bus import InProcessBus
from shared.topics import Topics

W, H = 32, 24
T0_NS = 1_700_000_000 * 10**9
CAM = "camera_color_optical_frame"


def M(name: str):
    return msg_class(name)


def header(stamp_ns: int, frame_id: str = CAM):
    return M("std_msgs/msg/Header")(stamp=M("builtin_interfaces/msg/Time")(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id)


def camera_info(stamp_ns: int):
    roi = M("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return M("sensor_msgs/msg/CameraInfo")(
        header=header(stamp_ns), height=H, width=W, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([30.0, 0, 15.5, 0, 30.0, 11.5, 0, 0, 1]), r=np.eye(3).reshape(-1),
        p=np.array([30.0, 0, 15.5, 0, 0, 30.0, 11.5, 0, 0, 0, 1, 0]), binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def image(stamp_ns: int, i: int, depth: bool = False):
    if depth:
        a = np.full((H, W), 1500 + i, np.uint16)
        return M("sensor_msgs/msg/Image")(header=header(stamp_ns), height=H, width=W, encoding="16UC1", is_bigendian=0, step=W * 2,
                                          data=a.view(np.uint8).reshape(-1))  # fmt: skip
    a = np.full((H, W, 3), i % 256, np.uint8)
    return M("sensor_msgs/msg/Image")(header=header(stamp_ns), height=H, width=W, encoding="rgb8", is_bigendian=0, step=W * 3, data=a.reshape(-1))


def tf(stamp_ns: int, x: float):
    t = M("geometry_msgs/msg/TransformStamped")(
        header=header(stamp_ns, "map"), child_frame_id=CAM,
        transform=M("geometry_msgs/msg/Transform")(translation=M("geometry_msgs/msg/Vector3")(x=x, y=0.0, z=1.0),
                                                   rotation=M("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)),
    )  # fmt: skip
    return M("tf2_msgs/msg/TFMessage")(transforms=[t])


@pytest.fixture
def rig(clock):
    bus = InProcessBus(clock=clock)
    wire = InProcessRosWire()
    cfg = TrackGraphConfig()
    alive: set[str] = set()
    s = Ros2SourceSession(bus, wire, cfg, alive=lambda: set(alive), clock=clock)
    frames: list[Frame] = []
    ends: list[EndOfSequence] = []
    topics = Topics(cfg.robot_id)
    bus.subscribe(topics.frames, Frame, lambda env: frames.append(env.body))
    bus.subscribe(topics.end_of_sequence, EndOfSequence, lambda env: ends.append(env.body))
    acks = bus.publisher(topics.frame_ack, FrameAck)
    yield s, bus, wire, clock, cfg, alive, frames, ends, acks
    s.close()


def send(wire: InProcessRosWire, cfg: TrackGraphConfig, i: int, *, depth: bool = True, info: bool = True, colour: bool = True,
         tf_stamp_ns: int | None = None, stamp_ns: int | None = None) -> None:  # fmt: skip
    inp = cfg.ros2.input
    st = T0_NS + i * 33_333_333 if stamp_ns is None else stamp_ns
    pub = {t: wire.publisher(t, ty) for t, ty in [(inp.tf_topic, "tf2_msgs/msg/TFMessage"), (inp.camera_info_topic, "sensor_msgs/msg/CameraInfo"),
                                                   (inp.depth_topic, "sensor_msgs/msg/Image"), (inp.rgb_topic, "sensor_msgs/msg/Image")]}  # fmt: skip
    pub[inp.tf_topic].put(tf(st if tf_stamp_ns is None else tf_stamp_ns, 0.1 * i))
    if info:
        pub[inp.camera_info_topic].put(camera_info(st))
    if depth:
        pub[inp.depth_topic].put(image(st, i, depth=True))
    if colour:
        pub[inp.rgb_topic].put(image(st, i))


def step(s, bus, clock, dt: float = 1 / 30) -> None:
    clock.t += dt
    s.tick(clock())
    bus.drain()


def test_frames_out_with_pose_intrinsics_and_an_end(rig):
    s, bus, wire, clock, cfg, alive, frames, ends, acks = rig
    for i in range(5):
        send(wire, cfg, i)
        step(s, bus, clock)
    step(s, bus, clock, 1.0)  # the last pair is final once max_wait_s has passed
    assert [f.frame_index for f in frames] == [0, 1, 2, 3, 4]
    f = frames[2]
    assert f.rgb.shape == (H, W, 3) and int(f.rgb[0, 0, 0]) == 2
    assert f.depth.dtype == np.uint16 and int(f.depth[0, 0]) == 1502 and f.depth_scale == 1000.0
    assert (f.intrinsics.fx, f.intrinsics.cx, f.intrinsics.width) == (30.0, 15.5, W)
    np.testing.assert_allclose(f.T_world_cam[:3, 3], [0.2, 0.0, 1.0], atol=1e-9)
    assert abs(f.time_s - (T0_NS + 2 * 33_333_333) * 1e-9) < 1e-6
    s.finish()
    s.finish()  # once
    bus.drain()
    assert len(ends) == 1 and ends[0].frames_published == 5 and ends[0].last_frame_index == 4
    rep = s.book.report()
    assert rep.figures["published"] == 5 and rep.figures["dropped"] == 0
    assert rep.figures["ros2"]["received"][cfg.ros2.input.rgb_topic] == 5


def test_a_busy_pipeline_gets_the_newest_frame_and_drops_are_counted(rig):
    s, bus, wire, clock, cfg, alive, frames, ends, acks = rig
    alive |= {"tracker", "fusion"}  # both pace the source (source.ack_from)
    window = cfg.ros2.input.window_frames
    for i in range(12):
        send(wire, cfg, i)
        step(s, bus, clock)
    step(s, bus, clock, 1.0)
    # Nothing acknowledged: only the first `window` frames may go; of the rest, one is held.
    assert [f.frame_index for f in frames] == list(range(window))
    assert s.dropped == 12 - window - 1 and len(s.waiting) == 1
    for stage in ("tracker", "fusion"):
        acks.put(FrameAck(frame_index=0, service=stage))
    bus.drain()
    step(s, bus, clock)
    assert frames[-1].frame_index == 11  # the newest, not the oldest held
    # The dropped frames are no gap: acks of what was sent keep it going.
    for i in range(12, 15):
        send(wire, cfg, i)
        step(s, bus, clock)
    step(s, bus, clock, 1.0)
    assert frames[-1].frame_index == 11 and len(s.waiting) == 1  # window full again
    for stage in ("tracker", "fusion"):
        acks.put(FrameAck(frame_index=11, service=stage))
    bus.drain()
    step(s, bus, clock)
    assert frames[-1].frame_index == 14
    s.finish()
    bus.drain()
    assert ends[0].frames_published == window + 2 and ends[0].frames_dropped == 15 - window - 2
    assert ends[0].last_frame_index == 14


def test_depth_stops_for_five_seconds_and_mapping_goes_on(rig):
    s, bus, wire, clock, cfg, alive, frames, ends, acks = rig
    for i in range(150 + 10):
        send(wire, cfg, i, depth=not (5 <= i < 155))  # 150 frames = 5 s of colour without depth
        step(s, bus, clock)
    step(s, bus, clock, 1.0)
    rejected = s.book.report().figures["ros2"]["rejected"]
    assert rejected["no_depth"] + rejected.get("superseded", 0) == 150, rejected
    got = [int(f.rgb[0, 0, 0]) for f in frames]
    assert got[:5] == [0, 1, 2, 3, 4]
    assert [(i % 256) for i in range(155, 160)] == got[-5:]  # back as soon as depth is


def test_tf_back_in_time_is_rejected_and_counted(rig, caplog):
    s, bus, wire, clock, cfg, alive, frames, ends, acks = rig
    for i in range(6):
        send(wire, cfg, i)
        step(s, bus, clock)
    # Frame 6 (0.3 s on) comes with a TF stamped two seconds before the last one: tf2's
    # TF_OLD_DATA. No TF is near its stamp then, and none may stand in for it.
    t6 = T0_NS + 5 * 33_333_333 + 300_000_000
    with caplog.at_level(logging.WARNING):
        send(wire, cfg, 6, tf_stamp_ns=T0_NS - 2 * 10**9, stamp_ns=t6)
        step(s, bus, clock)
        for _ in range(30):
            step(s, bus, clock)
    rejected = s.book.report().figures["ros2"]["rejected"]
    assert rejected.get("out_of_order", 0) + rejected.get("tf_backwards", 0) >= 1
    assert all(abs(f.time_s - t6 * 1e-9) > 1e-6 for f in frames)
    assert len(frames) == 6
    assert any("TF" in r.getMessage() for r in caplog.records)


def test_camera_info_never_comes(rig, caplog):
    s, bus, wire, clock, cfg, alive, frames, ends, acks = rig
    timeout = cfg.ros2.input.camera_info_timeout_s
    assert timeout < 5.0  # the issue: an error within 5 s
    with caplog.at_level(logging.ERROR, logger="services.ros2.session"):
        for i in range(int(30 * 4.5)):
            send(wire, cfg, i, info=False)
            step(s, bus, clock)
    assert not frames
    err = s.book.report().figures["error"]
    assert err is not None and cfg.ros2.input.camera_info_topic in err and "CameraInfo" in err
    assert any(cfg.ros2.input.camera_info_topic in r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)
    assert s.book.report().figures["ros2"]["rejected"]["no_camera_info"] >= 100
    assert s.book.report().errors >= 1
    # It comes after all: the error clears and frames flow.
    for i in range(200, 204):
        send(wire, cfg, i)
        step(s, bus, clock)
    step(s, bus, clock, 1.0)
    assert frames and s.book.report().figures["error"] is None


def test_ten_thousand_hostile_payloads_are_counted_not_fatal(rig):
    s, bus, wire, clock, cfg, alive, frames, ends, acks = rig
    rng = np.random.default_rng(7)
    inp = cfg.ros2.input
    topics = [inp.rgb_topic, inp.depth_topic, inp.camera_info_topic, inp.tf_topic]
    valid = {inp.rgb_topic: encode(image(T0_NS, 0)), inp.depth_topic: encode(image(T0_NS, 0, depth=True)),
             inp.camera_info_topic: encode(camera_info(T0_NS)), inp.tf_topic: encode(tf(T0_NS, 0.0))}  # fmt: skip
    types = {inp.rgb_topic: "sensor_msgs/msg/Image", inp.depth_topic: "sensor_msgs/msg/Image",
             inp.camera_info_topic: "sensor_msgs/msg/CameraInfo", inp.tf_topic: "tf2_msgs/msg/TFMessage"}  # fmt: skip
    n = 10_000
    for k in range(n):
        topic = topics[k % 4]
        if k % 2:
            payload = rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
        else:
            b = bytearray(valid[topic])
            for _ in range(int(rng.integers(1, 6))):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
            payload = bytes(b[: int(rng.integers(4, len(b) + 1))])
        wire.deliver(topic, payload, types[topic])
        if k % 100 == 0:
            step(s, bus, clock)
    step(s, bus, clock, 2.0)
    st = s.assembler.stats
    assert sum(st.received.values()) == n
    assert sum(st.accepted.values()) + sum(st.rejected.values()) + st.pending == n
    assert st.rejected["bad_payload"] > n / 2
    assert s.book.counts("ros2")["received"] == n
    # The source still works afterwards.
    before = len(frames)
    for i in range(100, 104):
        send(wire, cfg, i)
        step(s, bus, clock)
    step(s, bus, clock, 1.0)
    assert len(frames) > before
