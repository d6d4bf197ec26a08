"""Reading ServiceStatus reports: the table's cells (rate, drops, queue, progress with ETA),
the watch over a bus, and ``trackgraph status`` against a live loopback publisher."""

from __future__ import annotations

import io
import json
import socket
import threading

import pytest
from rich.console import Console

from services.monitor import (
    StatusWatch,
    drops,
    eta_s,
    progress_text,
    report_cells,
    report_summary,
    status_json,
    status_table,
    with_source_total,
)
from shared.messages.status import InputCounters, ServiceStatus
from shared.runtime.bus import InProcessBus
from shared.topics import Topics


def status(service: str = "tracker", **kw) -> ServiceStatus:
    base = {"service": service, "pid": 42, "state": "running", "uptime_s": 30.0}
    return ServiceStatus(**{**base, **kw})


def render(table) -> str:
    console = Console(file=io.StringIO(), width=250, record=True)
    console.print(table)
    return console.export_text()


def test_progress_with_eta_done_and_unknown_total():
    st = status(frames_done=120, frames_expected=300, rate_hz=4.0)
    assert eta_s(st) == pytest.approx(45.0)
    assert progress_text(st) == "120/300 (40%), ETA 45 s"
    assert progress_text(status(frames_done=30, frames_expected=2000, rate_hz=2.0)) == "30/2000 (2%), ETA 16 min 25 s"
    assert progress_text(status(frames_done=300, frames_expected=300)) == "300/300 (100%) done"
    assert progress_text(status(frames_done=120)) == "120 frames"
    assert progress_text(status()) == "-"
    # No recent rate (a pause): the average since the start gives the ETA.
    assert eta_s(status(frames_done=60, frames_expected=120, rate_hz=0.0, uptime_s=30.0)) == pytest.approx(30.0)
    assert eta_s(status(frames_done=0, frames_expected=120, rate_hz=0.0)) is None
    assert progress_text(status(frames_done=0, frames_expected=120)) == "0/120 (0%)"


def test_drops_add_every_input_and_the_source_own_count():
    tracker = status(inputs=[InputCounters(name="frames", received=90, dropped=3, queue_depth=2),
                             InputCounters(name="keyframe_masks", received=4, dropped=1, queue_depth=1)])  # fmt: skip
    assert drops(tracker) == 4
    assert report_cells(tracker) == {"Hz": "0", "drops": "4", "queue": "3", "progress": "-"}
    source = status("source", rate_hz=29.97, figures={"published": 100, "dropped": 5, "hz": 29.9},
                    inputs=[InputCounters(name="frame_ack", received=200)])  # fmt: skip
    assert drops(source) == 5 and report_cells(source)["Hz"] == "30"
    assert drops(status("fusion", figures={"dropped": True})) == 0  # only a count is a count
    assert report_cells(None) == {"Hz": "-", "drops": "-", "queue": "-", "progress": "-"}
    assert report_summary(status(frames_done=10, frames_expected=20, rate_hz=1.0))["eta_s"] == 10.0


def test_status_table_and_json_from_reports():
    latest = {
        "fusion": (status("fusion", frames_done=40, frames_expected=100, rate_hz=2.0, latency_p50_ms=12.5, latency_p99_ms=80.0,
                          inputs=[InputCounters(name="tracks_frame", received=41, dropped=1, queue_depth=1)]), 0.4),  # fmt: skip
        "source": (status("source", frames_done=50, frames_expected=100, rate_hz=2.5, figures={"dropped": 0}), 0.2),
        "query": (status("query", state="stopped"), 9.0),
        "tracker": (status("tracker", frames_done=45, stale_s=1.24), 0.1),
    }
    text = render(status_table(latest))
    lines = [ln for ln in text.splitlines() if ln.strip().startswith(("│ source", "│ tracker", "│ fusion", "│ query", "┃ service"))]
    assert [ln.split()[1] for ln in lines] == ["service", "source", "tracker", "fusion", "query"]  # pipeline order
    assert "50/100 (50%), ETA 20 s" in text and "40/100 (40%), ETA 30 s" in text and "12.5" in text and "9.0 s ago" in text
    out = status_json(latest, "robot0")
    assert "0.1 s ago, busy 1.2 s" in text  # a heartbeat's resent report says how old it is
    assert list(out["services"]) == ["source", "tracker", "fusion", "query"] and out["robot"] == "robot0"
    assert out["services"]["tracker"]["summary"]["stale_s"] == 1.24 and out["services"]["fusion"]["summary"]["stale_s"] == 0
    assert out["services"]["fusion"]["summary"]["dropped"] == 1 and out["services"]["fusion"]["inputs"][0]["name"] == "tracks_frame"
    assert out["services"]["query"]["age_s"] == 9.0
    json.dumps(out)


