"""Benchmark: ``trackgraph source --ros2`` at Replica resolution (1200x680), 30 Hz.

    python benchmarks/ros2_source.py [--seconds 10] [--quick]

Two parts, both with colour, depth, CameraInfo and TF per frame as a RealSense driver and a
SLAM back end send them:

- core: decode and synchronisation time per frame in the
  :class:`~services.ros2.live.FrameAssembler`, from CDR bytes to a TrackGraph ``Frame``, for raw
  (rgb8 + 16UC1) and compressed (JPEG + compressedDepth PNG) images;
- live: the whole source node over Zenoh on loopback. A publisher plays a robot at 30 Hz in
  the rmw_zenoh convention for ``--seconds``; what the node published, dropped (latest
  wins) and rejected is counted. No pacing stage runs, so a drop means the source itself fell
  behind.

Writes benchmarks/out/ros2_source.json and prints a table.
"""

from __future__ import annotations

import argparse
import io
import json
import platform
import socket
import struct
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.config.ros2 import Ros2InputConfig  # noqa: E402
from shared.ros2.types import encode, msg_class  # noqa: E402

OUT = Path(__file__).resolve().parent / "out"
W, H, RATE = 1200, 680, 30.0
T0_NS = 1_700_000_000 * 10**9
OPTICAL = "camera_color_optical_frame"


