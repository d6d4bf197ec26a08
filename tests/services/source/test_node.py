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
from shared.messages import EndOfSequence, Frame
from shared.topics import Topics
from shared.transport import TypedSubscriber, open_session

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


def test_lossless_replay_delivers_every_frame(tmp_path, router):
    seq = write_sequence(tmp_path / "seq")
    topics = Topics("robot0")
    session = open_session(TransportConfig(connect=[router], shared_memory=False))
    frames = TypedSubscriber(session, topics.frames, Frame, policy="fifo", capacity=4)
    ends = TypedSubscriber(session, topics.end_of_sequence, EndOfSequence)
    try:
        proc = subprocess.run(_source_cmd(seq, router, "--stride", "2"), capture_output=True, text=True, timeout=60, cwd=REPO)
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout.strip().splitlines()[-1]) | {"seconds": 0} == {"published": 6, "dropped": 0, "seconds": 0}
        got = []
        while (env := frames.recv(timeout=2.0)) is not None:
            got.append(env.body.frame_index)
        assert got == [0, 2, 4, 6, 8, 10]
        end = ends.recv(timeout=2.0)
        assert end is not None and end.body.frames_published == 6 and end.body.last_frame_index == 10
    finally:
        frames.close()
        ends.close()
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
