"""ROS 2 nodes: the sessions of :mod:`services.ros2.session` on Zenoh, and the bag player.

- :func:`run_ros2_source` is ``trackgraph source --ros2``: the robot's camera and pose topics
  in, TrackGraph frames out, until stopped (then an EndOfSequence, so fusion can finish).
- :class:`Ros2BridgeNode` is ``trackgraph serve ros2``: markers, trajectory and query answers
  out to ROS 2.
- :func:`play_bag` is ``trackgraph ros2 play BAG``: a bag's recorded CDR payloads published at
  the recorded pace in either convention, as the robot's drivers would send them.

The ROS 2 side shares TrackGraph's Zenoh session unless ``ros2.link.connect`` names the
robot's own router, then it gets a session of its own.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from services.ros2.session import Ros2BridgeSession, Ros2SourceSession
from shared.config.root import TrackGraphConfig
from shared.ros2.link import ZenohRosWire
from shared.runtime.adapter import SessionNode, open_bus
from shared.runtime.lifeline import install_stop_handlers
from shared.topics import Topics, service_of_alive_key
from shared.transport import LivelinessWatcher, ZenohBus, open_session

log = logging.getLogger(__name__)

TICK_S = 0.01
"""How often a node's session is ticked: the source sends a synchronised frame at most this
late; the bridge's markers and path are rate-limited by ``ros2.output.markers_min_period_s``."""


@dataclass
class LiveStats:
    """What ``trackgraph source --ros2`` did, for its ``--json`` line."""

    published: int = 0
    dropped: int = 0
    seconds: float = 0.0
    received: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    error: str | None = None


class Ros2SourceNode(SessionNode):
    """:class:`Ros2SourceSession` on Zenoh, ticked on its own thread: the live source of
    ``trackgraph source --ros2`` (and of tests that drive one in-process)."""

    def __init__(self, cfg: TrackGraphConfig, *, session=None) -> None:
        topics = Topics(cfg.robot_id)
        self.wire: ZenohRosWire | None = None
        self.alive: LivelinessWatcher | None = None

        def make(b: ZenohBus) -> Ros2SourceSession:
            self.wire = self.own(ZenohRosWire.open(cfg.ros2.link, session=b.session, transport=cfg.transport))
            alive = self.alive = self.own(LivelinessWatcher(b.session, topics.alive_all))

            def stages() -> set[str]:
                return {service_of_alive_key(k) for k in alive.alive()}

            return Ros2SourceSession(b, self.wire, cfg, alive=stages)

        super().__init__(
            open_bus(cfg, session), make, name="ros2-source", tick_s=TICK_S, stop_timeout_s=cfg.transport.query_timeout_s + 1,
            alive="source", running=False,
        )  # fmt: skip
        inp = cfg.ros2.input
        log.info(
            "ROS 2 source (%s, domain %d): %s + %s + %s, poses from %s, on %s",
            cfg.ros2.link.convention, cfg.ros2.link.domain_id, inp.rgb_topic, inp.depth_topic, inp.camera_info_topic,
            inp.pose_topic or f"TF {inp.world_frame} <- camera", topics.frames,
        )  # fmt: skip

    def stats(self) -> LiveStats:
        s = self.session
        st = s.assembler.stats
        return LiveStats(
            published=s.published, dropped=s.dropped, received=dict(st.received),
            rejected={k: v for k, v in st.rejected.items() if v}, error=s.assembler.error,
        )  # fmt: skip

    def close(self, keep_bus: bool = False) -> None:
        """Stop: the EndOfSequence out (fusion may finish its map), then everything closed."""
        if not self._closed and self.session is not None:
            try:
                self.session.finish()
            except Exception:  # noqa: BLE001 - closing anyway
                log.exception("ROS 2 source: the EndOfSequence did not go out")
        super().close(keep_bus)


def run_ros2_source(
    cfg: TrackGraphConfig,
    *,
    stop: threading.Event | None = None,
    status_file: Path | None = None,
    max_seconds: float | None = None,
) -> LiveStats:
    """Turn the robot's topics into frames (``cfg.ros2.input``) until ``stop`` (or a signal,
    or ``max_seconds``), reporting status as every service does; an EndOfSequence goes out at
    the end."""
    from services.serve import serve

    t_start = time.monotonic()
    node = serve("source", cfg, stop=stop, status_file=status_file, make_node=lambda: Ros2SourceNode(cfg), max_seconds=max_seconds)
    stats = node.stats()
    stats.seconds = round(time.monotonic() - t_start, 3)
    log.info("ROS 2 source: published %d frames in %.1f s, dropped %d; rejected %s", stats.published, stats.seconds, stats.dropped, stats.rejected or "none")
    return stats