def _header(stamp_ns: int, frame_id: str):
    t = msg_class("builtin_interfaces/msg/Time")(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return msg_class("std_msgs/msg/Header")(stamp=t, frame_id=frame_id)


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A textured colour image and a smooth depth map, like an indoor frame (noise-free
    gradients compress like real images; pure noise would not)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    rgb = np.stack([(x / W * 255), (y / H * 255), ((x + y) % 64 * 4)], axis=-1)
    rgb += rng.normal(0, 6, rgb.shape)
    depth_m = 1.5 + 2.5 * (y / H) + 0.3 * np.sin(x / 90.0)
    return np.clip(rgb, 0, 255).astype(np.uint8), np.round(depth_m * 1000).astype(np.uint16)


def _frame_messages(i: int, rgb: np.ndarray, depth: np.ndarray, compressed: bool) -> list[tuple[str, str, bytes]]:
    """(topic, type, CDR) of one frame: TF, CameraInfo, depth, colour."""
    from PIL import Image

    st = T0_NS + int(i * 1e9 / RATE)
    tf = msg_class("geometry_msgs/msg/TransformStamped")(
        header=_header(st, "map"), child_frame_id=OPTICAL,
        transform=msg_class("geometry_msgs/msg/Transform")(
            translation=msg_class("geometry_msgs/msg/Vector3")(x=0.01 * i, y=0.0, z=1.2),
            rotation=msg_class("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)),
    )  # fmt: skip
    tfm = msg_class("tf2_msgs/msg/TFMessage")(transforms=[tf])
    roi = msg_class("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    info = msg_class("sensor_msgs/msg/CameraInfo")(
        header=_header(st, OPTICAL), height=H, width=W, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([600.0, 0, 599.5, 0, 600.0, 339.5, 0, 0, 1]), r=np.eye(3).reshape(-1),
        p=np.array([600.0, 0, 599.5, 0, 0, 600.0, 339.5, 0, 0, 0, 1, 0]), binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip
    if compressed:
        buf = io.BytesIO()
        Image.fromarray(rgb).save(buf, format="JPEG", quality=90)
        colour = msg_class("sensor_msgs/msg/CompressedImage")(header=_header(st, OPTICAL), format="rgb8; jpeg compressed bgr8",
                                                              data=np.frombuffer(buf.getvalue(), np.uint8))  # fmt: skip
        buf = io.BytesIO()
        Image.fromarray(depth).save(buf, format="PNG", compress_level=1)
        depth_msg = msg_class("sensor_msgs/msg/CompressedImage")(
            header=_header(st, OPTICAL), format="16UC1; compressedDepth png",
            data=np.frombuffer(struct.pack("<iff", 0, 0.0, 0.0) + buf.getvalue(), np.uint8),
        )  # fmt: skip
        ctype = dtype = "sensor_msgs/msg/CompressedImage"
    else:
        Img = msg_class("sensor_msgs/msg/Image")
        colour = Img(header=_header(st, OPTICAL), height=H, width=W, encoding="rgb8", is_bigendian=0, step=W * 3, data=rgb.reshape(-1))
        depth_msg = Img(header=_header(st, OPTICAL), height=H, width=W, encoding="16UC1", is_bigendian=0, step=W * 2,
                        data=depth.view(np.uint8).reshape(-1))  # fmt: skip
        ctype = dtype = "sensor_msgs/msg/Image"
    cfg = Ros2InputConfig()
    return [
        (cfg.tf_topic, "tf2_msgs/msg/TFMessage", encode(tfm)),
        (cfg.camera_info_topic, "sensor_msgs/msg/CameraInfo", encode(info)),
        (cfg.depth_topic, dtype, encode(depth_msg)),
        (cfg.rgb_topic, ctype, encode(colour)),
    ]


def _input_config(compressed: bool) -> Ros2InputConfig:
    t = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    return Ros2InputConfig(rgb_type=t, depth_type=t)


def bench_core(frames: int, compressed: bool) -> dict:
    """Decode + sync time per frame in the assembler (one thread, no network)."""
    from services.ros2.live import FrameAssembler

    rng = np.random.default_rng(0)
    rgb, depth = _scene(rng)
    msgs = [_frame_messages(i, rgb, depth, compressed) for i in range(frames + 1)]
    asm = FrameAssembler(_input_config(compressed))
    times, out = [], 0
    for i in range(frames + 1):
        now = i / RATE
        t0 = time.perf_counter()
        for topic, ros_type, payload in msgs[i]:
            asm.on_message(topic, payload, now, ros_type)
        got = asm.poll(now)
        dt = time.perf_counter() - t0
        out += len(got)
        if i > 0:  # the first frame warms the decoders up
            times.append(dt * 1e3)
    ms = np.array(times)
    return {
        "case": "compressed (JPEG + compressedDepth)" if compressed else "raw (rgb8 + 16UC1)",
        "frames": frames, "emitted": out, "bytes_per_frame": sum(len(p) for _, _, p in msgs[0]),
        "ms_mean": round(float(ms.mean()), 2), "ms_p50": round(float(np.median(ms)), 2), "ms_p95": round(float(np.percentile(ms, 95)), 2),
        "max_hz": round(1000.0 / float(ms.mean()), 1), "rejected": {k: v for k, v in asm.stats.rejected.items() if v},
    }  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bench_live(seconds: float, compressed: bool) -> dict:
    """The source node on loopback Zenoh, fed at 30 Hz by an rmw_zenoh-convention publisher."""
    from services.ros2.node import Ros2SourceNode
    from services.router import run_router
    from shared.config import TrackGraphConfig
    from shared.messages.frames import Frame
    from shared.ros2.link import ZenohRosWire
    from shared.topics import Topics
    from shared.transport import ZenohBus, open_session

    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    t = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    cfg = TrackGraphConfig.model_validate({
        "transport": {"mode": "client", "connect": [endpoint], "shared_memory": False},
        "ros2": {"input": {"rgb_type": t, "depth_type": t}},
    })  # fmt: skip
    stop = threading.Event()
    router = threading.Thread(target=run_router, args=(cfg.transport.model_copy(update={"mode": "router", "connect": [], "listen": [endpoint]}), stop), daemon=True)
    router.start()
    time.sleep(0.5)
    rng = np.random.default_rng(0)
    rgb, depth = _scene(rng)
    n = int(seconds * RATE)
    msgs = [_frame_messages(i, rgb, depth, compressed) for i in range(n)]
    received = []
    session = open_session(cfg.transport)
    robot = ZenohRosWire(session, cfg.ros2.link.model_copy(update={"node_name": "robot"}))
    sink = ZenohBus.open(cfg.transport, cfg.robot_id)
    node = None
    try:
        sink.subscribe(Topics(cfg.robot_id).frames, Frame, lambda env: received.append(time.monotonic()), capacity=1024)
        node = Ros2SourceNode(cfg)
        pubs = {topic: robot.publisher(topic, ros_type) for topic, ros_type, _ in msgs[0]}
        time.sleep(1.0)
        t0 = time.monotonic()
        late = 0
        for i, frame in enumerate(msgs):
            due = t0 + i / RATE
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            else:
                late += 1
            for topic, _, payload in frame:
                pubs[topic].put_raw(payload)
        sent_s = time.monotonic() - t0
        time.sleep(1.0)
        stats = node.stats()
    finally:
        if node is not None:
            node.close()
        sink.close()
        robot.close()
        session.close()
        stop.set()
        router.join(timeout=10)
    rej = {k: v for k, v in stats.rejected.items() if v}
    return {
        "case": "compressed (JPEG + compressedDepth)" if compressed else "raw (rgb8 + 16UC1)",
        "sent": n, "sent_hz": round(n / sent_s, 1), "publisher_late": late, "published": stats.published,
        "dropped": stats.dropped, "rejected": rej, "received_downstream": len(received),
        "published_hz": round(stats.published / sent_s, 1),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="live part: seconds of 30 Hz traffic")
    ap.add_argument("--frames", type=int, default=60, help="core part: frames timed")
    ap.add_argument("--quick", action="store_true", help="10 frames and 3 s")
    ap.add_argument("--out", type=Path, default=OUT / "ros2_source.json")
    args = ap.parse_args(argv)
    frames, seconds = (10, 3.0) if args.quick else (args.frames, args.seconds)
    core = [bench_core(frames, c) for c in (False, True)]
    live = [bench_live(seconds, c) for c in (False, True)]
    result = {"resolution": f"{W}x{H}", "rate_hz": RATE, "machine": platform.platform(), "python": platform.python_version(),
              "core": core, "live": live}  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"\ntrackgraph source --ros2 at {W}x{H}, {RATE:.0f} Hz ({platform.machine()})\n")
    print(f"{'decode + sync per frame':40s} {'mean ms':>8s} {'p50':>7s} {'p95':>7s} {'max Hz':>7s} {'KB/frame':>9s}")
    for r in core:
        print(f"{r['case']:40s} {r['ms_mean']:8.2f} {r['ms_p50']:7.2f} {r['ms_p95']:7.2f} {r['max_hz']:7.1f} {r['bytes_per_frame'] / 1024:9.0f}")
    print(f"\n{'live over Zenoh (loopback)':40s} {'sent':>6s} {'pub':>6s} {'drop':>6s} {'Hz out':>7s} rejected")
    for r in live:
        print(f"{r['case']:40s} {r['sent']:6d} {r['published']:6d} {r['dropped']:6d} {r['published_hz']:7.1f} {r['rejected'] or '-'}")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
