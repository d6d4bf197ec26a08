"""Zenoh sessions and typed publish/subscribe/query helpers.

This is the only module of the common library that imports zenoh. Every helper decodes and
validates with :mod:`shared.codec`; a bad payload is logged, counted and skipped, never
raised into the service. Zenoh callbacks only hand bytes to a bounded queue: decoding and
user handlers run on the helper's own thread (blocking inside a zenoh callback stalls the
session).
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Generic, Literal, TypeVar

import zenoh
from pydantic import BaseModel

from shared.codec import CodecError, decode, encode
from shared.config.transport import CodecConfig, TransportConfig
from shared.messages.base import Envelope
from shared.runtime.bus import BusError

log = logging.getLogger(__name__)

M = TypeVar("M", bound=BaseModel)
R = TypeVar("R", bound=BaseModel)


class TransportError(BusError):
    """A request found no answer in time, or the remote side answered with an error."""


def zenoh_config(cfg: TransportConfig) -> zenoh.Config:
    """Build a zenoh.Config from our typed settings (the optional JSON5 file first)."""
    zc = zenoh.Config.from_file(cfg.zenoh_config_file) if cfg.zenoh_config_file else zenoh.Config()
    zc.insert_json5("mode", json.dumps(cfg.mode))
    if cfg.connect:
        zc.insert_json5("connect/endpoints", json.dumps(cfg.connect))
    # Always set listeners: left unset, a zenoh peer listens on every interface (tcp/[::]:0).
    zc.insert_json5("listen/endpoints", json.dumps(cfg.listen))
    zc.insert_json5("connect/timeout_ms", json.dumps(int(cfg.connect_timeout_s * 1000) if cfg.connect_timeout_s >= 0 else -1))
    zc.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    zc.insert_json5("scouting/gossip/enabled", json.dumps(cfg.gossip_scouting))
    zc.insert_json5("transport/shared_memory/enabled", json.dumps(cfg.shared_memory))
    if cfg.timestamping:
        zc.insert_json5("timestamping/enabled", json.dumps({"router": True, "peer": True, "client": True}))
    return zc


def open_session(cfg: TransportConfig) -> zenoh.Session:
    """Open a Zenoh session. Close it (context manager or ``finally``): a process holding a
    callback subscriber that exits without ``close()`` hangs."""
    try:
        return zenoh.open(zenoh_config(cfg))
    except zenoh.ZError as exc:
        where = ", ".join(cfg.connect or cfg.listen) or "no endpoints"
        raise TransportError(f"cannot open a zenoh {cfg.mode} session ({where}): {exc}") from None


@dataclass
class LinkStats:
    """Counters of one typed endpoint; services report them in their status."""

    received: int = 0
    rejected: int = 0
    dropped: int = 0
    published: int = 0
    handler_errors: int = 0
    last_error: str | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add(self, name: str, n: int = 1, error: str | None = None) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + n)
            if error is not None:
                self.last_error = error

    def as_dict(self) -> dict:
        with self._lock:
            return {k: getattr(self, k) for k in ("received", "rejected", "dropped", "published", "handler_errors", "last_error")}


def robot_of_key(key: str) -> str | None:
    """The robot id in a ``trackgraph/<robot>/...`` key, or None for other keys (and wildcards)."""
    parts = key.split("/")
    if len(parts) >= 2 and parts[0] == "trackgraph" and "*" not in parts[1] and "$" not in parts[1]:
        return parts[1]
    return None


def check_robot(key: str, robot: str | None, env: Envelope) -> None:
    """Refuse an envelope whose ``robot`` is not the robot of the key it came on: one robot's
    frames must never reach another's map because a client mislabelled them."""
    if robot is not None and env.robot_id != robot:
        raise CodecError(f"{type(env.body).__name__} on {key} claims robot {env.robot_id!r}; this key is robot {robot!r}")


