"""What every service session has in common: a bus, a status book, counted inputs and outputs.

A session is one service's coordination as a state machine: messages come in through the
subscriptions it declares on the :class:`~shared.runtime.bus.Bus` it is given, messages go out
through publishers of that bus, and :meth:`Session.tick` is called now and then for what
depends on time alone (time-outs, periodic work). It never blocks waiting for a message: what
has to wait is held in its state until the message arrives or ``tick`` gives up on it. The
same session runs in a service's own process (``ZenohBus``: one thread per subscription, and an
:class:`Inbox` worker for the inputs that must keep their order) and in ``trackgraph map``
(``InProcessBus``, one thread).

Every input and output is counted in the session's :class:`~shared.runtime.status.StatusBook`
under its ``shared.topics.Topics`` attribute name (``frames``, ``keyframe_masks``, ...), the
names ``ServiceStatus`` reports. A handler that raises is logged, and its message counted as
rejected and as an error: one bad message never stops a service.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, ClassVar, Generic, TypeVar

from pydantic import BaseModel

from shared.messages.base import Envelope
from shared.runtime.bus import Bus, Endpoint, Policy
from shared.runtime.status import StatusBook
from shared.topics import Topics

log = logging.getLogger(__name__)

M = TypeVar("M", bound=BaseModel)
R = TypeVar("R", bound=BaseModel)

LATER = object()
"""Returned by a handler whose message is not finished yet (held for later): the session
counts it as processed itself when it is."""


class FairLock:
    """A reentrant lock handed to waiting threads in the order they asked for it.

    Over Zenoh each subscription delivers on its own thread; with a plain lock the thread
    that just released it tends to take it again at once, so the frames of one key could run
    many messages ahead of another key's that arrived meanwhile (a keyframe's CLIP features
    behind the next ten frames). First come, first served keeps the session seeing its inputs
    in about the order they arrived, as one queue would.
    """

    def __init__(self) -> None:
        self._cv = threading.Condition(threading.Lock())
        self._owner: int | None = None
        self._depth = 0
        self._waiting: collections.deque[int] = collections.deque()

    def acquire(self) -> bool:
        me = threading.get_ident()
        with self._cv:
            if self._owner == me:
                self._depth += 1
                return True
            self._waiting.append(me)
            while self._owner is not None or self._waiting[0] != me:
                self._cv.wait()
            self._waiting.popleft()
            self._owner, self._depth = me, 1
            return True

    def release(self) -> None:
        with self._cv:
            if self._owner != threading.get_ident():
                raise RuntimeError("release of a FairLock this thread does not hold")
            self._depth -= 1
            if self._depth == 0:
                self._owner = None
                self._cv.notify_all()

    def __enter__(self) -> FairLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class Inbox:
    """One ordered queue in front of a session's queued inputs, worked off by one thread.

    A node gives one to its session: each subscription's thread then only decodes and queues
    (a hostile flood is rejected at decode and never waits behind a slow frame), and one worker
    hands the session its inputs in the order they arrived across keys. When the queue is full
    the subscription's thread waits here, its own queue fills and drops what comes (counted).
    Without one (``trackgraph map``), the bus's delivery is the order.
    """

    def __init__(self, capacity: int, *, name: str, start: bool = True) -> None:
        """With ``start=False`` what is put waits until :meth:`start` (a node starts its inbox
        once the session it feeds is made)."""
        self.name = name
        self._q: queue.Queue[tuple[str, Callable[[], None]]] = queue.Queue(maxsize=capacity)
        self._waiting: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        if start:
            self.start()

    def start(self) -> None:
        """Start working off the queue."""
        self._thread.start()

    def put(self, input_name: str, work: Callable[[], None]) -> None:
        with self._lock:
            self._waiting[input_name] += 1
        while not self._stop.is_set():
            try:
                self._q.put((input_name, work), timeout=0.2)
                return
            except queue.Full:
                continue
        with self._lock:  # stopping: it will not be handled
            self._waiting[input_name] -= 1

    def pending(self, *names: str) -> int:
        """Messages of these inputs (all when none named) queued and not yet being handled."""
        with self._lock:
            return sum(n for k, n in self._waiting.items() if not names or k in names)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                input_name, work = self._q.get(timeout=0.2)
            except queue.Empty:
                continue
            with self._lock:  # being handled now: no longer waiting
                self._waiting[input_name] -= 1
            try:
                work()
            except Exception:  # noqa: BLE001 - the session counts its own failures; this is a last resort
                log.exception("%s: work item failed", self.name)

    def stop(self) -> None:
        """Stop after the item being handled; what is still queued is dropped."""
        self._stop.set()
        if self._thread.ident is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=30)


class Output(Generic[M]):
    """A publisher of one topic that counts what it sends in the session's book."""

    def __init__(self, session: Session, name: str, msg_type: type[M], *, reliable: bool = True) -> None:
        self.name = name
        self._book = session.book
        self._pub = session.bus.publisher(getattr(session.topics, name), msg_type, reliable=reliable)

    @property
    def seq(self) -> int:
        """Sequence number of the next message, i.e. how many went out (or where a resumed
        stream goes on from)."""
        return self._pub.seq

    @seq.setter
    def seq(self, value: int) -> None:
        self._pub.seq = int(value)

    def put(self, body: M) -> int:
        seq = self._pub.put(body)
        self._book.published(self.name)
        return seq

    def has_subscribers(self) -> bool:
        return self._pub.has_subscribers()

    def close(self) -> None:
        self._pub.close()


