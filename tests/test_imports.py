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
    "shared.perception",
    "shared.perception.segmenters",
    "shared.perception.encoders",
    "shared.perception.features",
    "services.cli",
    "services.router",
]


def test_light_imports():
    code = (
        "import sys\n"
        + "".join(f"import {m}\n" for m in MODULES)
        # Listing the backends imports every built-in backend's config module: still light.
        + "from shared.perception import segmenters, encoders, features\n"
        + "names = segmenters.SEGMENTERS.names() + encoders.VL_ENCODERS.names() + features.DENSE_FEATURES.names()\n"
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


def test_shared_does_not_import_services():
    """The common library sits below the services: no module under ``shared/`` imports
    ``services``, not even inside a function."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    offenders = []
    for path in sorted((root / "shared").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        for node in ast.walk(ast.parse(path.read_text(), filename=rel)):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            else:
                continue
            offenders += [f"{rel}:{node.lineno}: {n}" for n in names if n == "services" or n.startswith("services.")]
    assert offenders == [], "shared/ imports services:\n" + "\n".join(offenders)
