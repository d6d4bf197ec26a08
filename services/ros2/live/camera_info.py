"""The camera's intrinsics from ``sensor_msgs/CameraInfo``, and the colour images that beat it.

The latest valid CameraInfo's K and size are what every frame uses. Over a network the first
colour image often arrives a few ms before its camera info, so colour images that come before
the first one are held up to ``max_wait_s`` (at most ``max_pending`` of them), then refused
as ``no_camera_info``.
"""

from __future__ import annotations

import math
from typing import Any

from services.ros2.live.stats import Ledger
from shared.config.ros2 import Ros2InputConfig

CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"

Held = tuple[str, Any, int, float]
"""A colour message waiting for the first CameraInfo: (topic, msg, stamp ns, arrival)."""


class CameraInfoGate:
    """The latest camera info, and the colour images held until the first one comes."""

    def __init__(self, cfg: Ros2InputConfig, ledger: Ledger, max_pending: int) -> None:
        self.cfg = cfg
        self.ledger = ledger
        self.max_pending = max_pending
        self.info: tuple[float, float, float, float, int, int] | None = None
        """fx fy cx cy width height of the latest valid CameraInfo (size 0: not given)."""
        self.held: list[Held] = []
        self._without_info_since: float | None = None

    def size_differs(self, size: tuple[int, int]) -> bool:
        """True if an image of ``size`` (w, h) is not the size the camera info gives."""
        iw, ih = self.info[4], self.info[5]  # type: ignore[index]  # only asked once info came
        return (iw or size[0], ih or size[1]) != size

    def hold(self, topic: str, msg: Any, stamp: int, now: float) -> None:
        """Keep a colour image that came before any camera info; say so once it has been long."""
        since = self._without_info_since
        if since is None:
            since = self._without_info_since = now
        if now - since >= self.cfg.camera_info_timeout_s:
            self.ledger.errors["camera_info"] = (
                f"no sensor_msgs/CameraInfo on {self.cfg.camera_info_topic} after {now - since:.1f} s of colour images"
            )
        self.held.append((topic, msg, stamp, now))
        self.expire(now)

    def on_info(self, topic: str, msg: Any) -> list[Held]:
        """Take in one CameraInfo; the colour images held for it, to be taken in now (their
        arrival kept: they wait no longer than max_wait_s in all)."""
        k = [float(x) for x in msg.k]
        w, h = int(msg.width), int(msg.height)
        fx, fy, cx, cy = k[0], k[4], k[2], k[5]
        if not (all(math.isfinite(v) for v in (fx, fy, cx, cy)) and fx > 0 and fy > 0) or w > 65536 or h > 65536:
            text = (f"sensor_msgs/CameraInfo on {topic} has an invalid camera matrix K (fx={fx}, fy={fy}, cx={cx}, "
                    f"cy={cy}) or size {w}x{h}; is the camera calibrated?")  # fmt: skip
            if self.info is None:
                self.ledger.errors["camera_info"] = text
            self.ledger.reject("bad_payload", topic, text)
            return []
        self.info = (fx, fy, cx, cy, w, h)
        self._without_info_since = None
        self.ledger.errors.pop("camera_info", None)
        self.ledger.accept(topic)
        held, self.held = self.held, []
        return held

    def expire(self, now: float) -> None:
        """Refuse held colour images older than max_wait_s, or past max_pending, as no_camera_info."""
        fresh = [now - h[3] <= self.cfg.max_wait_s for h in self.held]
        n_keep = min(sum(fresh), self.max_pending)  # arrivals only grow: the fresh ones are the newest
        for c_topic, _, c_stamp, _ in self.held[: len(self.held) - n_keep]:
            self.ledger.reject("no_camera_info", c_topic, f"{c_topic} at stamp {c_stamp} ns: no sensor_msgs/CameraInfo "
                               f"on {self.cfg.camera_info_topic} within max_wait_s={self.cfg.max_wait_s} s; "
                               "colour images are dropped until it comes")  # fmt: skip
        del self.held[: len(self.held) - n_keep]