class Session:
    """Base of the services' sessions; subclasses set ``service`` and declare their endpoints.

    ``serialized`` sessions run every handler and ``tick`` under one lock (their core is not
    thread-safe and over Zenoh each subscription delivers on its own thread); the others
    guard their own state.
    """

    service: ClassVar[str]
    serialized: ClassVar[bool] = True

    def __init__(
        self, bus: Bus, *, clock: Callable[[], float] = time.monotonic, inbox: Inbox | None = None, book: StatusBook | None = None,
    ) -> None:  # fmt: skip
        self.bus = bus
        self.inbox = inbox
        """Where the queued inputs wait for their turn, when the caller runs one."""
        self.topics = Topics(bus.robot_id)
        self.clock = clock
        self.book = book if book is not None else StatusBook(self.service, clock=clock)
        """The session's counters; a node that reported before the session existed (models
        loading) hands its book in, so the counting goes on in the same one."""
        self.lock = FairLock()
        """Held by every handler and ``tick`` of a serialized session (reentrant, first come first served)."""
        self.inputs: dict[str, Endpoint] = {}
        """Topic name -> the subscription or queryable that feeds it."""
        self._outputs: list[Output] = []
        self._closed = False

    # ---------------------------------------------------------------- wiring

    def output(self, name: str, msg_type: type[M], *, reliable: bool = True) -> Output[M]:
        out = Output(self, name, msg_type, reliable=reliable)
        self._outputs.append(out)
        return out

    def subscribe(
        self, name: str, msg_type: type[M], handler: Callable[[M], Any], *, policy: Policy = "fifo", capacity: int = 64,
        queued: bool = False,
    ) -> Endpoint:  # fmt: skip
        """Feed topic ``name`` to ``handler(body)``; counted received, then processed (unless
        the handler returns :data:`LATER`) or rejected (it raised). A ``queued`` input goes
        through the session's :class:`Inbox` when it has one, in arrival order with the other
        queued inputs; the others are handled on their subscription's thread at once."""
        book = self.book

        def handle(env: Envelope[M]) -> None:
            if self.serialized:
                with self.lock:
                    self.handle(name, handler, env)
            else:
                self.handle(name, handler, env)

        inbox = self.inbox if queued else None

        def deliver(env: Envelope[M]) -> None:
            book.count(name, "received")
            if inbox is None:
                handle(env)
            else:
                inbox.put(name, lambda: handle(env))

        sub = self.bus.subscribe(
            getattr(self.topics, name), msg_type, deliver, policy=policy, capacity=capacity, name=f"{self.service}:{name}",
            on_drop=lambda: book.count(name, "dropped"), on_reject=lambda _why: book.count(name, "rejected"),
        )  # fmt: skip
        book.declare_input(name, sub.pending if inbox is None else (lambda: sub.pending() + inbox.pending(name)))
        self.inputs[name] = sub
        return sub

    def serve(
        self, name: str, request_type: type[M], reply_type: type[R], handler: Callable[[M], R], *, workers: int = 1
    ) -> Endpoint:
        """Answer requests on topic ``name`` with ``handler(body)``; a handler that raises is
        counted and becomes the caller's error reply (the bus's)."""
        book = self.book

        def answer(env: Envelope[M]) -> R:
            book.count(name, "received")
            try:
                reply = handler(env.body)
            except Exception:
                book.count(name, "rejected")
                book.error()
                raise
            book.count(name, "processed")
            return reply

        q = self.bus.serve(getattr(self.topics, name), request_type, reply_type, answer, workers=workers)
        # (a queryable that cannot tell its queue depth reports none)
        book.declare_input(name, getattr(q, "pending", None))
        self.inputs[name] = q
        return q

    def handle(self, name: str, handler: Callable[[M], Any], env: Envelope[M]) -> None:
        try:
            result = handler(env.body)
        except Exception:  # noqa: BLE001 - one bad message must not stop the service
            self.book.count(name, "rejected")
            self.book.error()
            log.exception("%s: %s failed on a %s (seq %d)", self.service, name, type(env.body).__name__, env.seq)
            return
        if result is not LATER:
            self.book.count(name, "processed")

    def queued(self, *names: str) -> int:
        """Messages of these inputs (all when none named) waiting in their queues, the inbox's included."""
        waiting = sum(ep.pending() for n, ep in self.inputs.items() if (not names or n in names) and hasattr(ep, "pending"))
        return waiting + (self.inbox.pending(*names) if self.inbox is not None else 0)

    # ---------------------------------------------------------------- running

    @contextlib.contextmanager
    def recovering(self, what: str) -> Iterator[None]:
        """Run the block; if it raises, count an error and log it instead (the next ``what``
        tries again: a session's periodic work never stops on one failure)."""
        try:
            yield
        except Exception:  # noqa: BLE001 - counted and logged; the next call tries again
            self.book.error()
            log.exception("%s: %s failed", self.service, what)

    def tick(self, now: float) -> Any:
        """Whatever depends on time alone; the default has nothing to do."""
        return None

    def close(self) -> None:
        """Stop the inbox after the item in hand (subscription threads waiting for room in it
        give up), close this session's subscriptions, queryables and publishers (not the
        bus). Not under the lock: a subscription's close waits for its thread, which may want it."""
        if self._closed:
            return
        self._closed = True
        if self.inbox is not None:
            self.inbox.stop()
        for ep in list(self.inputs.values()):
            try:
                ep.close()
            except Exception:  # noqa: BLE001 - already gone with its transport
                log.debug("%s: closing an input failed", self.service, exc_info=True)
        for out in self._outputs:
            try:
                out.close()
            except Exception:  # noqa: BLE001
                log.debug("%s: closing %s failed", self.service, out.name, exc_info=True)


class Ticker:
    """Calls ``tick(clock())`` at once and then every ``period_s`` on a thread of its own until
    :meth:`stop` (a node's time-outs; in one process the caller ticks its sessions itself). A
    failed tick is logged, reported to ``on_error`` and tried again on the next one."""

    def __init__(self, tick: Callable[[float], Any], period_s: float, *, name: str, clock: Callable[[], float] = time.monotonic,
                 on_error: Callable[[], None] | None = None) -> None:  # fmt: skip
        if period_s <= 0:
            raise ValueError("period_s must be positive")
        self._tick, self.period_s, self._clock, self._on_error = tick, period_s, clock, on_error
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                self._tick(self._clock())
            except Exception:  # noqa: BLE001 - a failed tick is the session's to report; keep ticking
                if self._on_error is not None:
                    self._on_error()
                log.exception("%s failed", self._thread.name)
            if self._stop.wait(self.period_s):
                return

    def stop(self, timeout: float | None = 30.0) -> None:
        """Stop ticking; waits up to ``timeout`` for a tick in progress (a request may be in flight)."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
