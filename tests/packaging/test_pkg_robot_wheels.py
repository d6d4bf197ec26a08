"""The robot profile `trackgraph[tracker,fusion,source]` installs from wheels alone on a Jetson
(JetPack 6: aarch64, CPython 3.10, glibc 2.35): pip resolves it against the registry as the
Jetson would (tests/packaging/pkg_jetson_pip.py) with `--only-binary=:all:`, downloading
nothing."""

from __future__ import annotations

import json
import os
import re
import ssl
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
from packaging.utils import canonicalize_name, parse_wheel_filename

from tests.packaging.pkg_extras import JETSON_ENV, ROOT, profile_requirements
from tests.packaging.pkg_jetson_pip import PLATFORM_ARGS

SHIM = Path(__file__).resolve().parent / "pkg_jetson_pip.py"

ROBOT = ["tracker", "fusion", "source"]
NETWORK = re.compile(r"NewConnectionError|Max retries exceeded|Temporary failure in name resolution|"
                     r"Name or service not known|ConnectTimeout|Network is unreachable|Connection refused")  # fmt: skip


def _index_url() -> str:
    url = os.environ.get("PIP_INDEX_URL")
    if not url:
        got = subprocess.run([sys.executable, "-m", "pip", "config", "get", "global.index-url"], capture_output=True, text=True)
        url = got.stdout.strip() if got.returncode == 0 and got.stdout.strip() else "https://pypi.org/simple"
    return url.rstrip("/") + "/"


def _registry_reachable(url: str) -> str | None:
    """None when ``url`` answers; else why not."""
    ctx = ssl.create_default_context(cafile=os.environ.get("PIP_CERT") or None)
    try:
        with urllib.request.urlopen(url + "pip/", timeout=15, context=ctx) as r:
            r.read(1)
    except OSError as exc:  # URLError, timeouts, DNS
        return f"{url}: {exc}"
    return None


def test_the_robot_requirements_follow_the_extras_for_a_jetson():
    names = {canonicalize_name(r.name) for r in profile_requirements(ROBOT, JETSON_ENV)}
    assert "open3d" in names and "open3d-cpu" not in names  # PyPI has no open3d-cpu for aarch64
    assert {"torch", "numba", "scipy", "rosbags", "eclipse-zenoh"} <= names
    assert not names & {"spark-dsg", "ultralytics", "open-clip-torch"}, names


@pytest.mark.slow
@pytest.mark.registry
def test_the_robot_profile_resolves_to_aarch64_wheels(tmp_path):
    index = _index_url()
    why = _registry_reachable(index)
    if why is not None:
        pytest.skip(f"the package registry is unreachable: {why}")
    reqs = [str(r) for r in profile_requirements(ROBOT, JETSON_ENV)]
    report = tmp_path / "report.json"
    cmd = [sys.executable, str(SHIM), "install", "--dry-run", "--ignore-installed", "--quiet", "--report", str(report),
           "--target", str(tmp_path / "target"), "--only-binary=:all:", *PLATFORM_ARGS, *reqs]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=ROOT)
    if proc.returncode != 0:
        if NETWORK.search(proc.stderr) and "ResolutionImpossible" not in proc.stderr:
            pytest.skip(f"the package registry failed mid-resolution: {proc.stderr[-500:]}")
        pytest.fail(f"the robot profile does not resolve to wheels for a Jetson:\n{proc.stderr[-4000:]}")
    items = json.loads(report.read_text())["install"]
    bad, names = [], set()
    for item in items:
        url = item["download_info"]["url"]
        filename = url.rsplit("/", 1)[-1].split("#", 1)[0]
        names.add(canonicalize_name(item["metadata"]["name"]))
        if not filename.endswith(".whl"):
            bad.append(f"{filename}: not a wheel")
            continue
        tags = parse_wheel_filename(filename)[3]
        platforms = {t.platform for t in tags}
        abis = {t.abi for t in tags}
        if not (platforms & {"any"} or any(p.endswith("_aarch64") for p in platforms)):
            bad.append(f"{filename}: not for aarch64")
        if not abis & {"none", "abi3", "cp310"}:
            bad.append(f"{filename}: not for CPython 3.10")
    assert not bad, bad
    assert "open3d" in names, sorted(names)
    assert "torch" in names and "spark-dsg" not in names, sorted(names)
