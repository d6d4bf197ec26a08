"""A paired colour and depth image and a pose made into a :class:`Frame`, pixels decoded last.

Everything that can still be wrong once a pair is complete (sizes that disagree, a pose that is
no rigid transform, pixels the decoder refuses) is counted and logged here, never raised.
"""

from __future__ import annotations

from services.ros2.live.camera_info import CameraInfoGate
from services.ros2.live.clock import NS
from services.ros2.live.stats import Ledger
from services.ros2.live.sync import PendingImage
from shared.datasets.base import DatasetError
from shared.datasets.files import checked_pose
from shared.datasets.rosimage import UnsupportedEncodingError, decode_colour, decode_depth
from shared.geometry import Intrinsics, Pose
from shared.messages.frames import Frame


def build_frame(
    index: int, c: PendingImage, d: PendingImage, T: Pose, camera: CameraInfoGate, depth_scale: float, pose_source: str,
    ledger: Ledger,
) -> Frame | None:  # fmt: skip
    """Frame ``index`` of colour ``c`` and depth ``d`` at ``T`` (T_world_cam, (4, 4)), with the
    camera info's intrinsics; None (counted under :data:`~services.ros2.live.stats.REASONS`)
    when they do not make one. ``pose_source`` names where ``T`` came from, for the log."""
    if c.size != d.size:
        ledger.size_error(f"{d.where}: depth is {d.size[0]}x{d.size[1]}, colour {c.where} is "
                          f"{c.size[0]}x{c.size[1]} (publish depth aligned to colour)")  # fmt: skip
        return None
    fx, fy, cx, cy, iw, ih = camera.info  # type: ignore[misc]  # colour is only taken in with camera info
    w, h = c.size
    if camera.size_differs(c.size):
        ledger.size_error(f"{c.where}: image is {w}x{h}, camera info says {iw}x{ih}")
        return None
    try:
        T = checked_pose(T, f"{c.where}: pose from {pose_source}")
    except DatasetError as e:
        ledger.count("bad_pose", str(e))
        return None
    try:
        rgb = decode_colour(c.msg, c.where)
        depth, scale = decode_depth(d.msg, depth_scale, d.where)
    except UnsupportedEncodingError as e:
        ledger.count("unknown_encoding", str(e))
        return None
    except DatasetError as e:
        ledger.count("bad_payload", str(e))
        return None
    if rgb.shape[:2] != (h, w) or depth.shape != (h, w):
        ledger.size_error(f"{c.where}: decoded colour {rgb.shape[1]}x{rgb.shape[0]} and depth "
                          f"{depth.shape[1]}x{depth.shape[0]} differ from the header's {w}x{h}")  # fmt: skip
        return None
    try:
        return Frame(
            frame_index=index,
            time_s=c.stamp_ns / NS,
            rgb=rgb,
            depth=depth,
            depth_scale=scale,
            intrinsics=Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h),
            T_world_cam=T,
        )
    except ValueError as e:  # what the checks above let through (a 70000-pixel-wide image, say)
        ledger.count("bad_payload", f"{c.where}: not a valid frame ({e})")
        return None
