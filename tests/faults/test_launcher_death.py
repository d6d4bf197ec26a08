"""A launcher's services end with it: SIGHUP (a closed terminal) and SIGKILL (the OOM killer)
to ``trackgraph launch deploy/local.yaml`` mid-run on ``small``, on a free loopback port.
Within 10 s no process of that launch is left, and a new launch on the same port starts."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import yaml

from shared.runtime.lifeline import LAUNCHER_PID_ENV

pytestmark = [pytest.mark.faults, pytest.mark.zenoh, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
TEARDOWN_S = 10.0
"""The issue's bound on how long a dead launcher's services may outlive it."""


def _launch_file(tmp: Path, port: int, *, services: list[dict] | None = None, name: str = "local.yaml") -> Path:
    doc = yaml.safe_load((ROOT / "deploy" / "local.yaml").read_text())
    doc.update(config=str(ROOT / "deploy" / doc["config"]), connect=[f"tcp/127.0.0.1:{port}"], listen=[f"tcp/127.0.0.1:{port}"])
    if services is not None:
        doc["services"] = services
    path = tmp / name
    path.write_text(yaml.safe_dump(doc))
    return path


def _of_launch(launcher: int, marks: tuple[str, ...]) -> list[tuple[int, str]]:
    """Live processes of one launch: a command line naming its unique out dir or its port, or
    an environment naming its launcher (the status heartbeat's command line names neither)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            env = (entry / "environ").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue  # gone meanwhile, or not ours to read
        if state == "Z":
            continue  # exited, waiting for its (new) parent to reap it: holds no port
        if any(m in cmd for m in marks) or f"{LAUNCHER_PID_ENV}={launcher}".encode() in env:
            found.append((int(entry.name), cmd))
    return found


def _wait_log(path: Path, text: str, timeout: float, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.is_file() and text in path.read_text(errors="replace"):
            return
        if proc.poll() is not None:
            raise AssertionError(f"launcher exited ({proc.returncode}) before {text!r}:\n{path.read_text(errors='replace')[-3000:]}")
        time.sleep(0.2)
    raise AssertionError(f"no {text!r} in {timeout:.0f} s:\n{path.read_text(errors='replace')[-3000:]}")


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGKILL], ids=["SIGHUP", "SIGKILL"])
def test_the_services_of_a_launch_end_with_it(sig, small, tmp_path, free_port):
    run = tmp_path / f"launch-{uuid.uuid4().hex[:12]}"
    run.mkdir()
    out = run / "map"
    log_path = run / "launcher.log"
    launch_file = _launch_file(run, free_port)
    marks = (str(run), f"127.0.0.1:{free_port}")
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "launch", str(launch_file), "--sequence", str(small), "--out", str(out), "--json"],
            stdout=subprocess.DEVNULL, stderr=log,
        )  # fmt: skip
    try:
        # Mid-run: every long-running service alive, the replay just started.
        _wait_log(log_path, "source started", 240, proc)
        before = _of_launch(proc.pid, marks)
        assert len(before) >= 7, before  # launcher, router, keyframe_vl, fusion, query, tracker, source (+ heartbeats)
        t0 = time.monotonic()
        proc.send_signal(sig)
        proc.wait(30)
        left = _of_launch(proc.pid, marks)
        while left and time.monotonic() - t0 < TEARDOWN_S + 5:
            time.sleep(0.1)
            left = _of_launch(proc.pid, marks)
        took = time.monotonic() - t0
        print(f"{sig.name}: {len(before)} processes gone in {took:.2f} s")
        assert not left, f"{sig.name}: still running after {took:.1f} s: {left}"
        assert took <= TEARDOWN_S, f"{sig.name}: teardown took {took:.1f} s"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        for pid, _ in _of_launch(proc.pid, marks):
            os.kill(pid, signal.SIGKILL)

    # The port is free: a new launch on it starts its router.
    again = _launch_file(run, free_port, services=[{"name": "router"}], name="again.yaml")
    log2 = run / "again.log"
    with open(log2, "wb") as log:
        proc2 = subprocess.Popen([sys.executable, "-m", "services.cli", "launch", str(again), "--log-dir", str(run / "again-logs"), "--json"], stdout=subprocess.DEVNULL, stderr=log)
    try:
        _wait_log(log2, "router alive", 30, proc2)
    finally:
        proc2.send_signal(signal.SIGINT)
        assert proc2.wait(30) == 0, log2.read_text(errors="replace")[-3000:]
