"""``trackgraph launch``: launch files, the restart policy, and the whole system as separate OS
processes on the ``small`` preset over loopback Zenoh: the saved graph equals the in-process
map, the live query service answers like an offline query on that map, and a query service
killed with SIGKILL is restarted, resynchronises and answers the same."""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from services.launch import LaunchError, Supervisor, plan_launch
from shared.config.base import ConfigError
from shared.messages.status import InputCounters, ServiceStatus
from shared.runtime.status import read_status, status_path, write_status
from tests.same_map import assert_same_map

ROOT = Path(__file__).resolve().parents[2]
SYNTHETIC = ROOT / "deploy" / "configs" / "synthetic.yaml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_launch(tmp: Path, services: list[dict], **extra) -> Path:
    port = _free_port()
    doc = {
        "config": str(SYNTHETIC),
        "set": ["tracker.wait_for_masks=true", "tracker.device=cpu", "transport.shared_memory=false"],
        "connect": [f"tcp/127.0.0.1:{port}"],
        "listen": [f"tcp/127.0.0.1:{port}"],
        "services": services,
        **extra,
    }
    path = tmp / "launch.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_launch_file_errors_name_the_problem(tmp_path):
    bad = write_launch(tmp_path, [{"name": "router"}, {"name": "tracker", "after": ["keyframe_vl"]}])
    with pytest.raises(ConfigError, match="keyframe_vl"):
        plan_launch(bad)
    dup = write_launch(tmp_path, [{"name": "query"}, {"name": "query"}])
    with pytest.raises(ConfigError, match="twice"):
        plan_launch(dup)
    typo = write_launch(tmp_path, [{"name": "query", "restart": {"max_restart": 2}}])
    with pytest.raises(ConfigError, match="max_restart"):
        plan_launch(typo)
    nosrc = write_launch(tmp_path, [{"name": "router"}, {"name": "source"}])
    with pytest.raises(ConfigError, match="sequence"):
        plan_launch(nosrc)
    nofusion = write_launch(tmp_path, [{"name": "fusion"}])
    with pytest.raises(ConfigError, match="--out"):
        plan_launch(nofusion)


