"""Replay scheduling of the source, with a fake clock (no Zenoh, no sleeping)."""

from __future__ import annotations

import numpy as np

from services.source.core import planned_indices, replay
from shared.config import SourceConfig
from shared.datasets.base import SequenceReader
from shared.geometry import Intrinsics
from shared.messages import Frame


class FakeReader(SequenceReader):
    def __init__(self, n: int) -> None:
        self.n = n
        self.intrinsics = Intrinsics(fx=10, fy=10, cx=1.5, cy=1.5, width=4, height=4)
        self.depth_scale = 1000.0
        self.loaded: list[int] = []

    def __len__(self) -> int:
        return self.n

    def pose(self, i: int) -> np.ndarray:
        T = np.eye(4)
        T[0, 3] = i
        return T

    def frame(self, i: int) -> Frame:
        self.loaded.append(i)
        return Frame(
            frame_index=i,
            rgb=np.zeros((4, 4, 3), np.uint8),
            depth=np.ones((4, 4), np.uint16),
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            T_world_cam=self.pose(i),
        )


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        assert dt >= 0
        self.t += dt


def test_planned_indices():
    assert planned_indices(10, 1) == list(range(10))
    assert planned_indices(10, 3) == [0, 3, 6, 9]
    assert planned_indices(10, 3, max_frames=2) == [0, 3]
    assert planned_indices(0, 2) == []


def test_lossless_sends_everything_in_order():
    reader = FakeReader(12)
    sent = []
    stats = replay(reader, SourceConfig(mode="lossless", stride=2), lambda f: sent.append(f.frame_index))
    assert sent == [0, 2, 4, 6, 8, 10]
    assert stats.published == 6 and stats.dropped == 0 and stats.last_frame_index == 10


def test_live_paces_at_rate_when_consumer_keeps_up():
    clock = FakeClock()
    sent_at = []
    reader = FakeReader(10)
    stats = replay(
        reader, SourceConfig(mode="live", rate_hz=10.0), lambda f: sent_at.append(clock.t),
        clock=clock, sleep=clock.sleep,
    )  # fmt: skip
    assert stats.published == 10 and stats.dropped == 0
    np.testing.assert_allclose(sent_at, np.arange(10) * 0.1, atol=1e-9)


def test_live_drops_and_counts_when_publish_blocks():
    clock = FakeClock()
    reader = FakeReader(20)

    def slow_publish(frame: Frame) -> None:
        # A lagging subscriber makes each put block for 2.5 frame periods.
        clock.t += 0.25

    stats = replay(reader, SourceConfig(mode="live", rate_hz=10.0), slow_publish, clock=clock, sleep=clock.sleep)
    assert stats.published + stats.dropped == 20
    assert stats.dropped > 0 and stats.published < 20
    assert sorted(set(reader.loaded) | set(stats.dropped_indices)) == list(range(20))
    assert not set(reader.loaded) & set(stats.dropped_indices), "dropped frames are never loaded"
    # Roughly one frame in 2.5 gets through.
    assert 6 <= stats.published <= 10


def test_stop_request_ends_replay():
    reader = FakeReader(100)
    sent = []
    replay(reader, SourceConfig(), lambda f: sent.append(f.frame_index), should_stop=lambda: len(sent) >= 5)
    assert sent == [0, 1, 2, 3, 4]


def test_pacer_keeps_the_source_a_window_ahead_of_the_slowest_live_stage():
    from services.source.core import Pacer

    p = Pacer(plan=[0, 2, 4, 6, 8, 10], window=2, stages=["tracker", "fusion"])
    both = {"tracker", "fusion", "source"}
    assert p.ready(0, both) and p.ready(1, both) and not p.ready(2, both)
    p.ack("tracker", 2)  # position 1
    assert not p.ready(3, both)  # fusion still has acknowledged nothing
    p.ack("fusion", 0)
    assert p.ready(2, both) and not p.ready(3, both)
    p.ack("fusion", 2)
    assert p.ready(3, both) and not p.ready(4, both)
    # A stage that is not running does not hold the source, an unknown frame or stage is ignored.
    assert p.ready(4, {"tracker"}) is False and p.ready(3, {"tracker"})
    assert p.ready(5, set())
    p.ack("tracker", 7)
    p.ack("viewer", 10)
    assert p.done == {"tracker": 1, "fusion": 1}


def test_a_vanished_stage_holds_the_source_for_hold_gone_s():
    from services.source.core import Pacer

    now = [0.0]
    p = Pacer(plan=list(range(10)), window=1, stages=["tracker", "fusion"], hold_gone_s=5.0, clock=lambda: now[0])
    assert p.ready(0, set()) and p.ready(5, set())  # never seen: not waited for
    p.ack("tracker", 3)
    p.ack("fusion", 3)
    assert p.ready(4, {"tracker", "fusion"}) and not p.ready(5, {"tracker", "fusion"})
    p.ack("tracker", 4)
    now[0] = 1.0
    assert not p.ready(5, {"tracker"})  # fusion vanished at 0 s (a restart): it still counts
    now[0] = 4.5
    assert not p.ready(5, {"tracker"})  # gone 4.5 s of 5
    now[0] = 5.5
    assert p.ready(5, {"tracker"})  # gone too long: the source goes on without it
    p.ack("tracker", 5)
    now[0] = 7.0
    # back (restarted): what it lost while away is never acknowledged, so it paces afresh
    assert p.ready(6, {"tracker", "fusion"}) and p.rejoins == {"fusion": 1}
    p.ack("tracker", 6)
    assert not p.ready(7, {"tracker", "fusion"})  # and then holds like any stage
    p.ack("fusion", 6)
    assert p.ready(7, {"tracker", "fusion"})


def test_pacer_wait_returns_on_ack_or_stop():
    import threading
    import time

    from services.source.core import Pacer

    p = Pacer(plan=list(range(10)), window=1, stages=["tracker"])
    alive = lambda: {"tracker"}  # noqa: E731
    threading.Timer(0.2, p.ack, args=("tracker", 3)).start()
    t0 = time.monotonic()
    p.wait(4, alive, lambda: False, poll_s=0.05)
    assert 0.15 < time.monotonic() - t0 < 2
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    p.wait(9, alive, stop.is_set, poll_s=0.05)
    assert stop.is_set()


def test_lossless_replay_calls_pace_before_each_frame():
    from services.source.core import replay
    from shared.config.source import SourceConfig

    calls: list[int] = []

    class Reader:
        def __len__(self) -> int:
            return 4

        def frame(self, i: int):
            return i

    sent: list[int] = []
    stats = replay(Reader(), SourceConfig(mode="lossless"), sent.append, pace=calls.append)
    assert calls == [0, 1, 2, 3] and sent == [0, 1, 2, 3] and stats.published == 4


def test_loops_replay_the_plan_with_running_frame_numbers():
    from services.source.core import replay
    from shared.config.source import SourceConfig

    class Reader:
        def __len__(self) -> int:
            return 5

        def frame(self, i: int):
            from types import SimpleNamespace

            f = SimpleNamespace(frame_index=i, time_s=i / 30.0)
            f.model_copy = lambda update: SimpleNamespace(**{**vars(f), **update})
            return f

    sent = []
    stats = replay(Reader(), SourceConfig(mode="lossless", loops=3, stride=2), sent.append)
    assert [f.frame_index for f in sent] == [0, 2, 4, 5, 7, 9, 10, 12, 14]
    assert stats.published == 9 and stats.last_frame_index == 14
    assert sent[3].time_s == 5 / 30.0  # lap 1 starts one sequence length later
