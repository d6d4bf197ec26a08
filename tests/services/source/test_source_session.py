"""The source session over the in-process bus with a fake clock: lossless pacing on acks,
live drops, the end of the sequence once, refused frames, figures."""

from __future__ import annotations

from services.source.session import POLL_S, SourceSession
from shared.config import SourceConfig
from shared.datasets.base import DatasetError
from shared.messages.frames import EndOfSequence, Frame, FrameAck
from shared.runtime.bus import InProcessBus
from shared.topics import Topics


class Reader:
    def __init__(self, make_frame, n: int, bad: tuple[int, ...] = ()) -> None:
        self.make_frame, self.n, self.bad = make_frame, n, set(bad)

    def __len__(self) -> int:
        return self.n

    def frame(self, i: int) -> Frame:
        if i in self.bad:
            raise DatasetError(f"frame{i:06d}.jpg: truncated")
        return self.make_frame(i)


def rig(clock, reader, cfg: SourceConfig, alive=set):
    bus = InProcessBus("robot0", clock=clock)
    session = SourceSession(bus, reader, cfg, alive=alive, clock=clock)
    t = Topics("robot0")
    sent: list[int] = []
    ends: list[EndOfSequence] = []
    bus.subscribe(t.frames, Frame, lambda env: sent.append(env.body.frame_index))
    bus.subscribe(t.end_of_sequence, EndOfSequence, lambda env: ends.append(env.body))
    return bus, session, bus.publisher(t.frame_ack, FrameAck), sent, ends


def run(bus, session, clock, steps: int = 100) -> list[float | None]:
    delays = []
    for _ in range(steps):
        d = session.tick(clock())
        bus.drain()
        delays.append(d)
        if d is None or d > 0:
            break
    return delays


def test_lossless_stays_a_window_ahead_of_the_acks(clock, make_frame):
    cfg = SourceConfig(mode="lossless", window_frames=2, ack_from=["tracker"])
    bus, session, acks, sent, ends = rig(clock, Reader(make_frame, 6), cfg, alive=lambda: {"tracker"})
    assert run(bus, session, clock)[-1] == POLL_S
    assert sent == [0, 1]
    acks.put(FrameAck(frame_index=0, service="tracker"))
    bus.drain()
    run(bus, session, clock)
    assert sent == [0, 1, 2]
    for k in range(1, 6):
        acks.put(FrameAck(frame_index=k, service="tracker"))
    bus.drain()
    assert run(bus, session, clock)[-1] is None
    assert sent == list(range(6)) and len(ends) == 1 and ends[0].frames_published == 6 and ends[0].last_frame_index == 5
    assert session.tick(clock()) is None and len(ends) == 1  # the end goes out once
    report = session.book.report()
    assert report.frames_done == report.frames_expected == 6
    assert report.figures["published"] == 6 and report.figures["held_s"] == 0.0
    assert {c.name: c.processed for c in report.inputs}["frame_ack"] == 6


def test_a_vanished_stage_holds_the_source_and_the_time_is_counted(clock, make_frame):
    cfg = SourceConfig(mode="lossless", window_frames=1, ack_from=["tracker"], hold_gone_s=5.0)
    alive = {"tracker"}
    bus, session, acks, sent, _ = rig(clock, Reader(make_frame, 4), cfg, alive=lambda: set(alive))
    run(bus, session, clock)
    assert sent == [0]
    alive.clear()  # the tracker crashed
    for _ in range(3):
        clock.advance(1.0)
        assert run(bus, session, clock)[-1] == POLL_S
    assert session.pacer.held_s == 2.0  # counted from the first tick that found it gone
    clock.advance(5.0)
    run(bus, session, clock)
    assert sent == [0, 1, 2, 3]  # gone for longer than hold_gone_s: the source goes on


def test_live_drops_the_frames_whose_slot_passed(clock, make_frame):
    cfg = SourceConfig(mode="live", rate_hz=10.0)
    bus, session, _, sent, ends = rig(clock, Reader(make_frame, 10), cfg)
    assert session.tick(clock()) == 0.0  # frame 0 at once
    d = session.tick(clock())
    assert abs(d - 0.1) < 1e-9  # frame 1 is due in 0.1 s
    clock.advance(0.35)  # a blocked publish: frames 1 and 2 missed their slots
    session.tick(clock())
    bus.drain()
    assert sent == [0, 3] and session.stats.dropped_indices == [1, 2]
    clock.advance(10.0)
    while session.tick(clock()) is not None:
        pass
    bus.drain()
    report = session.book.report()
    assert report.frames_done == report.figures["published"] + report.figures["dropped"] == 10
    assert ends[0].frames_dropped == report.figures["dropped"]


def test_refused_frames_are_counted_and_kept_for_the_report(clock, make_frame):
    bus, session, _, sent, ends = rig(clock, Reader(make_frame, 4, bad=(1, 2)), SourceConfig(mode="lossless", ack_from=[]))
    run(bus, session, clock)
    assert sent == [0, 3] and ends[0].frames_published == 2
    assert session.stats.rejected == 2 and session.stats.rejected_errors == ["frame000001.jpg: truncated", "frame000002.jpg: truncated"]
    assert session.book.report().figures["rejected"] == 2


def test_finish_early_sends_the_end_with_what_went_out(clock, make_frame):
    bus, session, _, sent, ends = rig(clock, Reader(make_frame, 10), SourceConfig(mode="lossless", ack_from=[]))
    session.tick(clock())
    session.tick(clock())
    stats = session.finish(clock())
    bus.drain()
    assert stats.published == 2 and ends[0].last_frame_index == 1 and session.tick(clock()) is None
