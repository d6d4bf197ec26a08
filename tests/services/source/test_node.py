"""The source as a real process: replays a sequence through a router to a subscriber."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.router import run_router
from shared.config import TransportConfig
from shared.messages import EndOfSequence, Frame, FrameAck
from shared.messages.status import ServiceStatus
from shared.runtime.status import read_status
from shared.topics import Topics
from shared.transport import TypedPublisher, TypedSubscriber, declare_alive, open_session

pytestmark = pytest.mark.zenoh

REPO = Path(__file__).resolve().parents[3]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_sequence(root: Path, n: int = 12, w: int = 16, h: int = 12) -> Path:
    (root / "results").mkdir(parents=True)
    rows = []
    for i in range(n):
        rgb = np.full((h, w, 3), (i * 20) % 256, np.uint8)
        Image.fromarray(rgb).save(root / "results" / f"frame{i:06d}.jpg", quality=95)
        Image.fromarray(np.full((h, w), 6553 + i, np.uint16)).save(root / "results" / f"depth{i:06d}.png")
        T = np.eye(4)
        T[0, 3] = 0.1 * i
        rows.append(" ".join(f"{v:.9f}" for v in T.ravel()))
    (root / "traj.txt").write_text("\n".join(rows) + "\n")
    (root / "intrinsics.json").write_text(json.dumps({"fx": 10.0, "fy": 10.0, "cx": 7.5, "cy": 5.5, "width": w, "height": h, "depth_scale": 6553.5}))
    return root


@pytest.fixture
def router():
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    stop = threading.Event()
    t = threading.Thread(target=run_router, args=(TransportConfig(mode="router", connect=[], listen=[endpoint], shared_memory=False), stop), daemon=True)
    t.start()
    time.sleep(0.3)
    try:
        yield endpoint
    finally:
        stop.set()
        t.join(timeout=10)


def _source_cmd(seq: Path, endpoint: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "services.cli", "source", str(seq), "--connect", endpoint, "--json", *extra]


def test_lossless_replay_is_paced_by_the_stages_and_delivers_every_frame(tmp_path, router):
    """A slow stage that acknowledges each frame (``frames/ack``), with a queue of only 4:
    the source stays ``window_frames`` ahead of it, so nothing is dropped and no Zenoh
    thread waits."""
    seq = write_sequence(tmp_path / "seq")
    topics = Topics("robot0")
    session = open_session(TransportConfig(connect=[router], shared_memory=False))
    token = declare_alive(session, topics.alive("tracker"))
    acks = TypedPublisher(session, topics.frame_ack, FrameAck, robot_id="robot0")
    got: list[int] = []

    def slow_stage(env) -> None:
        time.sleep(0.1)
        got.append(env.body.frame_index)
        acks.put(FrameAck(frame_index=env.body.frame_index, service="tracker"))

    frames = TypedSubscriber(session, topics.frames, Frame, policy="fifo", capacity=4, callback=slow_stage)
    ends = TypedSubscriber(session, topics.end_of_sequence, EndOfSequence)
    reports: list[ServiceStatus] = []
    status = TypedSubscriber(session, topics.status("source"), ServiceStatus, callback=lambda env: reports.append(env.body))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("source:\n  window_frames: 2\n")
    status_file = tmp_path / "source.status.json"
    try:
        t0 = time.monotonic()
        cmd = _source_cmd(seq, router, "--config", str(cfg), "--status-file", str(status_file))
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=REPO)
        took = time.monotonic() - t0
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout.strip().splitlines()[-1]) | {"seconds": 0} == {"published": 12, "dropped": 0, "seconds": 0}
        end = ends.recv(timeout=5.0)
        assert end is not None and end.body.frames_published == 12 and end.body.last_frame_index == 11
        deadline = time.monotonic() + 5
        while len(got) < 12 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert got == list(range(12))
        assert frames.stats.dropped == 0
        assert took > 0.9  # it waited for the stage (12 frames at 0.1 s, 2 ahead)
        final = read_status(status_file)
        assert final.state == "stopped" and final.frames_done == final.frames_expected == 12
        assert final.figures["published"] == 12 and final.figures["dropped"] == 0 and final.published["frames"] == 12
        assert {c.name: c.processed for c in final.inputs}["frame_ack"] >= 12 - 2  # the last ones may come after it is done
        deadline = time.monotonic() + 5
        while not any(r.state == "stopped" for r in reports) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert any(r.state == "stopped" for r in reports), reports
    finally:
        status.close()
        frames.close()
        ends.close()
        acks.close()
        token.undeclare()
        session.close()


def test_lossless_replay_to_a_plain_subscriber(tmp_path, router):
    """No pacing stage is alive: the replay is not held up, and a subscriber that keeps
    up gets every frame in order."""
    seq = write_sequence(tmp_path / "seq")
    topics = Topics("robot0")
    session = open_session(TransportConfig(connect=[router], shared_memory=False))
    got: list[int] = []
    frames = TypedSubscriber(session, topics.frames, Frame, policy="fifo", capacity=64, callback=lambda env: got.append(env.body.frame_index))
    try:
        proc = subprocess.run(_source_cmd(seq, router, "--stride", "2"), capture_output=True, text=True, timeout=60, cwd=REPO)
        assert proc.returncode == 0, proc.stderr
        deadline = time.monotonic() + 5
        while len(got) < 6 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert got == [0, 2, 4, 6, 8, 10]
    finally:
        frames.close()
        session.close()


def test_lossless_without_subscriber_fails_clearly(tmp_path, router):
    seq = write_sequence(tmp_path / "seq", n=2)
    proc = subprocess.run(_source_cmd(seq, router, "--wait", "0.5"), capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("trackgraph: error:") and "no subscriber" in last


def test_bad_sequence_names_the_file(tmp_path, router):
    seq = write_sequence(tmp_path / "seq", n=2)
    (seq / "traj.txt").unlink()
    proc = subprocess.run(_source_cmd(seq, router), capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode != 0 and "traj.txt" in proc.stderr
