"""run.json's ``peak_rss_mb`` is the service's own peak, not one inherited from its parent."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

# A parent that touches 400 MB, then starts a child that reports its own peak both ways.
PARENT = """
import json, subprocess, sys
block = bytearray(400 * 1024 * 1024)
for i in range(0, len(block), 4096):
    block[i] = 1
child = "import json, resource; from services.fusion.export import peak_rss_mb; " \\
        "print(json.dumps([peak_rss_mb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024]))"
print(subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, check=True).stdout)
"""


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs Linux /proc")
def test_a_child_of_a_large_parent_reports_its_own_peak():
    out = subprocess.run([sys.executable, "-c", PARENT], capture_output=True, text=True, check=True, cwd=ROOT)
    own, inherited = json.loads(out.stdout)
    # ru_maxrss carries the parent's 400 MB over fork and exec; VmHWM is the child's alone.
    assert inherited > 390
    assert own < 200
