"""StatusBook: counters, rates over a window, latency percentiles, and status.json."""

from __future__ import annotations

import pytest

from shared.messages.status import ServiceStatus
from shared.runtime.status import StatusBook, read_status, status_path, write_status


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_counts_rates_and_latency():
    clock = Clock()
    book = StatusBook("tracker", clock=clock)
    depth = [3]
    book.declare_input("frames", depth=lambda: depth[0])
    for _ in range(10):
        clock.t += 0.1
        book.count("frames", "received")
        book.count("frames", "processed")
        book.work_done(0.010)
    book.work_done(0.110)
    book.count("frames", "dropped", 2)
    book.published("tracks_frame", 10)
    book.figure("keyframes", lambda: {"requested": 2})
    book.progress(done=10, expected=20)
    st = book.report()
    assert isinstance(st, ServiceStatus)
    (inp,) = st.inputs
    assert (inp.name, inp.received, inp.processed, inp.dropped, inp.queue_depth) == ("frames", 10, 10, 2, 3)
    assert inp.rate_hz == pytest.approx(10.0, rel=0.01)  # 10 in the 1 s since start
    assert st.latency_p50_ms == pytest.approx(10.0)
    assert st.latency_p99_ms > 50.0
    assert st.published == {"tracks_frame": 10}
    assert st.figures == {"keyframes": {"requested": 2}}
    assert (st.frames_done, st.frames_expected, st.state) == (10, 20, "starting")
    # old events leave the rate window
    clock.t += 60
    assert book.report().inputs[0].rate_hz == 0.0


def test_unknown_counter_and_bad_figure_are_refused():
    book = StatusBook("fusion")
    with pytest.raises(ValueError, match="unknown counter 'lost'"):
        book.count("tracks_frame", "lost")
    book.figure("bad", object())
    with pytest.raises(TypeError, match="not JSON-compatible"):
        book.report()


def test_status_json_round_trip(tmp_path):
    book = StatusBook("source")
    book.progress(done=3, expected=5)
    path = status_path(tmp_path, "source")
    write_status(path, book.report("stopped"))
    back = read_status(path)
    assert (back.service, back.state, back.frames_done) == ("source", "stopped", 3)
    (tmp_path / "x.status.json").write_text("{}")
    with pytest.raises(ValueError, match="x.status.json: not a ServiceStatus"):
        read_status(tmp_path / "x.status.json")
