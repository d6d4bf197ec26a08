"""The ROS 2 side of a session, without Zenoh: publish messages on ROS topics, receive raw CDR.

A :class:`RosWire` is what the ROS 2 sessions (``services/ros2``) talk through, as the
services' sessions talk through a :class:`~shared.runtime.bus.Bus`: over the network it is
:class:`shared.ros2.link.ZenohRosWire` (either key convention, liveliness tokens and
attachments included); in tests it is :class:`InProcessRosWire`, which delivers each
publication to the subscribers of its topic at once, on the publishing thread.

Subscribers get the raw payload and the type the key named (``None`` under the bridge
convention, whose keys carry no type): decoding is the receiver's, so that one hostile
payload is counted where it is understood instead of crashing a transport thread.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from collections.abc import Callable
from typing import Any, Protocol

from shared.ros2.types import encode

RawCallback = Callable[[str, bytes, "str | None"], None]
"""``callback(topic, payload, ros_type_or_None)``."""


class RosPublisher(Protocol):
    """One ROS topic, one message type."""

    topic: str
    ros_type: str

    def put(self, msg: Any) -> None:
        """Serialise ``msg`` (a rosbags message object of ``ros_type``) to CDR and send it."""

    def put_raw(self, payload: bytes, stamp_ns: int | None = None) -> None:
        """Send CDR bytes as they are (a bag player's recorded payloads)."""

    def has_subscribers(self) -> bool: ...

    def close(self) -> None: ...


class RosSubscription(Protocol):
    topic: str

    def close(self) -> None: ...


class RosWire(Protocol):
    """Publishers and subscriptions on a ROS 2 graph."""

    def publisher(self, topic: str, ros_type: str, *, transient_local: bool = False, depth: int = 10) -> RosPublisher: ...

    def subscribe(
        self, topic: str, ros_type: str, callback: RawCallback, *, transient_local: bool = False, depth: int = 10,
    ) -> RosSubscription: ...  # fmt: skip

    def close(self) -> None: ...


class _Pub:
    def __init__(self, wire: InProcessRosWire, topic: str, ros_type: str, distro: str, transient_local: bool) -> None:
        self.wire, self.topic, self.ros_type, self.distro = wire, topic, ros_type, distro
        self.transient_local = transient_local
        self.sent = 0

    def put(self, msg: Any) -> None:
        self.put_raw(encode(msg, self.ros_type, self.distro))

    def put_raw(self, payload: bytes, stamp_ns: int | None = None) -> None:
        self.sent += 1
        self.wire.deliver(self.topic, bytes(payload), self.ros_type, latch=self.transient_local)

    def has_subscribers(self) -> bool:
        return bool(self.wire.subscribers(self.topic))

    def close(self) -> None:
        pass


class _Sub:
    def __init__(self, wire: InProcessRosWire, topic: str, callback: RawCallback) -> None:
        self.wire, self.topic, self.callback = wire, topic, callback

    def close(self) -> None:
        self.wire.unsubscribe(self)


class InProcessRosWire:
    """A ROS graph in one process: for tests of the ROS 2 sessions, and to see the messages
    they send (``sent``: topic -> list of (ros_type, payload))."""

    def __init__(self, distro: str = "jazzy", *, keep: bool = True, typed_keys: bool = True) -> None:
        self.distro = distro
        self.keep = keep
        self.typed_keys = typed_keys
        """False: subscribers get no type (as under the bridge convention)."""
        self._subs: dict[str, list[_Sub]] = defaultdict(list)
        self._latched: dict[str, tuple[bytes, str]] = {}
        self._lock = threading.Lock()
        self.sent: dict[str, list[tuple[str, bytes]]] = defaultdict(list)

    def publisher(self, topic: str, ros_type: str, *, transient_local: bool = False, depth: int = 10) -> _Pub:
        return _Pub(self, topic, ros_type, self.distro, transient_local)

    def subscribe(self, topic: str, ros_type: str, callback: RawCallback, *, transient_local: bool = False, depth: int = 10) -> _Sub:
        sub = _Sub(self, topic, callback)
        with self._lock:
            self._subs[topic].append(sub)
            latched = self._latched.get(topic) if transient_local else None
        if latched is not None:
            callback(topic, latched[0], latched[1] if self.typed_keys else None)
        return sub

    def subscribers(self, topic: str) -> list[_Sub]:
        with self._lock:
            return list(self._subs.get(topic, ()))

    def unsubscribe(self, sub: _Sub) -> None:
        with self._lock:
            if sub in self._subs.get(sub.topic, []):
                self._subs[sub.topic].remove(sub)

    def deliver(self, topic: str, payload: bytes, ros_type: str, *, latch: bool = False) -> None:
        with self._lock:
            if self.keep:
                self.sent[topic].append((ros_type, payload))
            if latch:
                self._latched[topic] = (payload, ros_type)
            subs = list(self._subs.get(topic, ()))
        for s in subs:
            s.callback(topic, payload, ros_type if self.typed_keys else None)

    def close(self) -> None:
        with self._lock:
            self._subs.clear()
