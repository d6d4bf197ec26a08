"""Colour/depth pairing of the live input (approximate-time sync).

Each colour image is paired with the depth image nearest to it in stamp within ``slop_s``,
nearest pairs first, each depth used once. Pixels are not decoded here: only the headers are
checked (:meth:`Pairing.peek`), so a few pending messages cost little memory.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.ros2.live.clock import NS, Timeline
from services.ros2.live.stats import Ledger
from shared.config.ros2 import Ros2InputConfig
from shared.datasets.base import DatasetError
from shared.datasets.rosimage import UnsupportedEncodingError, peek_size


@dataclass(eq=False)  # identity: two messages are never "equal" (and numpy fields cannot say)
class PendingImage:
    """A decoded colour or depth message waiting to be paired (pixels not decoded yet)."""

    stamp_ns: int
    arrival: float
    msg: Any
    size: tuple[int, int]
    topic: str
    frame_id: str = ""

    @property
    def where(self) -> str:
        return f"{self.topic} at stamp {self.stamp_ns} ns"


class Pairing:
    """The pending colour images (sorted by stamp), the unused depth images (sorted by
    stamp), and the stamp of the last frame emitted."""

    def __init__(self, cfg: Ros2InputConfig, ledger: Ledger, timeline: Timeline, max_pending: int) -> None:
        self.cfg = cfg
        self.ledger = ledger
        self.timeline = timeline
        self.max_pending = max_pending
        self.slop_ns = int(round(cfg.slop_s * NS))
        self.colours: list[PendingImage] = []
        self.depths: list[PendingImage] = []
        self.last_emitted_ns: int | None = None

    def peek(self, im: PendingImage, role: str) -> bool:
        """Header checks of a colour or depth image (no pixel decoded); counts a failure."""
        try:
            im.size = peek_size(im.msg, role, im.where)
        except UnsupportedEncodingError as e:
            expected = "rgb8, bgr8, rgba8, bgra8, mono8, JPEG or PNG" if role == "colour" else "16UC1, 32FC1 or compressedDepth png"
            self.ledger.reject("unknown_encoding", im.topic, f"{e} (expected {expected})")
            return False
        except DatasetError as e:
            self.ledger.reject("bad_payload", im.topic, str(e))
            return False
        return True

    def add_colour(self, c: PendingImage, now: float) -> None:
        """Queue a colour image whose size fits the camera info, unless it is stamped back."""
        last = self.last_emitted_ns
        if last is not None and c.stamp_ns <= last:
            if not self.timeline.went_back("colour", now, self.cfg.rgb_topic):
                self.ledger.reject("out_of_order", c.topic, f"{c.where}: stamp is not newer than the last frame's "
                                   f"({last} ns); expected increasing stamps")  # fmt: skip
                return
        else:
            self.timeline.forward("colour")
        if any(p.stamp_ns == c.stamp_ns for p in self.colours):
            self.ledger.reject("out_of_order", c.topic, f"{c.where}: a colour image with this stamp is already waiting (duplicate)")
            return
        bisect.insort(self.colours, c, key=lambda x: x.stamp_ns)
        while len(self.colours) > self.max_pending:
            self.drop(self.colours[0], "superseded", f"{self.colours[0].where}: more than {self.max_pending} colour "
                      "images waiting; the oldest is dropped")  # fmt: skip

    def on_depth(self, topic: str, msg: Any, stamp: int, now: float) -> None:
        d = PendingImage(stamp, now, msg, (0, 0), topic)
        if not self.peek(d, "depth"):
            return
        if self.last_emitted_ns is not None and stamp < self.last_emitted_ns - self.slop_ns:
            # No later colour (newer than the last frame) can be within slop of it.
            self.ledger.reject("out_of_order", topic, f"{d.where}: older than the last frame ({self.last_emitted_ns} ns) "
                               f"by more than slop_s={self.cfg.slop_s}; expected increasing stamps")  # fmt: skip
            return
        bisect.insort(self.depths, d, key=lambda x: x.stamp_ns)
        if len(self.depths) > self.max_pending:
            del self.depths[0]  # unused depth is no fault (depth often runs faster than colour)
        self.ledger.accept(topic)

    def assign_depths(self) -> dict[int, PendingImage]:
        """Pending colour (by id) -> its depth: nearest pairs first, each depth once."""
        if not self.depths:
            return {}
        cs = np.array([c.stamp_ns for c in self.colours], np.int64)
        ds = np.array([d.stamp_ns for d in self.depths], np.int64)
        dt = np.abs(cs[:, None] - ds[None, :])
        ci, di = np.nonzero(dt <= self.slop_ns)
        order = np.lexsort((cs[ci], dt[ci, di]))
        out: dict[int, PendingImage] = {}
        used: set[int] = set()
        for k in order:
            c, d = int(ci[k]), int(di[k])
            if id(self.colours[c]) in out or d in used:
                continue
            out[id(self.colours[c])] = self.depths[d]
            used.add(d)
        return out

    def depth_final(self, c: PendingImage, d: PendingImage) -> bool:
        """No nearer depth can still come for ``c`` (depth arrives in stamp order)."""
        return self.depths[-1].stamp_ns >= c.stamp_ns + abs(c.stamp_ns - d.stamp_ns)

    def drop(self, c: PendingImage, reason: str, text: str) -> None:
        """Give up a pending colour image."""
        self.colours.remove(c)
        self.ledger.drop(reason, text)

    def emitted(self, c: PendingImage, d: PendingImage) -> None:
        """The frame of ``c`` and ``d`` went out: ``d`` is used, and so is every depth that no
        later colour (stamped after this frame) can be within slop of."""
        self.last_emitted_ns = c.stamp_ns
        self.depths.remove(d)
        self.depths = [x for x in self.depths if x.stamp_ns >= c.stamp_ns - self.slop_ns]

    def prune(self, now: float) -> None:
        """Forget a depth nobody claimed for a while, unless a waiting colour may still take it."""
        keep = now - 2 * self.cfg.max_wait_s
        if self.depths and self.depths[0].arrival < keep:
            near = [c.stamp_ns for c in self.colours]
            self.depths = [d for d in self.depths
                           if d.arrival >= keep or any(abs(d.stamp_ns - t) <= self.slop_ns for t in near)]  # fmt: skip

    def reset(self) -> None:
        """A new timeline: every pending colour is dropped, and depth and the last stamp forgotten."""
        for c in list(self.colours):
            self.drop(c, "out_of_order", f"{c.where}: dropped, the stamps went back in time")
        self.depths.clear()
        self.last_emitted_ns = None
