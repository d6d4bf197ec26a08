"""The data source: dataset replay, and how fast it plays."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, Field

from shared.config.base import StrictModel


def _registered_dataset(name: str) -> str:
    from shared.datasets.base import DATASETS

    if name not in DATASETS:
        raise ValueError(DATASETS.unknown(name))
    return name


class RosbagConfig(StrictModel):
    """Topics and frames of a ROS 2 bag read with ``rosbags`` (no ROS install needed)."""

    rgb_topic: str = "/camera/color/image_raw"
    """sensor_msgs/Image (rgb8, bgr8) or sensor_msgs/CompressedImage colour topic."""
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    """sensor_msgs/Image depth topic (16UC1 in depth units, or 32FC1 in metres)."""
    camera_info_topic: str = "/camera/color/camera_info"
    """sensor_msgs/CameraInfo of the colour camera."""
    pose_topic: str | None = None
    """nav_msgs/Odometry or geometry_msgs/PoseStamped giving the camera pose; when unset the
    pose comes from TF (``/tf``, ``/tf_static``)."""
    world_frame: str = "map"
    """TF frame the poses are expressed in."""
    camera_frame: str | None = None
    """TF frame of the camera (OpenCV optical axes); default: the image header's frame_id."""
    depth_scale: float = Field(1000.0, gt=0)
    """Depth units per metre of 16UC1 depth (1000 for millimetres)."""
    max_time_diff_s: float = Field(0.02, gt=0)
    """Colour, depth and pose are paired when their stamps differ by at most this."""


class TumConfig(StrictModel):
    """TUM RGB-D association."""

    max_time_diff_s: float = Field(0.02, gt=0)
    """Colour, depth and ground-truth stamps are associated within this (TUM's tool: 0.02)."""


class SourceConfig(StrictModel):
    """Dataset replay settings of the source service and of ``trackgraph map``."""

    dataset: Annotated[str, AfterValidator(_registered_dataset)] = "replica"
    """Reader for the sequence folder (docs/architecture.md, "Input formats")."""
    path: str | None = None
    """Sequence folder or bag; the command line's SEQ_DIR overrides it."""
    corrections: str | None = None
    """A JSON-lines file of pose corrections (one ``PoseCorrection`` per line, such as the
    ``corrections.jsonl`` of ``trackgraph synth --drift``), replayed as a SLAM back end would
    send them: each goes out on ``poses/correction`` right after the frame it is valid up to
    (or its own ``apply_after_frame``), and fusion applies it once it has fused that frame.
    None: no corrections."""
    mode: Literal["lossless", "live"] = "lossless"
    """lossless: block until subscribers keep up (offline mapping). live: publish at
    ``rate_hz`` and drop, counting, frames a slow subscriber cannot take."""
    rate_hz: float = Field(30.0, gt=0)
    """Publishing rate in live mode (Replica is 30 Hz)."""
    window_frames: int = Field(8, ge=1)
    """Lossless mode: frames the source may be ahead of the slowest stage that acknowledges
    them (``frames/ack``) among those alive; bounds every queue of the pipeline."""
    ack_from: list[str] = Field(default_factory=lambda: ["tracker", "fusion"])
    """Lossless mode: the stages whose acknowledgements pace the source, when they are
    running (a stage that is not alive does not hold it up)."""
    loops: int = Field(1, ge=1)
    """Replay the planned frames this many times, frame indices and time stamps running on
    (lap L's frame i is number L * N + i): soak and load tests of the live system."""
    hold_gone_s: float = Field(60.0, ge=0)
    """Lossless mode: a pacing stage that was running and vanished (a crash being restarted,
    a router restart) still holds the source this long, so frames are not replayed into the
    void; after it, the source goes on without that stage."""
    stride: int = Field(1, ge=1)
    """Use every Nth frame."""
    max_frames: int | None = Field(None, ge=1)
    """Stop after this many frames (after striding)."""
    rosbag: RosbagConfig = Field(default_factory=RosbagConfig)
    """Topics and TF frames when ``dataset: rosbag``."""
    tum: TumConfig = Field(default_factory=TumConfig)
    """Timestamp association when ``dataset: tum``."""