class Ros2BridgeNode(SessionNode):
    """:class:`Ros2BridgeSession` on Zenoh: ``trackgraph serve ros2``. The session declares
    its liveliness itself, once its ROS 2 side is up."""

    def __init__(self, cfg: TrackGraphConfig, *, session=None) -> None:
        def make(b: ZenohBus) -> Ros2BridgeSession:
            self.wire = self.own(ZenohRosWire.open(cfg.ros2.link, session=b.session, transport=cfg.transport))
            return Ros2BridgeSession(b, self.wire, cfg)

        super().__init__(open_bus(cfg, session), make, name="ros2", tick_s=0.05, stop_timeout_s=cfg.transport.query_timeout_s + 1)

    def stats(self) -> dict:
        s = self.session
        return {"markers_sent": s.markers_sent, "paths_sent": s.paths_sent, "queries_answered": s.queries_answered,
                "queries_refused": s.queries_refused}  # fmt: skip


@dataclass
class PlayStats:
    """What ``trackgraph ros2 play`` sent."""

    messages: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    late_s: float = 0.0
    """Largest lag behind the recorded schedule (the network or the disk held the player)."""


def play_bag(
    bag: Path,
    cfg: TrackGraphConfig,
    *,
    rate: float = 1.0,
    topics: list[str] | None = None,
    stop: threading.Event | None = None,
    wait_subscribers_s: float = 0.0,
    progress: bool = False,
) -> PlayStats:
    """Publish ``bag``'s messages over Zenoh in ``cfg.ros2.link``'s convention, at ``rate``
    times the recorded pace. ``wait_subscribers_s``: first wait this long for a subscriber of
    every colour/depth topic (a live consumer that is still starting would miss the start)."""
    from shared.ros2 import bagio

    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"--rate must be a positive finite factor of the recorded pace, got {rate}")
    stop = stop or threading.Event()
    install_stop_handlers(stop.set)
    available = bagio.bag_topics(bag)
    chosen = list(available) if topics is None else topics
    for t in chosen:
        if t not in available:
            raise bagio.BagError(f"{bag}: topic {t!r} is not in the bag; available: {', '.join(sorted(available))}")
    link = cfg.ros2.link
    own = open_session(cfg.transport) if not link.connect else None
    wire = ZenohRosWire.open(link, session=own, transport=cfg.transport)
    stats = PlayStats()
    bar = None
    try:
        pubs = {t: wire.publisher(t, available[t], transient_local=t == "/tf_static", depth=100 if t == "/tf_static" else 10) for t in chosen}
        if wait_subscribers_s > 0:
            deadline = time.monotonic() + wait_subscribers_s
            want = [p for t, p in pubs.items() if available[t].startswith("sensor_msgs/msg/")]
            while not all(p.has_subscribers() for p in want) and time.monotonic() < deadline and not stop.is_set():
                time.sleep(0.05)
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=bagio.bag_message_count(bag, chosen), unit="msg", desc="ros2 play", leave=False)
        t0 = time.monotonic()
        first_ns = None
        for m in bagio.read_bag_messages(bag, topics=chosen):
            if stop.is_set():
                break
            if first_ns is None:
                first_ns = m.time_ns
            due = t0 + (m.time_ns - first_ns) * 1e-9 / rate
            wait = due - time.monotonic()
            if wait > 0:
                if stop.wait(wait):
                    break
            else:
                stats.late_s = max(stats.late_s, -wait)
            pubs[m.topic].put_raw(m.payload, stamp_ns=time.time_ns())
            stats.messages += 1
            stats.topics[m.topic] = stats.topics.get(m.topic, 0) + 1
            if bar is not None:
                bar.update(1)
        stats.seconds = round(time.monotonic() - t0, 3)
        stats.late_s = round(stats.late_s, 3)
    finally:
        if bar is not None:
            bar.close()
        wire.close()
        if own is not None:
            own.close()
    log.info("played %d messages of %s in %.1f s (rate %.2f)", stats.messages, bag, stats.seconds, rate)
    return stats


def build(cfg, *, out=None, resume: bool = False) -> Ros2BridgeNode:
    """``trackgraph serve ros2``: the markers-and-queries bridge."""
    return Ros2BridgeNode(cfg)
