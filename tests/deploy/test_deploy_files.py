"""The systemd units and Dockerfiles under deploy/ agree with the CLI and with pyproject.toml.

Docker cannot be built here and systemd is not run: these are static checks that every
command line they contain parses with the real ``trackgraph`` parser, every extra they
install exists, and torch is pinned to the Makefile's pair before anything else pulls it.
"""

from __future__ import annotations

import configparser
import contextlib
import io
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SYSTEMD = ROOT / "deploy" / "systemd"
DOCKER = ROOT / "deploy" / "docker"
UNITS = ["router", "keyframe-vl", "tracker", "fusion", "query", "source"]
TORCH_PAIR = "torch==2.14.1 torchvision==0.29.1"
CPU_INDEX = "https://download.pytorch.org/whl/cpu"


# --------------------------------------------------------------------------- helpers


def cli_error(argv: list[str]) -> str | None:
    """None if ``trackgraph ARGV`` parses with the real parser, else argparse's message."""
    from services.cli import build_parser

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(argv)
    except SystemExit as exc:
        return err.getvalue().strip() or f"exit {exc.code}"
    return None


def check_cli(argv: list[str], where: str) -> None:
    """Fail on a command line the CLI rejects; skip, naming it, on a subcommand or service
    that is still being built (argparse's 'invalid choice')."""
    msg = cli_error(argv)
    if msg is None:
        return
    if "invalid choice" in msg:
        pytest.skip(f"{where}: `trackgraph {' '.join(argv[:2])}` is not in the CLI yet ({msg.splitlines()[-1]})")
    pytest.fail(f"{where}: `trackgraph {shlex.join(argv)}` does not parse: {msg}")


_help_cache: dict[str, int] = {}


