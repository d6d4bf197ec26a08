"""The two ROS 2 sessions, without Zenoh: each talks to TrackGraph through a
:class:`~shared.runtime.bus.Bus` and to the robot through a :class:`~shared.ros2.wire.RosWire`.

:class:`Ros2SourceSession` is ``trackgraph source --ros2``: the robot's colour, depth,
CameraInfo and TF (or odometry) topics in, synchronised by a
:class:`~services.ros2.live.FrameAssembler`, TrackGraph ``frames`` out. A live robot does not
wait for the mapper, so frames are never queued behind a slow stage: at most
``ros2.input.window_frames`` may be unacknowledged by the pacing stages
(``source.ack_from``), and while the pipeline holds, a newer synchronised frame replaces the
held one (latest wins) and the replaced one is counted as dropped.

:class:`Ros2BridgeSession` is ``trackgraph serve ros2``: the scene graph (kept by the same
:class:`~shared.graph.sync.ReplicaFollower` as the query service's and the viewer's) out as a
``visualization_msgs/MarkerArray`` after each delta, the trajectory as a ``nav_msgs/Path``, and
ROS queries (``std_msgs/String`` JSON on ``ros2.output.query_topic``) answered on the reply
topic, their hits also as a MarkerArray and a ``geometry_msgs/PoseArray``.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from pydantic import ValidationError

from services.ros2.live import FrameAssembler
from services.source.core import Pacer
from shared.config.root import TrackGraphConfig
from shared.graph.scene import GraphReplica
from shared.messages.base import Envelope
from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame
from shared.messages.poses import PoseCorrection
from shared.messages.rpc import QueryReply, QueryRequest
from shared.ros2 import markers
from shared.ros2.corrections import CorrectionBuilder, read_path
from shared.ros2.types import RosDecodeError, decode, msg_class
from shared.ros2.wire import RosWire
from shared.runtime.bus import Bus, BusError, subscribe_counted
from shared.runtime.session import Session
from shared.runtime.status import StatusBook
from shared.topics import Topics

log = logging.getLogger(__name__)

STRING = "std_msgs/msg/String"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
PATH = "nav_msgs/msg/Path"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

MAX_QUERY_BYTES = 64 * 1024
"""Largest JSON query taken from a ROS String (a text query is a few dozen bytes)."""
MAX_PATH_POSES = 20_000
"""Poses kept for the Path: beyond this every other one is dropped (RViz draws a 10-minute
30 Hz trajectory from 20 000 poses in one message of 1.3 MB)."""


class LivePacer(Pacer):
    """:class:`~services.source.core.Pacer` without a plan: positions are the order frames
    were sent in, so the frames latest-wins dropped leave no gap the pipeline would have to
    acknowledge (a frame index it never saw)."""

    KEEP = 4096
    """Sent frames whose acks are still looked up (far more than any window)."""

    def __init__(self, window: int, stages: list[str], hold_gone_s: float = 0.0, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__([], window, stages, hold_gone_s=hold_gone_s, clock=clock)
        self.sent = 0

    def send(self, frame_index: int) -> None:
        """Frame ``frame_index`` goes out now, at position :attr:`sent`."""
        with self._cv:
            self.position[int(frame_index)] = self.sent
            self.sent += 1
            if len(self.position) > 2 * self.KEEP:
                for f in sorted(self.position)[: len(self.position) - self.KEEP]:
                    del self.position[f]

    def next_held(self, alive: set[str]) -> set[str]:
        """The stages that hold the next frame to send; empty when it may go."""
        return self.holding(self.sent, alive)


class Ros2SourceSession(Session):
    """The robot's topics in, ``frames`` out (see the module docstring). ``alive`` says which
    services are running (their liveliness), for the pacer."""

    service = "source"
    serialized = False  # the assembler has its own lock; the pacer has its own

    def __init__(
        self, bus: Bus, wire: RosWire, cfg: TrackGraphConfig, *, alive: Callable[[], set[str]] = set,
        on_input: Callable[[], None] | None = None, clock: Callable[[], float] = time.monotonic,
    ) -> None:  # fmt: skip
        super().__init__(bus, clock=clock)
        self.cfg = cfg
        inp, link = cfg.ros2.input, cfg.ros2.link
        self.assembler = FrameAssembler(inp, distro=link.distro, max_payload_bytes=link.max_payload_bytes)
        self._lock = threading.Lock()
        self.pacer = LivePacer(inp.window_frames, cfg.source.ack_from, hold_gone_s=cfg.source.hold_gone_s, clock=clock)
        self.alive = alive
        self.on_input = on_input
        self.waiting: list[Frame] = []
        """Synchronised frames the pipeline has not taken yet: at most one after a tick."""
        self.published = 0
        self.dropped = 0
        self.last_published = -1
        self._last_error: str | None = None
        self.frames_out = self.output("frames", Frame)
        self.end_out = self.output("end_of_sequence", EndOfSequence)
        self.ended = False
        self.subscribe("frame_ack", FrameAck, self._on_ack, capacity=256)
        self.wire = wire
        self._subs = []
        topics = [(inp.rgb_topic, inp.rgb_type, False), (inp.depth_topic, inp.depth_type, False), (inp.camera_info_topic, CAMERA_INFO, False)]
        if inp.pose_topic is not None:
            topics.append((inp.pose_topic, inp.pose_type, False))
        else:
            topics += [(inp.tf_topic, TF_MESSAGE, False), (inp.tf_static_topic, TF_MESSAGE, True)]
        for topic, ros_type, latched in topics:
            self._subs.append(wire.subscribe(topic, ros_type, self._on_ros, transient_local=latched, depth=100 if latched else 10))
        self.corrections: CorrectionBuilder | None = None
        if inp.corrections != "none":
            self.corrections = CorrectionBuilder(inp)
            self.corrections_out = self.output("poses_correction", PoseCorrection)
            self._odom_seen: int | None = None  # stamp of the newest world -> odom sample looked at
            if inp.corrections == "path":
                self._subs.append(wire.subscribe(inp.corrections_path_topic, PATH, self._on_path, depth=2))
            self.book.figure("corrections", lambda: self.corrections.stats.as_dict())
        self.book.declare_input("ros2")
        self.book.figure("published", lambda: self.published)
        self.book.figure("dropped", lambda: self.dropped)
        self.book.figure("ros2", lambda: self.assembler.stats.as_dict())
        self.book.figure("silent_topics", lambda: self.assembler.silent_topics(self.clock()))
        self.book.figure("error", lambda: self.assembler.error)
        self.book.figure("convention", link.convention)
        self.book.set_state("running")

    def _on_ack(self, msg: FrameAck) -> None:
        self.pacer.ack(msg.service, msg.frame_index)
        if self.on_input is not None:
            self.on_input()

    def _on_ros(self, topic: str, payload: bytes, ros_type: str | None) -> None:
        self.book.count("ros2", "received")
        with self._lock:
            self.assembler.on_message(topic, payload, self.clock(), ros_type)
        if self.on_input is not None:
            self.on_input()

    def _on_path(self, topic: str, payload: bytes, ros_type: str | None) -> None:
        """An optimised path from the SLAM: a correction, if it moves the map enough."""
        inp, link = self.cfg.ros2.input, self.cfg.ros2.link
        try:
            msg = decode(payload, PATH, link.distro, max_bytes=link.max_payload_bytes)
            stamps, poses, head = read_path(msg, inp.world_frame)
        except (RosDecodeError, ValueError) as e:
            self.corrections.stats.rejected += 1
            self.book.count("poses_correction", "rejected")
            log.warning("ROS 2 corrections: a nav_msgs/Path on %s refused (%s)", topic, e)
            return
        with self._lock:
            c = self.corrections.from_path(stamps, poses, self.clock(), head)
        self._send_correction(c)

    def _poll_corrections(self, now: float) -> None:
        """A correction held back by its minimum period, or one from a new map -> odom."""
        inp = self.cfg.ros2.input
        with self._lock:
            c = self.corrections.due(now)
            if c is None and inp.corrections == "map_odom" and self.corrections.frames:
                stamp = self.assembler.newest_stamp(inp.odom_frame)
                if stamp is not None and stamp != self._odom_seen:
                    M = self.assembler.transform(inp.world_frame, inp.odom_frame, stamp)
                    if M is not None:
                        self._odom_seen = stamp
                        c = self.corrections.from_map_odom(M, stamp, now)
        self._send_correction(c)

    def _send_correction(self, c: PoseCorrection | None) -> None:
        if c is not None:
            self.corrections_out.put(c)
            self.book.count("poses_correction", "processed")

    def tick(self, now: float) -> float:
        """Send the synchronised frames the pipeline takes now; of those it holds, keep only
        the newest (latest wins, the others counted as dropped). Returns the seconds until
        calling again is useful."""
        with self._lock:
            frames = self.assembler.poll(now)
        self.waiting.extend(frames)
        error = self.assembler.error
        if error != self._last_error:
            if error is not None:
                log.error("ROS 2 input: %s", error)
                self.book.error()
            else:
                log.info("ROS 2 input: recovered (%s)", self._last_error)
            self._last_error = error
        alive = self.alive() if self.waiting else set()
        while self.waiting and not self.pacer.next_held(alive):
            frame = self.waiting.pop(0)
            t0 = self.clock()
            if self.corrections is not None:
                frame = self._placed(frame)
            self.pacer.send(frame.frame_index)
            self.frames_out.put(frame)
            self.published += 1
            self.last_published = frame.frame_index
            self.book.count("ros2", "processed")
            self.book.work_done(max(self.clock() - t0, 0.0))
        if len(self.waiting) > 1:
            stale, self.waiting = self.waiting[:-1], self.waiting[-1:]
            self.dropped += len(stale)
            log.debug("frames %s replaced by frame %d: the pipeline holds them (%s)", [f.frame_index for f in stale],
                      self.waiting[0].frame_index, ", ".join(sorted(self.pacer.next_held(alive))))  # fmt: skip
        if self.corrections is not None:
            self._poll_corrections(now)
        self.book.progress(done=self.published + self.dropped)
        return 0.01 if self.waiting else 0.05

    def _placed(self, frame: Frame) -> Frame:
        """The frame at its odometry pose, recorded for corrections (:meth:`CorrectionBuilder.place`)."""
        origin = self.assembler.origin(frame.frame_index)
        if origin is None:
            return frame
        with self._lock:
            pose = self.corrections.place(frame.frame_index, origin[0], origin[1], frame.T_world_cam, self.assembler.transform)
        if pose is None:
            return frame
        return frame.model_copy(update={"T_world_cam": pose})

    def finish(self) -> None:
        """The live stream is over (the source is stopping): an EndOfSequence, once, so
        fusion can write its final map."""
        if self.ended:
            return
        self.ended = True
        self.dropped += len(self.waiting)  # held to the end: never taken
        self.waiting = []
        self.end_out.put(EndOfSequence(frames_published=self.published, frames_dropped=self.dropped, last_frame_index=self.last_published))

    def close(self) -> None:
        for s in self._subs:
            try:
                s.close()
            except Exception:  # noqa: BLE001 - closing after the wire went
                log.debug("closing %s failed", s, exc_info=True)
        self._subs.clear()
        super().close()


class Ros2BridgeSession:
    """The scene graph, trajectory and query answers out to ROS 2 (see the module docstring)."""

    service = "ros2"

    def __init__(self, bus: Bus, wire: RosWire, cfg: TrackGraphConfig, *, clock: Callable[[], float] = time.monotonic) -> None:
        from shared.graph.sync import ReplicaFollower

        self.cfg, self.bus, self.wire, self.clock = cfg, bus, wire, clock
        out, self.distro = cfg.ros2.output, cfg.ros2.link.distro
        self.out = out
        self.topics = Topics(cfg.robot_id)
        self.book = StatusBook("ros2", clock=clock)
        self._lock = threading.Lock()
        self._dirty = False
        self._view: GraphReplica | None = None
        self._last_markers = -math.inf
        self._path_dirty = False
        self._last_path = -math.inf
        self._poses: list[np.ndarray] = []
        self._stamps: list[int] = []
        self._last_frame = -1
        self._queries: queue.Queue = queue.Queue(maxsize=64)
        self._closed = threading.Event()
        self.markers_sent = self.paths_sent = self.queries_answered = self.queries_refused = 0
        self._endpoints: list[Any] = []
        self.token = None
        book = self.book
        try:
            self.markers_pub = wire.publisher(out.markers_topic, MARKER_ARRAY, transient_local=True, depth=1)
            self.path_pub = wire.publisher(out.path_topic, PATH, transient_local=True, depth=1)
            self.reply_pub = wire.publisher(out.reply_topic, STRING)
            self.hits_pub = wire.publisher(out.hits_markers_topic, MARKER_ARRAY, transient_local=True, depth=1)
            self.poses_pub = wire.publisher(out.hits_poses_topic, POSE_ARRAY, transient_local=True, depth=1)
            self._endpoints += [self.markers_pub, self.path_pub, self.reply_pub, self.hits_pub, self.poses_pub]
            self._endpoints.append(wire.subscribe(out.query_topic, STRING, self._on_query))
            book.declare_input("ros2_query", self._queries.qsize)
            self.graph = ReplicaFollower(
                bus, self.topics, book, with_mesh=False, timeout_s=cfg.transport.query_timeout_s, on_change=self._graph_changed,
                capacity=256, name="ros2:delta",
            )  # fmt: skip
            self._endpoints.append(self.graph)
            self.frames = subscribe_counted(
                bus, book, "tracks_frame", self.topics.tracks_frame, TrackedFrame, self._on_frame, policy="latest", capacity=1,
                name="ros2:frame",
            )  # fmt: skip
            self._endpoints.append(self.frames)
            for name, value in {
                "markers_sent": lambda: self.markers_sent, "paths_sent": lambda: self.paths_sent,
                "queries_answered": lambda: self.queries_answered, "queries_refused": lambda: self.queries_refused,
                "convention": cfg.ros2.link.convention,
            }.items():  # fmt: skip
                book.figure(name, value)
            self._worker = threading.Thread(target=self._answer_queries, name="ros2:query", daemon=True)
            self._worker.start()
            self.token = bus.declare_alive(self.topics.alive("ros2"))
        except BaseException:
            self.close()
            raise
        book.set_state("running")

    # ------------------------------------------------------------ graph and trajectory

    def _graph_changed(self, replica: GraphReplica, mesh_changed: bool) -> None:
        # Called under the replica's lock on every change: keep a shallow copy of its nodes
        # (cheap) and let tick() build the markers at its own pace.
        view = GraphReplica()
        view.graph_seq, view.frame_index = replica.graph_seq, replica.frame_index
        view.segments, view.places, view.rooms = dict(replica.segments), dict(replica.places), dict(replica.rooms)
        view.edges = set(replica.edges)
        with self._lock:
            self._view = view
            self._dirty = True

    def _on_frame(self, env: Envelope[TrackedFrame]) -> None:
        self.book.count("tracks_frame", "received")
        f = env.body.frame
        with self._lock:
            if f.frame_index > self._last_frame:
                self._last_frame = f.frame_index
                self._poses.append(np.asarray(f.T_world_cam, np.float64))
                self._stamps.append(int(round(f.time_s * 1e9)))
                if len(self._poses) > MAX_PATH_POSES:
                    self._poses, self._stamps = self._poses[::2], self._stamps[::2]
                self._path_dirty = True
        self.book.count("tracks_frame", "processed")

    def tick(self, now: float) -> None:
        """Repair the replica if it needs a snapshot; send markers and the path when they
        changed and ``markers_min_period_s`` has passed."""
        self.graph.tick(now)
        period = self.out.markers_min_period_s
        if self._dirty and now - self._last_markers >= period:
            self._dirty = False
            self._last_markers = now
            self.publish_markers()
        if self._path_dirty and now - self._last_path >= period:
            self._path_dirty = False
            self._last_path = now
            with self._lock:
                poses, stamps = np.array(self._poses), np.array(self._stamps, np.int64)
            try:
                self.path_pub.put(markers.trajectory_path(poses, stamps, frame_id=self.out.frame_id, distro=self.distro))
                self.paths_sent += 1
                self.book.published("path")
            except Exception:  # noqa: BLE001 - a path that cannot go must not stop the bridge
                self.book.error()
                log.exception("ros2: trajectory not published")

    def publish_markers(self) -> None:
        """The whole graph as one MarkerArray (a DELETEALL first, so removed nodes vanish)."""
        with self._lock:
            view = self._view
        if view is None:
            return
        try:
            msg = markers.replica_markers(view, frame_id=self.out.frame_id, stamp_ns=time.time_ns(), show_ids=self.out.show_ids, distro=self.distro)
            self.markers_pub.put(msg)
            self.markers_sent += 1
            self.book.published("markers")
        except Exception:  # noqa: BLE001
            self.book.error()
            log.exception("ros2: scene-graph markers not published")

    # ------------------------------------------------------------ queries

    def _on_query(self, topic: str, payload: bytes, ros_type: str | None) -> None:
        self.book.count("ros2_query", "received")
        try:
            self._queries.put_nowait(payload)
        except queue.Full:
            self.book.count("ros2_query", "dropped")
            self.queries_refused += 1

    def _answer_queries(self) -> None:
        while not self._closed.is_set():
            try:
                payload = self._queries.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self.answer(payload)
            except Exception:  # noqa: BLE001 - one query must not stop the worker
                self.book.error()
                log.exception("ros2: query failed")

    def answer(self, payload: bytes) -> dict:
        """Answer one ROS query (CDR of a std_msgs/String holding JSON); returns the reply sent."""
        t0 = self.clock()
        qid = None
        try:
            text = decode(payload, STRING, self.distro, max_bytes=MAX_QUERY_BYTES).data
            req, qid = parse_query(text)
        except (RosDecodeError, ValueError) as e:
            self.book.count("ros2_query", "rejected")
            self.queries_refused += 1
            return self._reply({"id": qid, "error": str(e)})
        try:
            reply = self.bus.request(self.topics.query, req, QueryReply, timeout=self.out.query_timeout_s)
        except BusError as e:
            reply = QueryReply(error=f"query service: {e}")
        body = json.loads(reply.model_dump_json())
        body["id"] = qid
        sent = self._reply(body)
        if reply.error is None:
            stamp = time.time_ns()
            self.hits_pub.put(markers.hits_markers(reply, frame_id=self.out.frame_id, stamp_ns=stamp, distro=self.distro))
            self.poses_pub.put(markers.hits_pose_array(reply, frame_id=self.out.frame_id, stamp_ns=stamp, distro=self.distro))
            self.queries_answered += 1
            self.book.count("ros2_query", "processed")
        else:
            self.queries_refused += 1
            self.book.count("ros2_query", "rejected")
        self.book.work_done(max(self.clock() - t0, 0.0))
        return sent

    def _reply(self, body: dict) -> dict:
        self.reply_pub.put(msg_class(STRING, self.distro)(data=json.dumps(body)))
        self.book.published("reply")
        return body

    def close(self) -> None:
        self._closed.set()
        if self.token is not None:
            self.token.undeclare()
            self.token = None
        for ep in reversed(self._endpoints):
            try:
                ep.close()
            except Exception:  # noqa: BLE001
                log.debug("closing %r failed", ep, exc_info=True)
        self._endpoints.clear()


def parse_query(text: str) -> tuple[QueryRequest, Any]:
    """A ROS query's JSON: a ``QueryRequest`` (``{"text": "red armchair", "top_k": 3}``), plus
    an optional ``id`` echoed in the reply; plain text (``red armchair``) is a text query.
    ValueError with what is wrong otherwise."""
    if not text.strip().startswith(("{", "[", '"')):
        text = json.dumps({"text": text.strip()})  # `ros2 topic pub ... "data: red armchair"`
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"query is not JSON ({e.msg} at character {e.pos}); expected e.g. {{\"text\": \"red armchair\"}}") from None
    if isinstance(data, str):
        data = {"text": data}
    if not isinstance(data, dict):
        raise ValueError(f"query must be a JSON object like {{\"text\": \"red armchair\"}}, got {type(data).__name__}")
    qid = data.pop("id", None)
    if "image" in data:
        raise ValueError("image queries are not taken over ROS (send a text query, or use QueryClient)")
    try:
        return QueryRequest.model_validate(data), qid
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "query"
        raise ValueError(f"{where}: {first['msg']}") from None
