"""Faults injected into the whole system running as OS processes (``trackgraph launch``'s
Supervisor) on the ``small`` preset over loopback Zenoh: kill -9 keyframe_vl and bring it back
50 frames later; kill -9 fusion mid-run and mid-snapshot and let it resume from its journal with
nothing lost; restart the router; SIGSTOP a service past
the liveliness lease. (A SIGKILLed query service and a client killed mid-query are in
tests/services/test_launch.py.)"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from services.launch import Supervisor, plan_launch
from shared.config.overrides import as_sets
from shared.messages.frames import FrameAck
from shared.messages.keyframes import KeyframeMasks
from shared.topics import Topics
from shared.transport import TypedSubscriber, open_session

pytestmark = [pytest.mark.faults, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(900)]

ROOT = Path(__file__).resolve().parents[2]
SYNTHETIC = ROOT / "deploy" / "configs" / "synthetic.yaml"
FRAMES = 120


def write_launch(tmp: Path, port: int, services: list[dict], overrides: dict | None = None, **extra) -> Path:
    base = {
        "tracker": {"wait_for_masks": True, "device": "cpu", "keyframe_timeout_s": 2.0},
        "transport": {"shared_memory": False},
        "source": {"max_frames": FRAMES},
    }
    for k, v in (overrides or {}).items():
        base[k] = {**base.get(k, {}), **v}
    doc = {
        "config": str(SYNTHETIC),
        "set": as_sets(base),
        "connect": [f"tcp/127.0.0.1:{port}"],
        "listen": [f"tcp/127.0.0.1:{port}"],
        "services": services,
        "restart": {"backoff_s": 0.2},
        **extra,
    }
    path = tmp / "launch.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


class Run:
    """A Supervisor on its own thread, and a session that watches acknowledgements."""

    def __init__(self, path: Path, sequence: Path | None, out: Path | None) -> None:
        # logs beside the launch file: without a map folder they would go to ./trackgraph-logs
        self.plan = plan_launch(path, sequence=sequence, out=out, log_dir=path.parent / "logs")
        self.sup = Supervisor(self.plan, status=False)
        self.thread = threading.Thread(target=self.sup.run, daemon=True)
        self.acked: dict[str, int] = {}
        self.masks: list[tuple[float, int]] = []
        self.session = None
        self.subs: list = []

    def start(self, watch: bool = True) -> Run:
        self.thread.start()
        if watch:
            self.wait(lambda: self.sup.procs["router"].state == "alive", "router up", 60)
            t = self.plan.system.transport.model_copy(update={"connect_timeout_s": -1.0})
            self.session = open_session(t)
            topics = Topics(self.plan.system.robot_id)
            self.subs = [
                TypedSubscriber(self.session, topics.frame_ack, FrameAck, capacity=1024, callback=self._on_ack),
                TypedSubscriber(self.session, topics.keyframe_masks, KeyframeMasks, capacity=64,
                                callback=lambda env: self.masks.append((time.monotonic(), env.body.frame_index))),
            ]  # fmt: skip
        return self

    def _on_ack(self, env) -> None:
        s, k = env.body.service, env.body.frame_index
        self.acked[s] = max(self.acked.get(s, -1), k)

    def wait(self, cond, what: str, timeout: float = 600) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert self.sup.error is None, self.sup.error
            assert self.thread.is_alive() or cond(), f"{what}: the launch ended: {self.sup.summary()}"
            assert time.monotonic() < deadline, f"{what}: {self.sup.summary()}"
            time.sleep(0.1)

    def close(self) -> None:
        for s in self.subs:
            s.close()
        if self.session is not None:
            self.session.close()
        self.sup.stop_event.set()
        self.thread.join(timeout=120)
        assert not self.thread.is_alive()
        assert all(p.pid is None for p in self.sup.procs.values())


def pipeline(*, keyframe_vl: bool = True) -> list[dict]:
    services = [{"name": "router"}, {"name": "fusion", "args": ["--exit-at-end"]}, {"name": "tracker"}]
    if keyframe_vl:
        services.insert(1, {"name": "keyframe_vl"})
        services[-1]["after"] = ["keyframe_vl"]
    return services + [{"name": "source", "after": ["tracker", "fusion"]}]


def test_keyframe_vl_killed_and_back_50_frames_later(small, tmp_path, free_port):
    """The tracker loses no frame while keyframe_vl is gone, and takes masks again after."""
    out = tmp_path / "map"
    path = write_launch(tmp_path, free_port, pipeline(keyframe_vl=False))
    run = Run(path, small, out)
    cmd = [sys.executable, "-m", "services.cli", "serve", "keyframe_vl", "--config", str(run.plan.config_path)]
    logf = open(tmp_path / "keyframe_vl.log", "ab")  # noqa: SIM115
    vl = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        run.start()
        run.wait(lambda: run.acked.get("tracker", -1) >= 20 and run.masks, "20 frames tracked with masks", 300)
        vl.send_signal(signal.SIGKILL)
        vl.wait()
        killed_at = run.acked["tracker"]
        run.wait(lambda: run.acked.get("tracker", -1) >= killed_at + 50, "50 frames without keyframe_vl", 300)
        back_at, t_back = run.acked["tracker"], time.monotonic()
        vl = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True)
        run.wait(lambda: (out / "run.json").exists(), "the map finished", 600)
        summary = json.loads((out / "run.json").read_text())
    finally:
        vl.kill()
        vl.wait()
        logf.close()
        run.close()
    assert back_at + 10 < FRAMES - 1, "the outage must end before the sequence does"
    assert summary["frames_in_map"] == summary["frames_announced"] == FRAMES and summary["frames_lost"] == 0
    tracker_log = (run.plan.log_dir / "tracker.log").read_text()
    assert "no masks after" in tracker_log  # the outage was noticed and propagated through
    after = [k for t, k in run.masks if t > t_back]
    assert after, "no keyframe masks after keyframe_vl came back"
    assert summary["segments"] > 10


def test_fusion_killed_mid_run_and_during_a_snapshot_write_loses_nothing(small, tmp_path, free_port):
    """kill -9 fusion mid-run, and again while it writes a snapshot: each time the Supervisor
    restarts it with --resume, it replays its journal after the newest good snapshot, the
    tracker sends again what it had not acknowledged, and the map is the uninterrupted one."""
    from services.mapping import run_map
    from shared.graph.store import MapStore
    from tests.same_map import assert_same_map

    out = tmp_path / "map"
    # The tracker waits for every keyframe's masks however long a restart's load delays them:
    # the comparison is of fusion's map, not of the tracker under load.
    overrides = {"fusion": {"snapshot_interval_s": 1.0}, "tracker": {"keyframe_timeout_s": 60.0}}
    path = write_launch(tmp_path, free_port, pipeline(), overrides=overrides)
    run = Run(path, small, out).start()
    snapshots = out / "graph" / "snapshots"
    try:
        fusion = run.sup.procs["fusion"]
        run.wait(lambda: MapStore(out / "graph").latest_name() is not None and run.acked.get("fusion", -1) >= 40, "a snapshot and 40 frames", 300)
        first = fusion.pid
        os.kill(first, signal.SIGKILL)  # mid-run: frames in its journal, more in flight
        run.wait(lambda: fusion.state == "alive" and fusion.pid not in (None, first), "fusion restarted", 120)
        run.wait(lambda: run.acked.get("fusion", -1) >= 60, "60 frames", 300)
        second = fusion.pid
        deadline = time.monotonic() + 120
        while not any(p.name.endswith(".partial") for p in snapshots.iterdir()):
            assert time.monotonic() < deadline, "no snapshot write seen"
            time.sleep(0.001)
        os.kill(second, signal.SIGKILL)  # mid-write: the partial snapshot folder is there
        run.wait(lambda: fusion.state == "alive" and fusion.pid not in (None, first, second), "fusion restarted again", 120)
        run.wait(lambda: (out / "run.json").exists(), "the map finished", 600)
        summary = json.loads((out / "run.json").read_text())
    finally:
        run.close()
    assert len(fusion.restarts) == 2 and summary["resumed_from"]
    assert summary["frames_announced"] == summary["frames_in_map"] == FRAMES and summary["frames_lost"] == 0, summary
    assert summary["journal_replayed"].get("frame", 0) > 0 and summary["journal_torn"] == 0, summary
    assert summary["reorder"]["skipped"] == 0, summary  # what overtook the resend waited for it
    fusion_log = (run.plan.log_dir / "fusion.log").read_text()
    assert fusion_log.count("journal: replayed") == 2
    assert "sending again" in (run.plan.log_dir / "tracker.log").read_text()

    # the uninterrupted map: the in-process pipeline on the same input and resolved config
    run_map(small, run.plan.system, tmp_path / "in_process", progress=False)
    got = MapStore(out / "graph").load().snapshot
    want = MapStore(tmp_path / "in_process" / "graph").load().snapshot
    assert_same_map(got, want)


def test_router_restart_every_service_reconnects(small, tmp_path, free_port):
    """kill -9 the router mid-run: the Supervisor restarts it, every service reconnects by
    itself, and the run completes; frames lost in flight are counted."""
    out = tmp_path / "map"
    path = write_launch(tmp_path, free_port, pipeline())
    run = Run(path, small, out).start()
    try:
        router = run.sup.procs["router"]
        run.wait(lambda: run.acked.get("fusion", -1) >= 30, "30 frames fused", 300)
        old = router.pid
        os.kill(old, signal.SIGKILL)
        run.wait(lambda: router.state == "alive" and router.pid not in (None, old), "router restarted", 60)
        run.wait(lambda: (out / "run.json").exists(), "the map finished", 600)
        summary = json.loads((out / "run.json").read_text())
        procs = {n: (p.state, len(p.restarts)) for n, p in run.sup.procs.items()}
    finally:
        run.close()
    assert procs["router"][1] == 1
    assert all(n == "router" or r == 0 for n, (_, r) in procs.items()), procs  # nobody else restarted
    assert summary["frames_announced"] == FRAMES
    assert summary["frames_lost"] <= 2 * run.plan.system.source.window_frames, summary
    assert summary["segments"] > 10


def test_a_frozen_service_is_reported_and_restarted(tmp_path, free_port):
    """SIGSTOP the query service past the link lease: the Supervisor reports it unresponsive,
    then restarts it under its policy. The stand-in keyframe_vl of examples/ answers the query
    service's warm-up: without a ``vl/embed`` it never declares itself alive."""
    stand_in = [sys.executable, str(ROOT / "examples" / "external_keyframe_vl.py"), "--connect", f"tcp/127.0.0.1:{free_port}", "--robot", "robot0"]
    services = [{"name": "router"}, {"name": "keyframe_vl", "command": stand_in}, {"name": "query"}]
    path = write_launch(tmp_path, free_port, services, unresponsive_s=4.0, exit_when_finished=False)
    run = Run(path, None, None).start(watch=False)
    try:
        query = run.sup.procs["query"]
        run.wait(lambda: query.state == "alive", "query up", 120)
        old = query.pid
        os.kill(old, signal.SIGSTOP)
        t0 = time.monotonic()
        seen = set()
        run.wait(lambda: seen.add(query.state) or (query.state == "alive" and query.pid not in (None, old)), "query restarted", 120)
        took = time.monotonic() - t0
        events = list(run.sup._events)
    finally:
        run.close()
    assert "unresponsive" in seen and len(query.restarts) == 1, (seen, events)
    assert any("unresponsive" in e for e in events)
    assert took < 60
