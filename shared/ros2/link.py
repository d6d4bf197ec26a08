"""A :class:`~shared.ros2.wire.RosWire` over Zenoh: TrackGraph as a node of a ROS 2 graph.

rmw_zenoh convention (docs/ros2.md):
- each publication goes on ``<domain>/<topic>/<dds type>/<RIHS01 hash>`` with CDR bytes and an
  attachment (sequence number, source timestamp, publisher GID), as rmw_zenoh's own
  publishers send;
- a node token ``@ros2_lv/<domain>/<zid>/<node>/<node>/NN/...`` and one token per publisher
  (``MP``) and subscriber (``MS``) make TrackGraph visible to ``ros2 topic list`` and
  ``ros2 node list`` on the robot;
- subscriptions use ``<domain>/<topic>/*/*``, so they receive whatever hash the sender's
  distribution computes (Humble sends ``TypeHashNotSupported``), and take the type from the key;
- transient-local endpoints (``/tf_static``, the scene-graph markers) are Zenoh advanced
  publishers with a cache and advanced subscribers that fetch late publishers' history, which is
  how rmw_zenoh implements that QoS.

bridge convention (``zenoh-bridge-ros2dds``): the topic name is the key, the payload CDR, no
attachment and no tokens: the bridge announces routes to DDS itself.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from typing import Any

import zenoh
import zenoh.ext

from shared.config.ros2 import Ros2LinkConfig
from shared.ros2 import keys
from shared.ros2.types import encode, type_hash
from shared.ros2.wire import RawCallback

log = logging.getLogger(__name__)


class _Endpoint:
    """A declared Zenoh publisher or subscriber (``_zenoh``) and its liveliness token."""

    _zenoh: Any
    token: Any = None
    _closed = False

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.token is not None:
            self.token.undeclare()
        self._zenoh.undeclare()


class _Publisher(_Endpoint):
    def __init__(self, link: ZenohRosWire, topic: str, ros_type: str, transient_local: bool, depth: int) -> None:
        self.link, self.topic, self.ros_type = link, topic, ros_type
        cfg = link.cfg
        self.key = keys.data_key(cfg.convention, topic, ros_type, domain_id=cfg.domain_id, distro=cfg.distro, prefix=cfg.bridge_prefix)
        self.gid = keys.new_gid()
        self.seq = itertools.count(1)
        self._lock = threading.Lock()
        # Reliable and blocking, as rmw_zenoh's reliable publishers: a MarkerArray or a camera
        # image spans many Zenoh fragments, and dropping one loses the whole message.
        cc = zenoh.CongestionControl.BLOCK
        self._zenoh = None
        if transient_local:
            try:
                self._zenoh = zenoh.ext.declare_advanced_publisher(
                    link.session, self.key, congestion_control=cc, cache=zenoh.ext.CacheConfig(depth), publisher_detection=True,
                )  # fmt: skip
            except zenoh.ZError as e:
                # A session without timestamping (a user's Zenoh file turned it off): late
                # joiners then miss the last message until the next one, nothing worse.
                log.warning("%s: transient-local publisher unavailable (%s); publishing volatile", topic, e)
        if self._zenoh is None:
            self._zenoh = link.session.declare_publisher(self.key, congestion_control=cc)
        self.token = link.announce("MP", topic, ros_type, transient_local=transient_local, depth=depth)
        self.sent = 0

    def put(self, msg: Any) -> None:
        self.put_raw(encode(msg, self.ros_type, self.link.cfg.distro))

    def put_raw(self, payload: bytes, stamp_ns: int | None = None) -> None:
        with self._lock:
            seq = next(self.seq)
            stamp = time.time_ns() if stamp_ns is None else int(stamp_ns)
            if self.link.cfg.convention == "rmw_zenoh":
                att = keys.Attachment(sequence=seq, timestamp_ns=stamp, gid=self.gid).encode()
                self._zenoh.put(payload, attachment=att)
            else:
                self._zenoh.put(payload)
            self.sent += 1

    def has_subscribers(self) -> bool:
        status = self._zenoh.matching_status
        return status if isinstance(status, bool) else bool(status.matching)


class _Subscription(_Endpoint):
    def __init__(self, link: ZenohRosWire, topic: str, ros_type: str, callback: RawCallback, transient_local: bool, depth: int) -> None:
        self.link, self.topic, self.callback = link, topic, callback
        cfg = link.cfg
        self.key = keys.subscribe_key(cfg.convention, topic, domain_id=cfg.domain_id, prefix=cfg.bridge_prefix)
        self.received = 0
        if transient_local:
            history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=depth)
            self._zenoh = zenoh.ext.declare_advanced_subscriber(link.session, self.key, self._on_sample, history=history)
        else:
            self._zenoh = link.session.declare_subscriber(self.key, self._on_sample)
        self.token = link.announce("MS", topic, ros_type, transient_local=transient_local, depth=depth)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.received += 1
        ros_type = None
        if self.link.cfg.convention == "rmw_zenoh":
            try:
                ros_type = keys.parse_data_key("rmw_zenoh", str(sample.key_expr)).ros_type
            except ValueError:
                ros_type = None  # the receiver counts an untyped payload it cannot place
        try:
            self.callback(self.topic, sample.payload.to_bytes(), ros_type)
        except Exception:  # noqa: BLE001 - a transport thread must survive its callback
            log.exception("ROS 2 subscription %s: callback failed", self.topic)


class ZenohRosWire:
    """TrackGraph's endpoints on the robot's ROS 2 graph (see the module docstring).

    ``session`` is shared (TrackGraph's own) unless ``cfg.connect`` names the robot's router,
    in which case :meth:`open` opens one and :meth:`close` closes it.
    """

    def __init__(self, session: zenoh.Session, cfg: Ros2LinkConfig, *, own_session: bool = False) -> None:
        self.session, self.cfg = session, cfg
        self._own = own_session
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._endpoints: list[_Publisher | _Subscription] = []
        self.zid = str(session.zid())
        self.node_id = next(self._ids)
        self._node_token = None
        if cfg.convention == "rmw_zenoh":
            key = keys.node_token(cfg.domain_id, self.zid, self.node_id, cfg.node_name, cfg.namespace)
            self._node_token = session.liveliness().declare_token(key)

    @classmethod
    def open(cls, cfg: Ros2LinkConfig, session: zenoh.Session | None = None, transport: Any = None) -> ZenohRosWire:
        """The link on ``session``, or on a new client session to ``cfg.connect`` when set
        (``transport``: the TrackGraph TransportConfig whose other settings it keeps)."""
        if cfg.connect:
            from shared.config.transport import TransportConfig
            from shared.transport import open_session

            base = transport if transport is not None else TransportConfig()
            tcfg = base.model_copy(update={"mode": "client", "connect": list(cfg.connect), "listen": []})
            return cls(open_session(tcfg), cfg, own_session=True)
        if session is None:
            raise ValueError("ZenohRosWire.open: no session and no ros2.link.connect endpoints")
        return cls(session, cfg)

    def announce(self, kind: str, topic: str, ros_type: str, *, transient_local: bool, depth: int) -> Any:
        """Declare the liveliness token of one endpoint (rmw_zenoh only; None otherwise)."""
        if self.cfg.convention != "rmw_zenoh":
            return None
        cfg = self.cfg
        with self._lock:
            entity = next(self._ids)
        qos = keys.qos_string(reliable=True, transient_local=transient_local, depth=depth)
        key = keys.endpoint_token(
            kind, cfg.domain_id, self.zid, self.node_id, entity, cfg.node_name, cfg.namespace, topic, ros_type,
            type_hash(ros_type, cfg.distro), qos,
        )  # fmt: skip
        return self.session.liveliness().declare_token(key)

    def publisher(self, topic: str, ros_type: str, *, transient_local: bool = False, depth: int = 10) -> _Publisher:
        pub = _Publisher(self, topic, ros_type, transient_local, depth)
        with self._lock:
            self._endpoints.append(pub)
        return pub

    def subscribe(self, topic: str, ros_type: str, callback: RawCallback, *, transient_local: bool = False, depth: int = 10) -> _Subscription:
        sub = _Subscription(self, topic, ros_type, callback, transient_local, depth)
        with self._lock:
            self._endpoints.append(sub)
        return sub

    def close(self) -> None:
        with self._lock:
            endpoints, self._endpoints = self._endpoints, []
        for ep in reversed(endpoints):
            try:
                ep.close()
            except Exception:  # noqa: BLE001 - closing twice, or the session went first
                log.debug("closing %r failed", ep, exc_info=True)
        if self._node_token is not None:
            try:
                self._node_token.undeclare()
            except Exception:  # noqa: BLE001
                log.debug("undeclaring the node token failed", exc_info=True)
            self._node_token = None
        if self._own:
            self.session.close()