class _RateLimitedLog:
    """At most one warning per key every ``period`` seconds, with the count in between."""

    def __init__(self, period: float = 5.0) -> None:
        self.period = period
        self._last: dict[str, tuple[float, int]] = {}

    def warn(self, key: str, msg: str) -> None:
        now = time.monotonic()
        last, skipped = self._last.get(key, (0.0, 0))
        if now - last >= self.period:
            extra = f" ({skipped} more since last report)" if skipped else ""
            log.warning("%s: %s%s", key, msg, extra)
            self._last[key] = (now, 0)
        else:
            self._last[key] = (last, skipped + 1)


_warn = _RateLimitedLog()


class TypedPublisher(Generic[M]):
    """Publishes one message type on one key, numbering and stamping each envelope."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        msg_type: type[M],
        *,
        robot_id: str,
        codec: CodecConfig | None = None,
        reliable: bool = True,
    ) -> None:
        self.key, self.msg_type, self.robot_id = key, msg_type, robot_id
        self.codec = codec or CodecConfig()
        # DROP silently loses large fragmented messages; frames, masks and deltas need BLOCK.
        cc = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        self._pub = session.declare_publisher(key, congestion_control=cc)
        self.seq = 0
        self.stats = LinkStats()

    def put(self, body: M, stamp: float | None = None) -> int:
        """Encode and send ``body``; returns its sequence number."""
        if not isinstance(body, self.msg_type):
            raise TypeError(f"{self.key} carries {self.msg_type.__name__}, not {type(body).__name__}")
        seq = self.seq
        payload = encode(body, robot_id=self.robot_id, seq=seq, stamp=time.time() if stamp is None else stamp, cfg=self.codec)
        self._pub.put(payload)
        self.seq += 1
        self.stats.add("published")
        return seq

    def has_subscribers(self) -> bool:
        """True if some subscriber in the network matches this key."""
        status = self._pub.matching_status
        return status if isinstance(status, bool) else bool(status.matching)

    def wait_for_subscribers(self, timeout: float) -> bool:
        """Wait until a subscriber matches (lossless replay must not publish into the void)."""
        deadline = time.monotonic() + timeout
        while not self.has_subscribers():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def close(self) -> None:
        if getattr(self, "_closed", False):
            return
        self._closed = True
        self._pub.undeclare()


class _Served:
    """What a subscriber and a queryable share: a queue filled by the Zenoh callback under
    ``_cv`` and emptied by worker threads, and the declared Zenoh entity behind it."""

    _queue: collections.deque
    _cv: threading.Condition
    _closed: bool
    _declared: zenoh.Subscriber | zenoh.Queryable
    _workers: list[threading.Thread]

    def pending(self) -> int:
        """Messages (or requests) queued and not yet being handled."""
        with self._cv:
            return len(self._queue)

    def close(self) -> None:
        """Stop receiving; calling it again does nothing."""
        with self._cv:
            if self._closed:
                return
            self._closed = True
            self._cv.notify_all()
        self._declared.undeclare()
        for t in self._workers:
            # A handler may close its own subscriber; a thread cannot join itself.
            if t is not threading.current_thread():
                t.join(timeout=5)


class TypedSubscriber(_Served, Generic[M]):
    """Receives one message type from one key through a bounded queue.

    ``policy="fifo"`` keeps messages in order and, when full, drops the new one, counts it
    and warns; ``policy="latest"`` keeps the newest ``capacity`` and counts what it drops
    (live frames). Neither ever waits in the Zenoh callback: a blocked callback stalls the
    whole session's receive path, so keep-alives go unread, the link lease expires, the
    session reconnects and everything in flight is lost (measured: the demo's tracker lost
    its link within seconds under load). Lossless replay is paced end to end instead: the
    source stays ``source.window_frames`` ahead of the stages' ``frames/ack``. With ``callback``, a worker thread calls it for each valid message;
    otherwise call :meth:`recv`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        msg_type: type[M],
        *,
        codec: CodecConfig | None = None,
        policy: Literal["fifo", "latest"] = "fifo",
        capacity: int = 64,
        callback: Callable[[Envelope[M]], None] | None = None,
        name: str | None = None,
        on_drop: Callable[[], None] | None = None,
        on_reject: Callable[[str], None] | None = None,
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be at least 1")
        self.key, self.msg_type, self.policy, self.capacity = key, msg_type, policy, capacity
        self.robot = robot_of_key(key)
        self._on_drop, self._on_reject = on_drop, on_reject
        self.codec = codec or CodecConfig()
        self.stats = LinkStats()
        self._queue: collections.deque[bytes] = collections.deque()
        self._cv = threading.Condition()
        self._closed = False
        self._declared = session.declare_subscriber(key, self._on_sample)
        self._workers = []
        if callback is not None:
            self._workers.append(
                threading.Thread(target=self._run, args=(callback,), name=name or f"sub:{key}", daemon=True)
            )
            self._workers[0].start()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        with self._cv:
            if self._closed:
                return
            dropped = len(self._queue) >= self.capacity
            if dropped:
                self.stats.add("dropped")
                if self.policy == "latest":
                    self._queue.popleft()
                    self._queue.append(data)
            else:
                self._queue.append(data)
            self._cv.notify_all()
        if dropped:
            if self.policy == "fifo":
                _warn.warn(self.key, f"subscriber queue full ({self.capacity}): message dropped")
            if self._on_drop is not None:
                self._on_drop()

    def recv(self, timeout: float | None = None) -> Envelope[M] | None:
        """Next valid message, or None on timeout or close. Invalid ones are counted and skipped."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._cv:
                while not self._queue and not self._closed:
                    remaining = None if deadline is None else deadline - time.monotonic()
                    if remaining is not None and remaining <= 0:
                        return None
                    self._cv.wait(remaining)
                if not self._queue:
                    return None
                data = self._queue.popleft()
                self._cv.notify_all()
            try:
                env = decode(data, self.msg_type, self.codec)
                check_robot(self.key, self.robot, env)
            except CodecError as exc:
                self.stats.add("rejected", error=str(exc))
                _warn.warn(self.key, f"rejected payload of {len(data)} bytes: {exc}")
                if self._on_reject is not None:
                    self._on_reject(str(exc))
                continue
            self.stats.add("received")
            return env

    def _run(self, callback: Callable[[Envelope[M]], None]) -> None:
        while not self._closed:
            env = self.recv(timeout=0.2)
            if env is None:
                continue
            try:
                callback(env)
            except Exception as exc:  # noqa: BLE001 - one bad message must not stop the service
                self.stats.add("handler_errors", error=repr(exc))
                log.exception("%s: handler failed on seq %d", self.key, env.seq)


class TypedQueryable(_Served, Generic[M, R]):
    """Answers requests of one type on one key with ``handler``, on ``workers`` threads.

    A malformed request is counted and answered with an error reply; a handler exception
    is answered the same way. Every query is finished, so no caller waits for its timeout.
    At most ``capacity`` queries wait for a worker (0: none, every query finds an idle one
    or is refused): one more is answered "overloaded: ..." at once (``on_drop`` is told).
    The handler's envelope carries ``received``, when the query arrived, so a deadline can
    count the wait for a worker.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        request_type: type[M],
        reply_type: type[R],
        handler: Callable[[Envelope[M]], R],
        *,
        robot_id: str,
        codec: CodecConfig | None = None,
        workers: int = 1,
        capacity: int = 256,
        on_drop: Callable[[], None] | None = None,
    ) -> None:
        self.key, self.request_type, self.reply_type = key, request_type, reply_type
        self.on_drop = on_drop
        self.robot_id, self.handler = robot_id, handler
        self.codec = codec or CodecConfig()
        self.stats = LinkStats()
        self._queue: collections.deque[tuple[zenoh.Query, float]] = collections.deque()
        """Queries waiting for a worker, each with its ``time.monotonic()`` of arrival."""
        self._cv = threading.Condition()
        self._closed = False
        if capacity < 0 or workers < 1:
            raise ValueError(f"{key}: a queryable needs workers >= 1 and capacity >= 0 (got {workers}, {capacity})")
        self.capacity = capacity
        self._idle = workers
        """Workers not answering a query now: a query for one of them never counts as waiting."""
        self._seq = 0
        self._declared = session.declare_queryable(key, self._on_query)
        self._workers = [
            threading.Thread(target=self._run, name=f"qbl:{key}:{i}", daemon=True) for i in range(workers)
        ]
        for t in self._workers:
            t.start()

    def _on_query(self, query: zenoh.Query) -> None:
        received = time.monotonic()
        with self._cv:
            if len(self._queue) >= self.capacity + self._idle:
                self.stats.add("dropped")
                overloaded = True
            else:
                self._queue.append((query, received))
                self._cv.notify()
                overloaded = False
        if overloaded:
            # Answering at once is cheap and non-blocking, and keeps the caller from waiting out its timeout.
            query.reply_err(f"overloaded: every worker busy and {self.capacity} requests waiting; try again shortly".encode())
            query.drop()
            if self.on_drop is not None:
                try:
                    self.on_drop()
                except Exception:  # noqa: BLE001 - a counter must not break the callback
                    log.debug("%s: on_drop failed", self.key, exc_info=True)

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._closed:
                    self._cv.wait(0.2)
                if self._closed and not self._queue:
                    return
                query, received = self._queue.popleft()
                self._idle -= 1
            try:
                self._answer(query, received)
            finally:
                query.drop()
                with self._cv:
                    self._idle += 1

    def _answer(self, query: zenoh.Query, received: float) -> None:
        payload = query.payload
        if payload is None:
            self.stats.add("rejected", error="empty request")
            query.reply_err(b"empty request: expected a " + self.request_type.__name__.encode())
            return
        data = payload.to_bytes()
        try:
            env = replace(decode(data, self.request_type, self.codec), received=received)
            check_robot(self.key, robot_of_key(self.key), env)
        except CodecError as exc:
            self.stats.add("rejected", error=str(exc))
            _warn.warn(self.key, f"rejected request: {exc}")
            query.reply_err(f"bad request: {exc}".encode())
            return
        self.stats.add("received")
        try:
            reply = self.handler(env)
            with self._cv:
                seq = self._seq
                self._seq += 1
            out = encode(reply, robot_id=self.robot_id, seq=seq, stamp=time.time(), cfg=self.codec)
        except Exception as exc:  # noqa: BLE001 - report the failure to the caller, keep serving
            self.stats.add("handler_errors", error=repr(exc))
            log.exception("%s: handler failed", self.key)
            query.reply_err(f"internal error: {type(exc).__name__}: {exc}".encode())
            return
        query.reply(self.key, out)
        self.stats.add("published")



