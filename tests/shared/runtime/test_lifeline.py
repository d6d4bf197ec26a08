"""The lifeline: a process started with the launcher's pid in its environment ends with the
launcher (parent-death signal on Linux, the parent watch everywhere); one started any other
way (systemd, Docker, a shell) never stops because its parent went. SIGHUP is a stop signal."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from shared.runtime import lifeline
from shared.runtime.lifeline import (
    LAUNCHER_GRACE_ENV,
    LAUNCHER_PID_ENV,
    Lifeline,
    launcher_pid,
    start_lifeline,
)

ROOT = Path(__file__).resolve().parents[3]

# A "service": stops in order when its lifeline fires (writes DONE), else lives 60 s.
SERVICE = textwrap.dedent(
    """
    import sys, threading
    from shared.runtime.lifeline import install_stop_handlers, start_lifeline
    stop = threading.Event()
    install_stop_handlers(stop.set)
    line = start_lifeline()
    if line is not None:
        line.stop_with(stop.set)
    print("up", flush=True)
    stop.wait(60)
    open(sys.argv[1], "w").write("stopped in order")
    """
)
# A "launcher": starts the service (with or without its pid in the environment), prints the
# service's pid, then waits to be killed.
LAUNCHER = textwrap.dedent(
    """
    import os, subprocess, sys, time
    env = dict(os.environ)
    if sys.argv[3] == "launched":
        env["TRACKGRAPH_LAUNCHER_PID"] = str(os.getpid())
        env["TRACKGRAPH_LAUNCHER_GRACE_S"] = "5"
    child = subprocess.Popen([sys.executable, "-c", sys.argv[1], sys.argv[2]], env=env, stdout=subprocess.PIPE, text=True, start_new_session=True)
    assert child.stdout.readline().strip() == "up"
    print(child.pid, flush=True)
    time.sleep(60)
    """
)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_launcher_pid_comes_only_from_the_launchers_variable():
    assert launcher_pid({}) is None
    assert launcher_pid({LAUNCHER_PID_ENV: ""}) is None
    assert launcher_pid({LAUNCHER_PID_ENV: "not-a-pid"}) is None
    assert launcher_pid({LAUNCHER_PID_ENV: "1"}) is None  # init is nobody's launcher
    assert launcher_pid({LAUNCHER_PID_ENV: " 4242 "}) == 4242


def test_no_lifeline_without_a_launcher(monkeypatch):
    monkeypatch.delenv(LAUNCHER_PID_ENV, raising=False)
    assert start_lifeline(lambda: pytest.fail("stopped without a launcher")) is None


def test_the_watch_notices_a_parent_that_is_not_the_launcher(monkeypatch):
    """The portable path (no prctl): a parent pid other than the launcher's means it has gone."""
    monkeypatch.setattr(lifeline, "set_parent_death_signal", lambda sig=None: False)
    gone = threading.Event()
    line = Lifeline(os.getppid() + 100000, gone.set, grace_s=3600, period_s=0.05)
    try:
        assert not line.pdeathsig
        assert gone.wait(2.0)
        assert line.gone_at is not None
    finally:
        line.close()
    later = threading.Event()
    line.stop_with(later.set)  # the service came up after the launcher went: stop at once
    assert later.is_set()


def test_the_watch_leaves_a_live_launchers_service_alone():
    stopped = threading.Event()
    line = Lifeline(os.getppid(), stopped.set, grace_s=3600, period_s=0.05)
    try:
        assert not stopped.wait(0.3)
    finally:
        line.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("how", ["launched", "systemd"])
def test_a_launched_service_ends_with_its_killed_launcher_and_no_other(how, tmp_path):
    done = tmp_path / "done"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop(LAUNCHER_PID_ENV, None)
    env.pop(LAUNCHER_GRACE_ENV, None)
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER, SERVICE, str(done), how], env=env, stdout=subprocess.PIPE, text=True)
    child = None
    try:
        child = int(launcher.stdout.readline())
        t0 = time.monotonic()
        launcher.kill()  # SIGKILL: no cleanup in the launcher
        launcher.wait(10)
        # Launched: gone well within the 5 s; otherwise still there after three watch periods.
        while _alive(child) and time.monotonic() - t0 < (5.0 if how == "launched" else 3 * lifeline.WATCH_PERIOD_S):
            time.sleep(0.02)
        if how == "launched":
            assert not _alive(child), "a launched service outlived its launcher"
            assert done.read_text() == "stopped in order"  # SIGTERM from the kernel, then the stop path
        else:
            assert _alive(child), "a service without a launcher stopped because its parent went"
            assert not done.exists()
    finally:
        launcher.stdout.close()
        if child is not None and _alive(child):
            os.kill(child, signal.SIGKILL)


def test_sighup_stops_in_order(tmp_path):
    """SIGHUP (a closed terminal) takes the same orderly path as SIGINT and SIGTERM."""
    done = tmp_path / "done"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop(LAUNCHER_PID_ENV, None)
    proc = subprocess.Popen([sys.executable, "-c", SERVICE, str(done)], env=env, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "up"
        proc.send_signal(signal.SIGHUP)
        assert proc.wait(10) == 0
        assert done.read_text() == "stopped in order"
    finally:
        proc.stdout.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
