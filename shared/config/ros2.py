"""ROS 2 on the wire: which convention, which topics, which frames (docs/ros2.md).

TrackGraph speaks to a ROS 2 graph directly over Zenoh, with no ROS install: the robot's
``rmw_zenoh`` router (keys ``<domain_id>/<topic>/<type>/<RIHS01 hash>``, liveliness tokens
under ``@ros2_lv``) or a ``zenoh-bridge-ros2dds`` in front of DDS (the topic name is the key).
Payloads are CDR either way, encoded and decoded by rosbags' typestore.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from shared.config.base import StrictModel

Distro = Literal["humble", "iron", "jazzy", "kilted"]

COLOUR_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
DEPTH_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped")


def _topic(v: str) -> str:
    """A ROS 2 topic name: absolute, no empty or trailing parts (``/camera/color/image_raw``)."""
    if not v.startswith("/") or v.endswith("/") or "//" in v or any(c.isspace() for c in v):
        raise ValueError(f"{v!r} is not an absolute ROS 2 topic name (like /camera/color/image_raw)")
    return v


class Ros2LinkConfig(StrictModel):
    """How TrackGraph joins the robot's ROS 2 graph over Zenoh."""

    convention: Literal["rmw_zenoh", "bridge"] = "rmw_zenoh"
    """``rmw_zenoh``: ROS 2 itself runs over Zenoh (keys carry the domain, type and RIHS01 type
    hash; TrackGraph announces its publishers and subscribers with liveliness tokens, so
    ``ros2 topic list`` shows them). ``bridge``: a ``zenoh-bridge-ros2dds`` exposes a DDS graph,
    the topic name (without its leading '/') is the key."""
    domain_id: int = Field(0, ge=0, le=232)
    """ROS_DOMAIN_ID of the robot's graph (rmw_zenoh puts it first in every key)."""
    distro: Distro = "jazzy"
    """ROS 2 distribution whose message definitions (and so RIHS01 type hashes) the robot
    uses. Type hashes exist from Iron on; Humble's rmw_zenoh sends ``TypeHashNotSupported``,
    which subscribers accept like any hash."""
    connect: list[str] = Field(default_factory=list)
    """Zenoh endpoints of the robot's router (``tcp/192.168.1.10:7447``). Empty: the same
    session as TrackGraph's own traffic (``transport``), which suits one router for both."""
    node_name: str = "trackgraph"
    """ROS 2 node name TrackGraph's endpoints appear under (``ros2 node list``)."""
    namespace: str = "/"
    """ROS 2 namespace of that node."""
    bridge_prefix: str = ""
    """``bridge`` convention: the bridge's ``namespace``/key prefix, if it was started with one
    (keys are ``<prefix>/<topic>``)."""
    max_payload_bytes: int = Field(64 * 2**20, gt=0)
    """Largest CDR payload decoded; a bigger one is refused and counted before parsing."""

    @field_validator("node_name")
    @classmethod
    def _node_name(cls, v: str) -> str:
        if not v or not all(c.isalnum() or c == "_" for c in v) or v[0].isdigit():
            raise ValueError(f"{v!r} is not a ROS 2 node name (letters, digits and '_', not starting with a digit)")
        return v

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, v: str) -> str:
        return v if v == "/" else _topic(v)


