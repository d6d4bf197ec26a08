"""The command-line contract (docs/architecture.md, "Command-line contract") for the commands
that exist so far."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from services.cli import main

REPO = Path(__file__).resolve().parents[2]
PRESETS = sorted((REPO / "deploy" / "configs").glob("*.yaml"))


def test_presets_exist():
    assert {p.stem for p in PRESETS} >= {"oracle", "synthetic", "classical", "paper", "onboard"}


@pytest.mark.parametrize("path", PRESETS, ids=lambda p: p.stem)
def test_config_check_accepts_presets(path, capsys):
    assert main(["config", "check", str(path)]) == 0
    assert "ok" in capsys.readouterr().out


def test_config_check_names_misspelt_key(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("fusion:\n  tsdf:\n    voxel_sze: 0.03\n")
    assert main(["config", "check", str(bad)]) != 0
    err = capsys.readouterr().err
    assert str(bad) in err and "fusion.tsdf.voxel_sze" in err and "voxel_size" in err
    assert len(err.strip().splitlines()) == 1


def test_config_check_names_out_of_range_value(tmp_path, capsys):
    bad = tmp_path / "neg.yaml"
    bad.write_text("fusion:\n  tsdf:\n    voxel_size: -0.05\n")
    assert main(["config", "check", str(bad)]) != 0
    err = capsys.readouterr().err
    assert "fusion.tsdf.voxel_size" in err and "-0.05" in err


def test_config_check_missing_file(tmp_path, capsys):
    assert main(["config", "check", str(tmp_path / "nope.yaml")]) != 0
    assert "nope.yaml" in capsys.readouterr().err


def test_config_show_resolves_defaults(capsys):
    onboard = REPO / "deploy" / "configs" / "onboard.yaml"
    assert main(["config", "show", str(onboard)]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["fusion"]["tsdf"]["voxel_size"] == 0.125
    assert shown["tracker"]["keyframe_interval"] == 24  # default filled in
    assert main(["config", "show", "--json", str(onboard)]) == 0
    assert json.loads(capsys.readouterr().out)["tracker"]["features"]["short_side"] == 480


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.zenoh
def test_router_subcommand_serves_and_stops_on_sigint():
    from shared.config import TransportConfig
    from shared.transport import open_session

    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "router", "--listen", endpoint],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 20
        session = None
        while session is None and time.monotonic() < deadline:
            try:
                session = open_session(TransportConfig(mode="client", connect=[endpoint], connect_timeout_s=0.5, shared_memory=False))
            except Exception:  # noqa: BLE001 - router not up yet
                time.sleep(0.2)
        assert session is not None, "could not connect to the router"
        session.close()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
        assert proc.returncode == 0, out
        assert "router closed" in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