def help_exit_code(subcommand: str) -> int:
    """Exit code of ``python -m services.cli SUBCOMMAND --help`` (once per subcommand)."""
    if subcommand not in _help_cache:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        proc = subprocess.run(
            [sys.executable, "-m", "services.cli", subcommand, "--help"],
            cwd=ROOT, env=env, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        _help_cache[subcommand] = proc.returncode
    return _help_cache[subcommand]


def read_unit(name: str) -> tuple[configparser.ConfigParser, list[str]]:
    """The unit as INI, plus its raw lines (configparser keeps only the last of repeated
    keys such as Environment=)."""
    path = SYSTEMD / f"trackgraph-{name}.service"
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # systemd keys are case-sensitive
    text = path.read_text()
    parser.read_string(text, source=str(path))
    return parser, text.splitlines()


def unit_environment(lines: list[str]) -> dict[str, str]:
    env: dict[str, str] = {}
    for line in lines:
        if line.startswith("Environment="):
            for item in shlex.split(line.split("=", 1)[1]):
                key, _, value = item.partition("=")
                env[key] = value
    return env


def expand(argv: list[str], env: dict[str, str]) -> list[str]:
    """systemd's ${VAR} (one word) and $VAR expansion in ExecStart=."""

    def sub(word: str) -> str:
        def one(m: re.Match) -> str:
            name = m.group(1) or m.group(2)
            assert name in env, f"ExecStart uses ${name}, which no Environment= line sets"
            return env[name]

        return re.sub(r"\$\{(\w+)\}|\$(\w+)", one, word)

    return [sub(w) for w in argv]


def exec_start(name: str) -> list[str]:
    parser, lines = read_unit(name)
    raw = parser["Service"]["ExecStart"]
    argv = expand(shlex.split(raw.lstrip("-@:+!")), unit_environment(lines))
    assert Path(argv[0]).name == "trackgraph", f"{name}: ExecStart must run the trackgraph console script"
    assert argv[0].startswith("/"), f"{name}: ExecStart needs an absolute path for older systemd"
    return argv[1:]


def dockerfile(name: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    out, buf = [], ""
    for line in (DOCKER / name).read_text().splitlines():
        stripped = line.strip()
        if not buf and (not stripped or stripped.startswith("#")):
            continue
        if stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            buf += stripped[:-1] + " "
            continue
        buf += stripped
        instr, _, args = buf.partition(" ")
        out.append((instr.upper(), args.strip()))
        buf = ""
    return out


def extras() -> dict[str, list[str]]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["project"]["optional-dependencies"]


def makefile_torch() -> str | None:
    path = ROOT / "Makefile"
    if not path.exists():
        return None
    m = re.search(r"^TORCH\s*\??=\s*(.+)$", path.read_text(), re.M)
    return " ".join(m.group(1).split()) if m else None


# --------------------------------------------------------------------------- systemd


def test_every_unit_is_there():
    names = sorted(p.name for p in SYSTEMD.glob("*.service"))
    assert names == sorted(f"trackgraph-{u}.service" for u in UNITS)
    assert (SYSTEMD / "README.md").is_file()


@pytest.mark.parametrize("name", UNITS)
def test_unit_is_a_well_behaved_service(name: str):
    parser, lines = read_unit(name)
    assert {"Unit", "Service", "Install"} <= set(parser.sections())
    svc = parser["Service"]
    assert parser["Unit"].get("Description")
    assert svc.get("User") and svc["User"] != "root", "a dedicated user, never root"
    assert svc.get("Restart") == "on-failure"
    assert float(svc.get("RestartSec", "0")) > 0
    assert svc.get("KillSignal") == "SIGINT", "the services shut down cleanly on SIGINT"
    timeout = float(svc.get("TimeoutStopSec", "0"))
    assert timeout >= (120 if name == "fusion" else 10), "fusion needs time for its final snapshot"
    assert any(ln.startswith("EnvironmentFile=") for ln in lines)
    assert any(ln.startswith("Environment=") for ln in lines)
    assert parser["Install"].get("WantedBy") == "multi-user.target"


@pytest.mark.parametrize("name", UNITS)
def test_unit_exec_start_is_a_real_command(name: str):
    argv = exec_start(name)
    assert help_exit_code(argv[0]) == 0, f"`trackgraph {argv[0]} --help` fails"
    check_cli(argv, f"trackgraph-{name}.service")


def test_unit_command_lines():
    assert exec_start("router")[:1] == ["router"]
    assert "--listen" in exec_start("router") and "--zenoh-config" in exec_start("router")
    assert exec_start("keyframe-vl") == ["serve", "keyframe_vl", "--config", "/etc/trackgraph/paper.yaml", "--connect", "tcp/BASE:7447"]
    assert exec_start("tracker")[:2] == ["serve", "tracker"]
    fusion = exec_start("fusion")
    assert fusion[:2] == ["serve", "fusion"] and "--resume" in fusion
    assert fusion[fusion.index("--out") + 1] == "/var/lib/trackgraph/map"
    assert exec_start("query")[:2] == ["serve", "query"]
    assert exec_start("source")[0] == "source"


def test_router_unit_points_at_a_shipped_zenoh_file():
    _, lines = read_unit("router")
    path = unit_environment(lines)["TRACKGRAPH_ZENOH_CONFIG"]
    assert path.startswith("/opt/trackgraph/deploy/zenoh/")
    assert (ROOT / path.removeprefix("/opt/trackgraph/")).is_file()


# --------------------------------------------------------------------------- docker


@pytest.mark.parametrize("name", ["Dockerfile.cpu", "Dockerfile.cuda"])
def test_dockerfile_installs_existing_extras_after_pinned_torch(name: str):
    steps = dockerfile(name)
    runs = [args for instr, args in steps if instr == "RUN"]
    known = extras()
    installs = [(i, m.group(1)) for i, r in enumerate(runs) for m in re.finditer(r"pip install [^;&]*?\"?\.\[([\w,-]+)\]", r)]
    assert installs, f"{name}: no pip install .[extras]"
    for _, group in installs:
        for extra in group.split(","):
            assert extra in known, f"{name}: extra [{extra}] is not in pyproject.toml ({', '.join(known)})"
    torch_runs = [i for i, r in enumerate(runs) if TORCH_PAIR in " ".join(r.split())]
    assert torch_runs, f"{name}: torch must be pinned to {TORCH_PAIR}"
    assert min(torch_runs) < min(i for i, _ in installs), f"{name}: torch must be installed before the extras"
    for r in runs:  # no other torch versions sneak in
        for m in re.finditer(r"\btorch(vision)?==([\w.+]+)", r):
            assert m.group(0) in TORCH_PAIR.split(), f"{name}: {m.group(0)}"
    if makefile_torch() is not None:
        assert makefile_torch() == TORCH_PAIR, "the Makefile's torch pair changed: update the Dockerfiles and this test"


def test_cpu_image():
    steps = dockerfile("Dockerfile.cpu")
    assert steps[0] == ("FROM", "python:3.11-slim")
    runs = " ".join(args for instr, args in steps if instr == "RUN")
    assert f"--index-url {CPU_INDEX} {TORCH_PAIR}" in " ".join(runs.split())
    for pkg in ("libusb-1.0-0", "libgl1"):
        assert re.search(rf"apt-get install[^&]*\b{re.escape(pkg)}\b", runs), pkg
    assert 'pip install ".[tracker,fusion,hydra,query,source]"' in runs


def test_cuda_image():
    steps = dockerfile("Dockerfile.cuda")
    args = dict(a.split("=", 1) for instr, a in steps if instr == "ARG" and "=" in a)
    base = args.get("CUDA_IMAGE", "")
    assert re.fullmatch(r"nvidia/cuda:12\.\d+(\.\d+)?-cudnn-runtime-ubuntu22\.04", base), base
    assert ("FROM", "${CUDA_IMAGE}") in steps
    runs = " ".join(a for instr, a in steps if instr == "RUN")
    assert "python3.11" in runs and "-m venv" in runs
    assert 'pip install ".[vl]"' in runs
    cmd = next(a for instr, a in steps if instr == "CMD")
    assert cmd == '["serve", "keyframe_vl", "--config", "/etc/trackgraph/paper.yaml"]'
    check_cli(["serve", "keyframe_vl", "--config", "/etc/trackgraph/paper.yaml"], "Dockerfile.cuda CMD")


@pytest.mark.parametrize("name", ["Dockerfile.cpu", "Dockerfile.cuda"])
def test_dockerfile_runs_trackgraph_as_a_user_and_bakes_no_secrets(name: str):
    steps = dockerfile(name)
    assert ("ENTRYPOINT", '["trackgraph"]') in steps
    users = [a for instr, a in steps if instr == "USER"]
    assert users and users[-1] not in ("root", "0"), "a non-root user"
    text = (DOCKER / name).read_text()
    assert not re.search(r"\b(wget|curl|hf_hub_download|huggingface-cli)\b", text), "weights are mounted, never downloaded"
    for instr, a in steps:
        if instr not in ("COPY", "ADD"):
            continue
        assert instr == "COPY", "ADD can fetch URLs; use COPY"
        *sources, _dest = shlex.split(a)
        for src in sources:
            if src.startswith("--"):
                continue
            assert src not in (".", "deploy", "deploy/", "deploy/zenoh", "deploy/zenoh/secure"), f"{name}: COPY {src} would bake certs/ into the image"
            assert "certs/" not in src and not src.endswith("certs"), f"{name}: certificates and passwords are mounted, not copied"
            assert list(ROOT.glob(src)), f"{name}: COPY source {src} does not exist in the build context"


def test_docker_readme_command_lines():
    """Every `docker run ... trackgraph:TAG ARGS` line of the README parses with the CLI,
    and the documented build commands name the Dockerfiles that exist."""
    text = (DOCKER / "README.md").read_text()
    assert "docker build -f deploy/docker/Dockerfile.cpu -t trackgraph:cpu ." in text
    assert "docker build -f deploy/docker/Dockerfile.cuda -t trackgraph:cuda ." in text
    joined = re.sub(r"\\\n\s*", " ", text)
    runs = [ln.strip() for ln in joined.splitlines() if ln.strip().startswith("docker run")]
    assert len(runs) >= 6, "one docker run line per role"
    commands = set()
    skipped = []
    for line in runs:
        words = shlex.split(line)
        image = next(i for i, w in enumerate(words) if re.fullmatch(r"trackgraph:(cpu|cuda)", w))
        argv = words[image + 1 :]
        if not argv:
            continue  # the image's default CMD
        commands.add(argv[0] if argv[0] != "serve" else f"serve {argv[1]}")
        msg = cli_error(argv)
        if msg is not None and "invalid choice" in msg:
            skipped.append(" ".join(argv[:2]))
            continue
        assert msg is None, f"README: `trackgraph {shlex.join(argv)}` does not parse: {msg}"
    assert {"router", "source", "serve tracker", "serve fusion", "serve keyframe_vl", "serve query"} <= commands
    if skipped:
        pytest.skip(f"README lines for commands not in the CLI yet: {', '.join(skipped)}")