def test_the_shipped_launch_files_are_valid(tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    for name in ("local.yaml", "robot.yaml", "gpu-server.yaml", "base-station.yaml"):
        path = ROOT / "deploy" / name
        plan = plan_launch(path, sequence=seq, out=tmp_path / "map", log_dir=tmp_path / name)
        assert plan.commands, name
        for service, cmd in plan.commands.items():
            assert cmd[:3] == [sys.executable, "-m", "services.cli"]
            # Every service but the router writes its last status report beside its log.
            if service == "router":
                assert "--status-file" not in cmd
            else:
                assert cmd[cmd.index("--status-file") + 1] == str(status_path(tmp_path / name, service)), (name, service)


def test_an_earlier_launch_status_file_is_removed_at_plan_time(tmp_path):
    path = write_launch(tmp_path, [{"name": "router"}, {"name": "query"}])
    old = status_path(tmp_path / "logs", "query")
    old.parent.mkdir()
    write_status(old, ServiceStatus(service="query", pid=1, state="stopped", uptime_s=1.0))
    plan_launch(path, log_dir=tmp_path / "logs")
    assert not old.exists()


def _report(service: str, **kw) -> ServiceStatus:
    return ServiceStatus(**{"service": service, "pid": 7, "state": "running", "uptime_s": 12.0, **kw})


def test_the_status_table_shows_rate_drops_queue_and_progress(tmp_path):
    from rich.console import Console

    from services.launch import LAUNCH_COLUMNS, launch_table

    seq = tmp_path / "seq"
    seq.mkdir()
    services = [{"name": "router"}, {"name": "source"}, {"name": "tracker"}, {"name": "fusion", "args": ["--exit-at-end"]}, {"name": "query"}]
    plan = plan_launch(write_launch(tmp_path, services), sequence=seq, out=tmp_path / "map", log_dir=tmp_path / "logs")
    sup = Supervisor(plan, status=False)
    reports = {
        "source": (_report("source", frames_done=150, frames_expected=300, rate_hz=10.0, figures={"dropped": 2}), 0.3),
        "tracker": (_report("tracker", frames_done=140, frames_expected=300, rate_hz=8.0,
                            inputs=[InputCounters(name="frames", received=145, dropped=5, queue_depth=1)]), 0.5),  # fmt: skip
        "fusion": (_report("fusion", frames_done=100, frames_expected=300, rate_hz=4.0, inputs=[InputCounters(name="tracks_frame", queue_depth=30)]), 9.0),
    }
    sup.report = lambda name: reports.get(name)
    # The fusion process has exited: its status.json (written at stop) is what the table shows.
    write_status(status_path(plan.log_dir, "fusion"), _report("fusion", state="stopped", frames_done=300, frames_expected=300))

    class Running:
        pid = 4242

        def poll(self):
            return None

    for name in ("source", "tracker"):
        sup.procs[name].popen, sup.procs[name].state = Running(), "alive"
    console = Console(width=300, record=True, file=__import__("io").StringIO())
    console.print(launch_table(sup, now=sup.procs["source"].started_at + 30))
    text = console.export_text()
    header = next(ln for ln in text.splitlines() if "service" in ln)
    assert [c.strip() for c in header.strip("┃ ").split("┃")] == list(LAUNCH_COLUMNS)
    row = {ln.split()[1]: ln for ln in text.splitlines() if ln.startswith("│")}
    assert "150/300 (50%), ETA 15 s" in row["source"] and " 10 " in row["source"] and " 2 " in row["source"]
    assert "140/300 (47%), ETA 20 s" in row["tracker"] and " 5 " in row["tracker"] and " 1 " in row["tracker"]
    assert "300/300 (100%) done" in row["fusion"]
    assert row["query"].count(" - ") >= 4  # no report yet
    summary = sup.summary()["services"]
    assert summary["source"]["status"]["frames_done"] == 150 and summary["source"]["status"]["dropped"] == 2
    assert summary["fusion"]["status"]["state"] == "stopped" and summary["router"]["status"] is None
    assert summary["tracker"]["status_file"] == str(status_path(plan.log_dir, "tracker"))


def test_a_service_reporting_starting_is_not_timed_out_until_it_stops_saying_so(tmp_path):
    # The query service waits for a vl/embed that may be on a machine started later: while its
    # own reports say "starting", the launcher's alive time-out does not run.
    plan = plan_launch(write_launch(tmp_path, [{"name": "query"}], alive_timeout_s=5.0), log_dir=tmp_path / "logs")
    sup = Supervisor(plan, status=False)
    sup._connecting = threading.Thread()  # never connects: liveliness and reports are faked below

    class Running:
        pid = 4242

        def poll(self):
            return None

    class NoTokens:
        def alive(self):
            return set()

    now = time.monotonic()
    q = sup.procs["query"]
    q.popen, q.state, q.started_at = Running(), "starting", now - 600
    sup.watcher, sup._watching_since = NoTokens(), now - 600
    latest = {"query": (_report("query", state="starting", pid=4242), 0.5)}

    class Reports:
        def get(self, name):
            return latest.get(name)

        def close(self):
            pass

    sup.reports = Reports()
    sup.step()
    assert q.state == "starting" and q.starting_seen >= now  # 600 s without a token, but it says why
    latest["query"] = (_report("query", state="starting", pid=999), 0.5)  # an earlier run's report
    sup.step()
    assert q.state == "starting"  # it said so a moment ago: the time-out counts from then
    q.starting_seen = now - 10
    sup.step()
    assert q.state == "backoff" and "not alive 5 s after start" in q.reason


@pytest.mark.zenoh
def test_a_crashing_service_is_restarted_then_given_up(tmp_path):
    path = write_launch(
        tmp_path, [{"name": "router"}, {"name": "query"}],
        restart={"max_restarts": 2, "window_s": 60, "backoff_s": 0.1},
    )  # fmt: skip
    plan = plan_launch(path, log_dir=tmp_path / "logs")
    plan.commands["query"] = [sys.executable, "-c", "import sys, time; time.sleep(0.3); sys.exit(3)"]
    sup = Supervisor(plan, status=False)
    t0 = time.monotonic()
    with pytest.raises(LaunchError, match="query failed: exited with status 3"):
        sup.run()
    q = sup.procs["query"]
    assert q.state == "failed" and q.exit_codes == [3, 3, 3] and len(q.restarts) == 2
    assert sup.procs["router"].state == "stopped" and sup.procs["router"].pid is None
    assert time.monotonic() - t0 < 30
    assert "restarting in" in (tmp_path / "logs" / "query.log").read_text() or q.log_path.exists()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out)
    return out


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_whole_system_as_processes_equals_in_process_and_survives_a_killed_query_service(small, tmp_path):
    from services.mapping import run_map
    from services.query.client import QueryClient
    from services.query.offline import OfflineQueries
    from shared.graph.store import MapStore
    from shared.messages.rpc import QueryRequest

    services = [
        {"name": "router"},
        {"name": "keyframe_vl"},
        {"name": "fusion"},  # stays up after the sequence: the restarted query service needs it
        {"name": "query"},
        {"name": "tracker", "after": ["keyframe_vl"]},
        {"name": "source", "after": ["tracker", "fusion"]},
    ]
    out = tmp_path / "distributed"
    path = write_launch(tmp_path, services, exit_when_finished=False, restart={"backoff_s": 0.2})
    plan = plan_launch(path, sequence=small, out=out)
    sup = Supervisor(plan, status=False)
    runner = threading.Thread(target=sup.run, daemon=True)
    runner.start()

    def wait(cond, what: str, timeout: float = 600) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert sup.error is None, sup.error
            assert time.monotonic() < deadline, f"{what}: {sup.summary()}"
            time.sleep(0.2)

    try:
        # Mid-run, once fusion has published a few graph versions, SIGKILL the query service.
        query = sup.procs["query"]
        wait(lambda: sup.procs["source"].state == "alive" and query.state == "alive", "source and query up")
        with QueryClient(plan.system.transport, robot_id=plan.system.robot_id, timeout_s=10) as client:
            wait(lambda: client.ask(QueryRequest(text="chair")).graph_seq >= 3, "three graph versions")
        old_pid = query.pid
        os.kill(old_pid, signal.SIGKILL)
        wait(lambda: query.state == "alive" and query.pid not in (None, old_pid), "query restarted", 120)
        assert len(query.restarts) == 1
        wait(lambda: (out / "run.json").exists(), "the map finished")
        assert sup.procs["source"].state == "finished"

        # The in-process pipeline on the same input and the same resolved config.
        run_map(small, plan.system, tmp_path / "in_process", progress=False)
        got = MapStore(out / "graph").load().snapshot
        want = MapStore(tmp_path / "in_process" / "graph").load().snapshot
        assert_same_map(got, want)

        # The restarted query service resynchronised: it answers as an offline query on the map.
        offline = OfflineQueries(out)
        texts = ["chair", "bookshelf", "rug", "potted plant"]
        expected = {t: [(h.segment, round(h.score, 4)) for h in offline.ask(QueryRequest(text=t, top_k=3)).hits] for t in texts}
        with QueryClient(plan.system.transport, robot_id=plan.system.robot_id, timeout_s=10) as client:
            wait(lambda: client.ask(QueryRequest(text="chair")).graph_seq == got.graph_seq, "query at the final version", 60)
            assert {t: [(h.segment, round(h.score, 4)) for h in client.query(t, top_k=3)] for t in texts} == expected

            # A client killed while its query is in flight harms nobody.
            victim = subprocess.Popen(
                [sys.executable, "-m", "services.cli", "query", "--live", "chair", "--config", str(plan.config_path)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            time.sleep(1.5)
            victim.kill()
            victim.wait()
            assert [(h.segment, round(h.score, 4)) for h in client.query("chair", top_k=3)] == expected["chair"]
    finally:
        sup.stop_event.set()
        runner.join(timeout=120)
    assert not runner.is_alive()
    assert all(p.pid is None for p in sup.procs.values())
    assert sup.procs["fusion"].state == "stopped" and (out / "graph").is_dir()


class ReportLog:
    """Every ServiceStatus on ``trackgraph/<robot>/status/**``, with when it came."""

    def __init__(self, endpoint: str, robot: str = "robot0") -> None:
        from shared.config import TransportConfig
        from shared.transport import ZenohBus

        transport = TransportConfig(mode="client", connect=[endpoint], shared_memory=False, connect_timeout_s=120.0)
        self.bus = ZenohBus.open(transport, robot)
        self.got: dict[str, list[tuple[float, str]]] = {}
        self._lock = threading.Lock()
        self.bus.subscribe(f"trackgraph/{robot}/status/**", ServiceStatus, self._on, capacity=1024)

    def _on(self, env) -> None:
        with self._lock:
            self.got.setdefault(env.body.service, []).append((time.monotonic(), env.body.state))

    def gaps(self) -> dict[str, float]:
        """Per service, the longest wait between two consecutive reports."""
        with self._lock:
            return {name: max((b[0] - a[0] for a, b in itertools.pairwise(ts)), default=float("inf")) for name, ts in self.got.items()}

    def close(self) -> None:
        self.bus.close()


MAX_REPORT_GAP_S = 1.0
"""Consumers are promised a report at least once a second (reports go out every 0.5 s, and
fusion's through its heartbeat process while Open3D holds its interpreter)."""


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_query_and_viewer_report_their_status_every_second_and_at_stop(tmp_path):
    from rich.console import Console

    from services.launch import launch_table

    services = [{"name": "router"}, {"name": "query"}, {"name": "viewer"}]
    path = write_launch(tmp_path, services, exit_when_finished=False)
    plan = plan_launch(path, out=None, log_dir=tmp_path / "logs")
    sup = Supervisor(plan, status=False)
    runner = threading.Thread(target=sup.run, daemon=True)
    runner.start()
    reports = None
    try:
        reports = ReportLog(plan.system.transport.connect[0])
        deadline = time.monotonic() + 120
        # No keyframe_vl in this launch: the query service reports "starting" (no vl/embed to
        # warm up with) and never declares itself alive, the viewer does.
        while not (sup.procs["viewer"].state == "alive" and sup.report("query") is not None):
            assert sup.error is None and time.monotonic() < deadline, sup.summary()
            time.sleep(0.2)
        time.sleep(4.5)
        counts = {name: len(ts) for name, ts in reports.got.items()}
        assert counts.get("query", 0) >= 3 and counts.get("viewer", 0) >= 3, counts
        gaps = reports.gaps()
        assert gaps["query"] <= MAX_REPORT_GAP_S and gaps["viewer"] <= MAX_REPORT_GAP_S, gaps
        # The launcher hears them too: its table has their figures, not dashes.
        assert sup.report("query") is not None and sup.report("query")[0].figures["synced"] is False
        assert sup.report("query")[0].state == "starting" and sup.procs["query"].state == "starting"
        console = Console(width=300, record=True, file=__import__("io").StringIO())
        console.print(launch_table(sup))
        row = next(ln for ln in console.export_text().splitlines() if ln.startswith("│ query"))
        assert row.split("│")[6].strip() != "-"  # Hz
    finally:
        sup.stop_event.set()
        runner.join(timeout=120)
        if reports is not None:
            reports.close()
    for name in ("query", "viewer"):
        final = read_status(status_path(plan.log_dir, name))
        assert final.state == "stopped" and final.service == name
        assert {i.name for i in final.inputs} >= {"graph_delta", "graph_snapshot"}
        assert sup.summary()["services"][name]["status"]["state"] == "stopped"
    assert read_status(status_path(plan.log_dir, "query")).figures["snapshot_failures"] >= 1  # no fusion in this launch


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_every_service_of_the_local_launch_reports_every_second(small, tmp_path):
    """``trackgraph launch deploy/local.yaml`` on the small preset (on a free port): every
    service's ServiceStatus arrives at least once a second, and at the end the source, the
    tracker and fusion report every frame done."""
    doc = yaml.safe_load((ROOT / "deploy" / "local.yaml").read_text())
    port = _free_port()
    doc.update(config=str(ROOT / "deploy" / doc["config"]), connect=[f"tcp/127.0.0.1:{port}"], listen=[f"tcp/127.0.0.1:{port}"])
    launch_file = tmp_path / "local.yaml"
    launch_file.write_text(yaml.safe_dump(doc))
    out = tmp_path / "map"
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "launch", str(launch_file), "--sequence", str(small), "--out", str(out), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    reports = None
    try:
        reports = ReportLog(f"tcp/127.0.0.1:{port}")
        stdout, _ = proc.communicate(timeout=800)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(60)
        if reports is not None:
            reports.close()
    assert proc.returncode == 0, stdout
    summary = json.loads(stdout.strip().splitlines()[-1])
    names = [s["name"] for s in doc["services"] if s["name"] != "router"]
    assert sorted(reports.got) == sorted(names), sorted(reports.got)
    gaps = reports.gaps()
    assert all(gaps[n] <= MAX_REPORT_GAP_S for n in names), gaps
    frames = summary["services"]["source"]["status"]["frames_expected"]
    assert frames and frames > 10
    for name in ("source", "tracker", "fusion"):
        st = summary["services"][name]["status"]
        assert (st["frames_done"], st["frames_expected"]) == (frames, frames), (name, st)
