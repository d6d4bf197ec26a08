"""Importing the common library and the services must not load torch, open3d or weights."""

from __future__ import annotations

import subprocess
import sys

MODULES = [
    "shared",
    "shared.config",
    "shared.codec",
    "shared.messages",
    "shared.topics",
    "shared.transport",
    "shared.geometry",
    "services.cli",
    "services.router",
]


def test_light_imports():
    code = (
        "import sys\n"
        + "".join(f"import {m}\n" for m in MODULES)
        + "heavy = [m for m in ('torch', 'open3d', 'onnxruntime', 'ultralytics', 'open_clip', 'timm') if m in sys.modules]\n"
        + "print(','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"heavy modules imported: {out.stdout.strip()}"


def test_cores_do_not_import_zenoh():
    """Functional core, thin shell: only transport and service nodes may import zenoh."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    allowed = {"shared/transport.py", "shared/ros2/link.py", "services/router.py"}
    offenders = []
    for path in list((root / "shared").rglob("*.py")) + list((root / "services").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel in allowed or rel.endswith("/node.py"):
            continue
        text = path.read_text()
        if "import zenoh" in text or "from zenoh" in text:
            offenders.append(rel)
    assert offenders == []