def request(
    session: zenoh.Session,
    key: str,
    body: BaseModel,
    reply_type: type[R],
    *,
    robot_id: str,
    timeout: float,
    codec: CodecConfig | None = None,
    seq: int = 0,
) -> Envelope[R]:
    """Send one request and wait for the first reply; raises TransportError on timeout or error."""
    codec = codec or CodecConfig()
    payload = encode(body, robot_id=robot_id, seq=seq, stamp=time.time(), cfg=codec)
    replies = session.get(key, payload=payload, timeout=timeout)
    for reply in replies:
        if reply.ok is not None:
            try:
                return decode(reply.ok.payload.to_bytes(), reply_type, codec)
            except CodecError as exc:
                raise TransportError(f"{key}: malformed reply: {exc}") from None
        err = reply.err.payload.to_bytes().decode("utf-8", "replace") if reply.err is not None else "unknown"
        raise TransportError(f"{key}: {err}")
    raise TransportError(f"{key}: no reply within {timeout:.1f} s (is the service running?)")


def declare_alive(session: zenoh.Session, key: str) -> zenoh.LivelinessToken:
    """Announce a service; the token disappears when the session closes or the process dies."""
    return session.liveliness().declare_token(key)


class LivelinessWatcher:
    """Tracks which liveliness tokens under a key expression are present."""

    def __init__(self, session: zenoh.Session, key_expr: str, on_change: Callable[[str, bool], None] | None = None) -> None:
        self._alive: set[str] = set()
        self._cv = threading.Condition()
        self._on_change = on_change
        self._sub = session.liveliness().declare_subscriber(key_expr, self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        present = sample.kind == zenoh.SampleKind.PUT
        with self._cv:
            (self._alive.add if present else self._alive.discard)(key)
            self._cv.notify_all()
        if self._on_change is not None:
            self._on_change(key, present)

    def alive(self) -> set[str]:
        with self._cv:
            return set(self._alive)

    def wait_for(self, key: str, present: bool = True, timeout: float = 5.0) -> bool:
        """Wait until ``key`` is (or is no longer) alive; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while (key in self._alive) != present:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cv.wait(remaining)
            return True

    def close(self) -> None:
        self._sub.undeclare()


class ZenohBus:
    """The :class:`shared.runtime.bus.Bus` of a service in its own process: every endpoint
    is a typed Zenoh publisher, subscriber or queryable on ``session``."""

    def __init__(self, session: zenoh.Session, robot_id: str, codec: CodecConfig | None = None, *, own_session: bool = False) -> None:
        self.session, self.robot_id = session, robot_id
        self.codec = codec or CodecConfig()
        self._own = own_session
        self._endpoints: list = []
        self._seq = 0
        self._lock = threading.Lock()

    @classmethod
    def open(cls, cfg: TransportConfig, robot_id: str) -> ZenohBus:
        """A bus on a new session of ``cfg``; :meth:`close` closes it."""
        return cls(open_session(cfg), robot_id, cfg.codec, own_session=True)

    def publisher(self, key: str, msg_type: type[M], *, reliable: bool = True) -> TypedPublisher[M]:
        pub = TypedPublisher(self.session, key, msg_type, robot_id=self.robot_id, codec=self.codec, reliable=reliable)
        self._endpoints.append(pub)
        return pub

    def subscribe(self, key: str, msg_type: type[M], callback: Callable[[Envelope[M]], None], *, policy: Literal["fifo", "latest"] = "fifo",
                  capacity: int = 64, name: str | None = None, on_drop: Callable[[], None] | None = None,
                  on_reject: Callable[[str], None] | None = None) -> TypedSubscriber[M]:  # fmt: skip
        sub = TypedSubscriber(self.session, key, msg_type, codec=self.codec, policy=policy, capacity=capacity,
                              callback=callback, name=name, on_drop=on_drop, on_reject=on_reject)  # fmt: skip
        self._endpoints.append(sub)
        return sub

    def serve(self, key: str, request_type: type[M], reply_type: type[R], handler: Callable[[Envelope[M]], R], *,
              workers: int = 1, capacity: int = 256, on_drop: Callable[[], None] | None = None) -> TypedQueryable[M, R]:  # fmt: skip
        q = TypedQueryable(self.session, key, request_type, reply_type, handler, robot_id=self.robot_id, codec=self.codec,
                           workers=workers, capacity=capacity, on_drop=on_drop)  # fmt: skip
        self._endpoints.append(q)
        return q

    def request(self, key: str, body: BaseModel, reply_type: type[R], *, timeout: float) -> R:
        with self._lock:
            seq, self._seq = self._seq, self._seq + 1
        return request(self.session, key, body, reply_type, robot_id=self.robot_id, timeout=timeout, codec=self.codec, seq=seq).body

    def declare_alive(self, key: str) -> zenoh.LivelinessToken:
        return declare_alive(self.session, key)

    def close(self) -> None:
        """Close every endpoint still open (each close is idempotent), then an owned session."""
        for ep in reversed(self._endpoints):
            try:
                ep.close()
            except Exception:  # noqa: BLE001 - already closed, or the session went first
                log.debug("closing %r failed", ep, exc_info=True)
        self._endpoints.clear()
        if self._own:
            self.session.close()
