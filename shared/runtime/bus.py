"""The :class:`Bus` a service session talks through, and its in-process implementation.

A session never sees Zenoh: it is handed a bus and asks it for publishers, subscriptions,
queryables and requests by key. Two buses implement the protocol with the same semantics:

- :class:`shared.transport.ZenohBus`, for services in their own processes;
- :class:`InProcessBus` here, for ``trackgraph map`` and tests: every session of the
  pipeline in one process, with no network and no threads of its own.

The in-process bus queues what is published and delivers it when :meth:`InProcessBus.drain`
is called, in publication order, so a pipeline run in one process is deterministic and never
re-enters a session from inside its own handler. Its fifo subscriptions never drop (nothing
is lost in a batch run); ``latest`` subscriptions keep their newest ``capacity`` messages, as
over Zenoh. Requests are answered at once by the queryable's handler.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeVar

from pydantic import BaseModel

from shared.messages.base import Envelope

if TYPE_CHECKING:  # the book is only a parameter's type here
    from shared.runtime.status import StatusBook

log = logging.getLogger(__name__)

M = TypeVar("M", bound=BaseModel)
R = TypeVar("R", bound=BaseModel)

Policy = Literal["fifo", "latest"]


class BusError(RuntimeError):
    """A request found no answer, or the answering side refused it."""


class Publisher(Protocol[M]):
    seq: int
    """Sequence number the next message will carry."""

    def put(self, body: M) -> int:
        """Send ``body``; returns its sequence number."""
        ...

    def has_subscribers(self) -> bool: ...

    def close(self) -> None: ...


class Endpoint(Protocol):
    """A subscription or a queryable: counted, closable."""

    def pending(self) -> int:
        """Messages waiting to be handled."""
        ...

    def close(self) -> None: ...


class Token(Protocol):
    def undeclare(self) -> None: ...


class Bus(Protocol):
    """What a session may do with the outside world."""

    robot_id: str

    def publisher(self, key: str, msg_type: type[M], *, reliable: bool = True) -> Publisher[M]: ...

    def subscribe(
        self,
        key: str,
        msg_type: type[M],
        callback: Callable[[Envelope[M]], None],
        *,
        policy: Policy = "fifo",
        capacity: int = 64,
        name: str | None = None,
        on_drop: Callable[[], None] | None = None,
        on_reject: Callable[[str], None] | None = None,
    ) -> Endpoint:
        """Call ``callback`` for each valid message on ``key``; ``on_drop`` and ``on_reject``
        are told of each message lost to a full queue and each refused one."""
        ...

    def serve(
        self,
        key: str,
        request_type: type[M],
        reply_type: type[R],
        handler: Callable[[Envelope[M]], R],
        *,
        workers: int = 1,
        capacity: int = 256,
        on_drop: Callable[[], None] | None = None,
    ) -> Endpoint:
        """Answer requests on ``key`` with ``handler`` on ``workers`` threads. At most
        ``capacity`` requests wait for a worker; one more is answered "overloaded" at once and
        ``on_drop`` is told. The handler's envelope has ``received`` set when the bus knows it."""
        ...

    def request(self, key: str, body: BaseModel, reply_type: type[R], *, timeout: float) -> R:
        """One request, the first reply's body; :class:`BusError` on time-out or refusal."""
        ...

    def declare_alive(self, key: str) -> Token: ...

    def close(self) -> None: ...


# ---------------------------------------------------------------- in-process


class _Token:
    def __init__(self, bus: InProcessBus, key: str) -> None:
        self._bus, self.key = bus, key
        bus.alive.add(key)

    def undeclare(self) -> None:
        self._bus.alive.discard(self.key)


class _Sub:
    def __init__(self, bus: InProcessBus, key: str, msg_type: type, callback: Callable, policy: Policy, capacity: int,
                 on_drop: Callable[[], None] | None) -> None:  # fmt: skip
        if capacity < 1:
            raise ValueError("capacity must be at least 1")
        self.bus, self.key, self.msg_type, self.callback = bus, key, msg_type, callback
        self.policy, self.capacity, self.on_drop = policy, capacity, on_drop
        self.queue: collections.deque[Envelope] = collections.deque()
        self.received = 0
        self.dropped = 0
        self.closed = False

    def offer(self, env: Envelope) -> None:
        if self.closed:
            return
        if self.policy == "latest" and len(self.queue) >= self.capacity:
            self.queue.popleft()
            self.dropped += 1
            if self.on_drop is not None:
                self.on_drop()
        self.queue.append(env)
        self.bus._ready.append(self)

    def pending(self) -> int:
        return len(self.queue)

    def close(self) -> None:
        self.closed = True
        self.queue.clear()
        subs = self.bus._subs.get(self.key, [])
        if self in subs:
            subs.remove(self)


class _Pub:
    def __init__(self, bus: InProcessBus, key: str, msg_type: type) -> None:
        self.bus, self.key, self.msg_type = bus, key, msg_type
        self.seq = 0

    def put(self, body: BaseModel, stamp: float | None = None) -> int:
        if not isinstance(body, self.msg_type):
            raise TypeError(f"{self.key} carries {self.msg_type.__name__}, not {type(body).__name__}")
        seq = self.seq
        self.seq += 1
        env = Envelope(body=body, robot_id=self.bus.robot_id, seq=seq, stamp=self.bus.clock() if stamp is None else stamp)
        for sub in list(self.bus._subs.get(self.key, [])):
            if isinstance(body, sub.msg_type):
                sub.offer(env)
        self.bus.published[self.key] = self.bus.published.get(self.key, 0) + 1
        return seq

    def has_subscribers(self) -> bool:
        return bool(self.bus._subs.get(self.key))

    def close(self) -> None:
        pass