class Ros2InputConfig(StrictModel):
    """The robot's camera and pose topics that ``trackgraph source --ros2`` turns into frames."""

    rgb_topic: str = "/camera/color/image_raw"
    """Colour images: rgb8, bgr8, rgba8, bgra8 or mono8 Image, or a JPEG/PNG CompressedImage."""
    rgb_type: Literal["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"] = "sensor_msgs/msg/Image"
    """Message type of ``rgb_topic`` (``.../compressed`` topics are CompressedImage). Under
    rmw_zenoh the type in the key wins; the bridge's keys carry none, so this says it."""
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    """Depth registered to the colour image: 16UC1 (``depth_scale`` units, mm by default) or
    32FC1 (m) Image, or a ``compressedDepth`` CompressedImage."""
    depth_type: Literal["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"] = "sensor_msgs/msg/Image"
    """Message type of ``depth_topic`` (``.../compressedDepth`` topics are CompressedImage)."""
    camera_info_topic: str = "/camera/color/camera_info"
    """sensor_msgs/CameraInfo of the colour camera (K and the image size)."""
    pose_topic: str | None = None
    """nav_msgs/Odometry or geometry_msgs/PoseStamped with the pose of the camera's optical
    frame in ``world_frame``. None: the pose comes from ``/tf`` and ``/tf_static``."""
    pose_type: Literal["nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"] = "nav_msgs/msg/Odometry"
    """Message type of ``pose_topic``."""
    tf_topic: str = "/tf"
    """Dynamic transforms (tf2_msgs/TFMessage)."""
    tf_static_topic: str = "/tf_static"
    """Static transforms (tf2_msgs/TFMessage, latched)."""
    world_frame: str = "map"
    """TF frame the map is built in: camera poses are ``T_world_camera``."""
    camera_frame: str | None = None
    """TF frame of the camera's optical axes (z forward, x right, y down; REP 103's
    ``*_optical_frame``). None: the colour image header's frame_id."""
    depth_scale: float = Field(1000.0, gt=0)
    """16UC1 depth units per metre (1000: millimetres, the RealSense/OAK convention)."""
    slop_s: float = Field(0.02, gt=0)
    """Approximate-time sync: colour and depth pair when their stamps differ by at most this
    (message_filters' ``slop``; TUM's association uses 0.02 s too)."""
    tf_tolerance_s: float = Field(0.05, ge=0)
    """A TF edge sampled no nearer than this to a frame's stamp, on either side, cannot be
    interpolated there: the frame waits for newer TF, and is rejected once ``max_wait_s`` is up."""
    max_wait_s: float = Field(0.5, gt=0)
    """How long a colour image waits for its depth and pose before it is given up (counted
    as unsynchronised); also how long the TF buffer keeps dynamic transforms beyond it."""
    tf_buffer_s: float = Field(10.0, gt=0)
    """Seconds of dynamic TF history kept (tf2's default cache is 10 s)."""
    camera_info_timeout_s: float = Field(3.0, gt=0)
    """Colour images for this long with no CameraInfo: an error in the status and the log
    naming ``camera_info_topic`` (images keep being counted until it comes)."""
    corrections: Literal["none", "path", "map_odom"] = "none"
    """Loop closures from the robot's SLAM, sent on as ``poses/correction`` (docs/ros2.md,
    "Loop closures"). ``path``: a ``nav_msgs/Path`` of optimised poses on
    ``corrections_path_topic`` (rtabmap's ``mapPath``, a pose-graph optimiser's output); each
    pose states the frame nearest its stamp, the frames between follow by their odometry.
    ``map_odom``: a change of the ``world_frame -> odom_frame`` transform (slam_toolbox,
    AMCL) is spread over the frames placed since the previous change, from none of it at the
    first to all of it at the newest, by distance travelled. ``none``: poses are final."""
    corrections_path_topic: str = "/slam/optimized_path"
    """``path``: the nav_msgs/Path topic, its poses in ``world_frame``."""
    corrections_body_frame: str | None = None
    """``path``: the TF frame whose poses the Path holds (``base_link``); the camera's offset
    from it is taken from TF at each frame's stamp. None: the Path holds camera poses."""
    odom_frame: str | None = "odom"
    """With corrections: the odometry frame (REP 105) between ``world_frame`` and the camera.
    Frames then go out at their odometry pose (the first frame's ``world -> odom`` times
    ``odom -> camera``), and the SLAM's view of the map reaches the map as corrections only;
    otherwise a map -> odom jump would count twice (fusion moves frames fused after a
    correction by its fix). None (``path`` only): TF's poses of the camera in ``world_frame``
    never jump (odometry published straight into it)."""
    corrections_min_m: float = Field(0.02, ge=0)
    """A correction goes out only when it moves some frame's camera by more than this (m)
    or ``corrections_min_rad``: each one costs fusion a pass over the map (about 1 s for
    900 frames), so the SLAM's small continual adjustments go out in batches."""
    corrections_min_rad: float = Field(0.01, ge=0)
    """The rotation counterpart of ``corrections_min_m`` (rad)."""
    corrections_min_period_s: float = Field(1.0, ge=0)
    """At most one correction per this many seconds; a newer one waiting goes out after it."""
    window_frames: int = Field(4, ge=1)
    """Frames the source may be ahead of the slowest stage that acknowledges them
    (``source.ack_from``); a newer synchronised frame then replaces the held one (latest
    wins) and the replaced frame is counted as dropped."""

    @field_validator("rgb_topic", "depth_topic", "camera_info_topic", "tf_topic", "tf_static_topic")
    @classmethod
    def _topics(cls, v: str) -> str:
        return _topic(v)

    @field_validator("corrections_path_topic")
    @classmethod
    def _path_topic(cls, v: str) -> str:
        return _topic(v)

    @field_validator("pose_topic")
    @classmethod
    def _pose_topic(cls, v: str | None) -> str | None:
        return None if v is None else _topic(v)

    @model_validator(mode="after")
    def _distinct(self) -> Ros2InputConfig:
        """Colour, depth and camera info are three different topics."""
        names = [self.rgb_topic, self.depth_topic, self.camera_info_topic]
        if len(set(names)) != len(names):
            raise ValueError(f"rgb_topic, depth_topic and camera_info_topic must differ (got {', '.join(names)})")
        if self.corrections == "map_odom" and self.odom_frame is None:
            raise ValueError("corrections: 'map_odom' needs odom_frame (the frame map -> odom ends in)")
        uses_tf = self.corrections == "map_odom" or self.corrections_body_frame is not None or self.odom_frame is not None
        if self.corrections != "none" and self.pose_topic is not None and uses_tf:
            raise ValueError(f"corrections: {self.corrections!r} with odom_frame or corrections_body_frame needs poses from "
                             "TF (pose_topic None); with a pose_topic, use 'path' with odom_frame: null")  # fmt: skip
        return self


