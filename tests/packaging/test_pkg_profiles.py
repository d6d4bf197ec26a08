"""Each install profile runs its services with only what the profile installs.

A profile's distributions are computed from pyproject.toml (base dependencies plus the extra,
self-references followed) and the installed distributions' metadata; a subprocess then hides
every other installed distribution (tests/packaging/pkg_blocker.py) and imports the profile's
services, or, for the base station's `trackgraph[query]`, runs `trackgraph serve query` and
`serve viewer` against a router.
"""

from __future__ import annotations

import json
import os
import pkgutil
import signal
import socket
import subprocess
import sys
import threading
import time
from importlib import import_module
from pathlib import Path

import pytest
import yaml

from tests.packaging.pkg_extras import ROOT, closure

BLOCKER = Path(__file__).resolve().parent / "pkg_blocker.py"

PROFILES = {
    # extra: the service packages it must run
    "query": ["services.query", "services.viewer"],  # the base station
    "tracker": ["services.tracker"],
    "robot": ["services.tracker", "services.fusion", "services.source"],  # tracker + fusion + source
    "vl": ["services.keyframe_vl"],  # the GPU server
}


def _modules(packages: list[str]) -> list[str]:
    """Every module of ``packages``: a module-level import of any of them must be installed."""
    out = []
    for name in packages:
        pkg = import_module(name)
        out += [name, *(m.name for m in pkgutil.walk_packages(pkg.__path__, name + "."))]
    return out


def _allowed(tmp: Path, extra: str) -> Path:
    path = tmp / f"allowed-{extra}.json"
    path.write_text(json.dumps(sorted(closure([extra]))))
    return path


def _blocked(allowed: Path, report: Path, *args: str) -> list[str]:
    return [sys.executable, str(BLOCKER), str(allowed), str(report), *args]


def test_the_profiles_hold_what_their_machines_run():
    base = closure(["query"])
    assert not base & {"torch", "open3d", "open3d-cpu", "torchvision", "onnxruntime"}, sorted(base)
    assert {"rerun-sdk", "matplotlib", "scipy", "threadpoolctl"} <= base  # the viewer too
    robot = closure(["robot"])
    assert closure(["tracker", "fusion", "source"]) == robot
    assert robot & {"open3d-cpu", "open3d"}
    assert not robot & {"ultralytics", "open-clip-torch", "spark-dsg"}, "the VL stack (or spark_dsg) on the robot"


@pytest.mark.slow
@pytest.mark.parametrize("extra", list(PROFILES))
def test_a_profile_imports_its_services(tmp_path, extra):
    allowed = _allowed(tmp_path, extra)
    report = tmp_path / "report.json"
    proc = subprocess.run(_blocked(allowed, report, "import", *_modules(PROFILES[extra])),
                          capture_output=True, text=True, timeout=120, cwd=ROOT)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    if extra == "query":
        assert not set(json.loads(report.read_text())["loaded"]) & {"torch", "open3d"}
    if extra == "robot":  # what fusion loads lazily: Open3D (libusb preloaded), numba, scipy
        code = "from shared.o3d import import_open3d; import_open3d(); import numba, scipy.spatial, rosbags"
        proc = subprocess.run(_blocked(allowed, report, "exec", code), capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert proc.returncode == 0, proc.stderr[-3000:]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.zenoh
def test_the_base_station_profile_serves_query_and_viewer(tmp_path):
    """`trackgraph serve query` and `serve viewer` with only `trackgraph[query]` importable:
    both report their status, stop on SIGINT with exit 0, and never load torch or open3d."""
    from services.router import run_router
    from shared.config.root import TrackGraphConfig
    from shared.messages.status import ServiceStatus
    from shared.topics import Topics
    from shared.transport import ZenohBus

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    data = yaml.safe_load((ROOT / "deploy" / "configs" / "synthetic.yaml").read_text())
    data["transport"] = {**data.get("transport", {}), "mode": "client", "connect": [endpoint], "listen": [],
                         "multicast_scouting": False, "shared_memory": False}  # fmt: skip
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump(data))
    cfg = TrackGraphConfig.model_validate(data)

    stop = threading.Event()
    router_cfg = cfg.transport.model_copy(update={"mode": "router", "connect": [], "listen": [endpoint]})
    router = threading.Thread(target=run_router, args=(router_cfg, stop), daemon=True)
    router.start()
    allowed = _allowed(tmp_path, "query")
    seen: dict[str, ServiceStatus] = {}
    procs: dict[str, subprocess.Popen] = {}
    bus = None
    try:
        deadline = time.monotonic() + 20
        while bus is None:
            try:
                bus = ZenohBus.open(cfg.transport.model_copy(update={"connect_timeout_s": 0.5}), cfg.robot_id)
            except Exception:  # noqa: BLE001 - the router is not listening yet
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        topics = Topics(cfg.robot_id)
        for service in ("query", "viewer"):
            bus.subscribe(topics.status(service), ServiceStatus, lambda env: seen.setdefault(env.body.service, env.body))
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        for service, extra in (("query", []), ("viewer", ["--out", str(tmp_path / "live.rrd")])):
            args = ["serve", service, "--config", str(config), "--status-file", str(tmp_path / f"{service}.status.json"), *extra]
            procs[service] = subprocess.Popen(_blocked(allowed, tmp_path / f"{service}.report.json", "cli", *args), cwd=ROOT,
                                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)  # fmt: skip
        deadline = time.monotonic() + 30
        while len(seen) < 2 and time.monotonic() < deadline and all(p.poll() is None for p in procs.values()):
            time.sleep(0.1)
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        outs = {name: p.communicate(timeout=30)[0] for name, p in procs.items()}
        for name, p in procs.items():
            assert name in seen, f"{name} published no ServiceStatus:\n{outs[name][-3000:]}"
            assert p.returncode == 0, f"{name} exited {p.returncode}:\n{outs[name][-3000:]}"
            assert (tmp_path / f"{name}.status.json").exists()
            report = json.loads((tmp_path / f"{name}.report.json").read_text())
            assert not set(report["loaded"]) & {"torch", "open3d"}, (name, report)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        if bus is not None:
            bus.close()
        stop.set()
        router.join(timeout=10)