class _Queryable:
    def __init__(self, bus: InProcessBus, key: str, request_type: type, handler: Callable) -> None:
        self.bus, self.key, self.request_type, self.handler = bus, key, request_type, handler

    def pending(self) -> int:
        return 0

    def close(self) -> None:
        if self.bus._queryables.get(self.key) is self:
            del self.bus._queryables[self.key]


class InProcessBus:
    """Every session of a pipeline in one process; call :meth:`drain` to deliver."""

    def __init__(self, robot_id: str = "robot0", *, clock: Callable[[], float] | None = None) -> None:
        import time

        self.robot_id = robot_id
        self.clock = clock or time.time
        self._subs: dict[str, list[_Sub]] = {}
        self._queryables: dict[str, _Queryable] = {}
        self._ready: collections.deque[_Sub] = collections.deque()
        self._draining = threading.local()
        self.alive: set[str] = set()
        self.published: dict[str, int] = {}
        """Messages put per key (for tests and summaries)."""

    def publisher(self, key: str, msg_type: type[M], *, reliable: bool = True) -> _Pub:
        return _Pub(self, key, msg_type)

    def subscribe(self, key: str, msg_type: type[M], callback: Callable[[Envelope[M]], None], *, policy: Policy = "fifo",
                  capacity: int = 64, name: str | None = None, on_drop: Callable[[], None] | None = None,
                  on_reject: Callable[[str], None] | None = None) -> _Sub:  # fmt: skip
        sub = _Sub(self, key, msg_type, callback, policy, capacity, on_drop)
        self._subs.setdefault(key, []).append(sub)
        return sub

    def serve(self, key: str, request_type: type[M], reply_type: type[R], handler: Callable[[Envelope[M]], R], *,
              workers: int = 1, capacity: int = 256, on_drop: Callable[[], None] | None = None) -> _Queryable:  # fmt: skip
        # Answered at once on the caller's thread: nothing ever waits, so nothing is dropped.
        if key in self._queryables:
            raise ValueError(f"{key}: a queryable is already declared here")
        q = self._queryables[key] = _Queryable(self, key, request_type, handler)
        return q

    def request(self, key: str, body: BaseModel, reply_type: type[R], *, timeout: float) -> R:
        q = self._queryables.get(key)
        if q is None:
            raise BusError(f"{key}: no queryable (is the service running?)")
        if not isinstance(body, q.request_type):
            raise BusError(f"{key}: bad request: expected a {q.request_type.__name__}, got {type(body).__name__}")
        try:
            reply = q.handler(Envelope(body=body, robot_id=self.robot_id, seq=0, stamp=self.clock()))
        except Exception as exc:  # noqa: BLE001 - a handler's failure is the caller's error reply, as over Zenoh
            log.exception("%s: handler failed", key)
            raise BusError(f"{key}: internal error: {type(exc).__name__}: {exc}") from None
        if not isinstance(reply, reply_type):
            raise BusError(f"{key}: expected a {reply_type.__name__} reply, got {type(reply).__name__}")
        return reply

    def declare_alive(self, key: str) -> _Token:
        return _Token(self, key)

    def pending(self) -> int:
        """Messages published and not yet delivered."""
        return sum(len(s.queue) for subs in self._subs.values() for s in subs)

    def drain(self, max_messages: int | None = None) -> int:
        """Deliver queued messages, each to its subscriber in publication order, until none
        is left (or ``max_messages``); what handlers publish meanwhile is delivered too.
        Returns how many were delivered. A handler's exception propagates: in one process
        the caller decides (a session catches its own)."""
        if getattr(self._draining, "on", False):
            return 0  # called from inside a handler: the outer drain delivers it
        self._draining.on = True
        n = 0
        try:
            while self._ready and (max_messages is None or n < max_messages):
                sub = self._ready.popleft()
                if sub.closed or not sub.queue:
                    continue
                env = sub.queue.popleft()
                sub.received += 1
                sub.callback(env)
                n += 1
        finally:
            self._draining.on = False
        return n

    def close(self) -> None:
        for subs in self._subs.values():
            for s in subs:
                s.closed = True
        self._subs.clear()
        self._queryables.clear()
        self._ready.clear()


def deliver_all(bus: Any) -> int:
    """Drain an in-process bus; a no-op for buses that deliver on their own threads."""
    drain = getattr(bus, "drain", None)
    return drain() if drain is not None else 0


def subscribe_counted(
    bus: Bus, book: StatusBook, input_name: str, key: str, msg_type: type[M], callback: Callable[[Envelope[M]], None],
    **kw: Any,
) -> Endpoint:  # fmt: skip
    """``bus.subscribe`` (``kw``: policy, capacity, name) as the service's input ``input_name``:
    ``book`` counts what the bus drops or refuses there and reads its queue depth."""
    sub = bus.subscribe(
        key, msg_type, callback,
        on_drop=lambda: book.count(input_name, "dropped"), on_reject=lambda _why: book.count(input_name, "rejected"), **kw,
    )  # fmt: skip
    book.declare_input(input_name, sub.pending)
    return sub
