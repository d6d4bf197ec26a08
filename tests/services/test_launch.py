"""``trackgraph launch``: launch files, the restart policy, and the whole system as separate OS
processes on the ``small`` preset over loopback Zenoh: the saved graph equals the in-process
map, the live query service answers like an offline query on that map, and a query service
killed with SIGKILL is restarted, resynchronises and answers the same."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from services.launch import LaunchError, Supervisor, plan_launch
from shared.config.base import ConfigError

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
        "overrides": {"tracker": {"wait_for_masks": True, "device": "cpu"}, "transport": {"shared_memory": False}},
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
        for cmd in plan.commands.values():
            assert cmd[:3] == [sys.executable, "-m", "services.cli"]


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
        assert len(got.segments) == len(want.segments) > 10
        assert [(s.id, s.tracks) for s in got.segments] == [(s.id, s.tracks) for s in want.segments]
        # CLIP features come back asynchronously; still every gallery holds the same tracks'
        # features (the last keyframes' included) as in-process.
        assert [s.gallery_tracks for s in got.segments] == [s.gallery_tracks for s in want.segments]
        for a, b in zip(got.segments, want.segments, strict=True):
            np.testing.assert_allclose(a.gallery, b.gallery, atol=1e-5, err_msg=f"segment {a.id}")

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