class Ros2OutputConfig(StrictModel):
    """What the ``ros2`` service publishes for RViz and the robot's planner, and the query
    topics it answers."""

    frame_id: str = "map"
    """Frame id of every marker, path and pose published (the map's world frame)."""
    markers_topic: str = "/trackgraph/scene_graph"
    """visualization_msgs/MarkerArray of segments (boxes, centroids, ids), places, rooms and
    graph edges, republished on every graph delta."""
    path_topic: str = "/trackgraph/trajectory"
    """nav_msgs/Path of the camera poses mapped so far."""
    query_topic: str = "/trackgraph/query"
    """std_msgs/String requests: a JSON ``QueryRequest`` (``{"text": "red armchair"}``)."""
    reply_topic: str = "/trackgraph/query/reply"
    """std_msgs/String replies: the JSON ``QueryReply``, with the request's ``id`` if it had one."""
    hits_markers_topic: str = "/trackgraph/query/markers"
    """visualization_msgs/MarkerArray of the last query's hits (boxes and ranks)."""
    hits_poses_topic: str = "/trackgraph/query/poses"
    """geometry_msgs/PoseArray of the last query's hit centroids, best first (goals for a
    planner)."""
    markers_min_period_s: float = Field(0.5, ge=0)
    """Marker arrays go out at most this often (the newest graph is sent after the pause):
    RViz redraws a few hundred markers per message, a delta every frame would flood it."""
    query_timeout_s: float = Field(5.0, gt=0)
    """How long a ROS query waits for the query service before it is answered with an error."""
    show_ids: bool = True
    """Text markers with segment ids (and room names) above the boxes."""

    @field_validator("markers_topic", "path_topic", "query_topic", "reply_topic", "hits_markers_topic", "hits_poses_topic")
    @classmethod
    def _topics(cls, v: str) -> str:
        return _topic(v)


class Ros2Config(StrictModel):
    """ROS 2 interop: the link, the live input and the output topics."""

    link: Ros2LinkConfig = Field(default_factory=Ros2LinkConfig)
    """Convention, domain and router."""
    input: Ros2InputConfig = Field(default_factory=Ros2InputConfig)
    """Camera and pose topics in."""
    output: Ros2OutputConfig = Field(default_factory=Ros2OutputConfig)
    """Markers, path and query topics out."""