def test_watch_keeps_the_newest_report_of_each_service():
    t = [100.0]
    bus = InProcessBus("robot0")
    watch = StatusWatch(bus, "robot0", clock=lambda: t[0])
    topics = Topics("robot0")
    # The in-process bus matches keys exactly: publish on the watch's key as Zenoh would deliver it.
    pub = bus.publisher(topics.status_all, ServiceStatus)
    pub.put(status("tracker", frames_done=1))
    pub.put(status("fusion"))
    pub.put(status("tracker", frames_done=2))
    bus.drain()
    t[0] = 101.5
    latest = watch.latest()
    assert sorted(latest) == ["fusion", "tracker"] and latest["tracker"][0].frames_done == 2 and latest["tracker"][1] == 1.5
    assert watch.received == 3 and watch.wait(3, timeout=0.01) and not watch.wait(4, timeout=0.01)
    watch.close()


# ---------------------------------------------------------------------- over Zenoh


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def publisher():
    """A peer session on loopback publishing a tracker's and a fusion's reports 5 times a second."""
    from shared.config import TransportConfig
    from shared.transport import TypedPublisher, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(TransportConfig(mode="peer", connect=[], listen=[endpoint], shared_memory=False))
    topics = Topics("robot0")
    pubs = {name: TypedPublisher(session, topics.status(name), ServiceStatus, robot_id="robot0") for name in ("tracker", "fusion")}
    stop = threading.Event()

    def run() -> None:
        k = 0
        while not stop.wait(0.2):
            k += 1
            pubs["tracker"].put(status("tracker", frames_done=12, frames_expected=40, rate_hz=2.0,
                                       inputs=[InputCounters(name="frames", received=14, dropped=2)]))  # fmt: skip
            pubs["fusion"].put(status("fusion", frames_done=10, frames_expected=40, rate_hz=2.0, uptime_s=float(k)))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield endpoint
    finally:
        stop.set()
        thread.join()
        for p in pubs.values():
            p.close()
        session.close()


@pytest.mark.zenoh
def test_trackgraph_status_reads_a_live_publisher(publisher, capsys):
    from services.cli import main

    assert main(["status", "--connect", publisher, "--once", "--json", "--timeout", "10"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(out["services"]) == {"tracker", "fusion"}
    tracker = out["services"]["tracker"]
    assert tracker["frames_done"] == 12 and tracker["summary"]["dropped"] == 2 and tracker["summary"]["eta_s"] == 14.0
    assert tracker["age_s"] < 1.0

    assert main(["status", "--connect", publisher, "--once", "--timeout", "10"]) == 0
    text = capsys.readouterr().out
    assert "12/40 (30%), ETA 14 s" in text and "10/40 (25%), ETA 15 s" in text


@pytest.mark.zenoh
def test_trackgraph_status_fails_with_one_line_when_nothing_answers(capsys):
    from services.cli import main
    from shared.config import TransportConfig
    from shared.transport import open_session

    # Nobody at the endpoint at all.
    assert main(["status", "--connect", f"tcp/127.0.0.1:{free_port()}", "--once", "--timeout", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("trackgraph: error:") and len(err.splitlines()) == 1
    # Someone there, but no service reports.
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(TransportConfig(mode="peer", connect=[], listen=[endpoint], shared_memory=False))
    try:
        assert main(["status", "--connect", endpoint, "--robot", "robot7", "--timeout", "1"]) == 2
    finally:
        session.close()
    err = capsys.readouterr().err.strip()
    assert "no service of robot 'robot7' reported on trackgraph/robot7/status/* within 1 s" in err and len(err.splitlines()) == 1


def test_a_downstream_stage_shows_its_progress_against_the_frames_the_source_sends():
    source = status("source", frames_done=80, frames_expected=120, figures={"dropped": 20})
    tracker = status("tracker", frames_done=50, uptime_s=10.0)
    assert report_cells(tracker)["progress"] == "50 frames"
    shown = with_source_total(tracker, source)
    assert shown.frames_expected == 100 and report_cells(shown)["progress"] == "50/100 (50%), ETA 10 s"
    own = status("fusion", frames_done=50, frames_expected=60)
    assert with_source_total(own, source) is own  # its own total, once it knows it, wins
    assert with_source_total(tracker, None) is tracker and with_source_total(source, source) is source
    assert with_source_total(status("query"), source).frames_expected is None  # handles no frames
