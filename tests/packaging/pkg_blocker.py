"""Run Python as if only some installed distributions were there.

    python tests/packaging/pkg_blocker.py ALLOWED_JSON REPORT_JSON import MODULE ...
    python tests/packaging/pkg_blocker.py ALLOWED_JSON REPORT_JSON cli ARG ...
    python tests/packaging/pkg_blocker.py ALLOWED_JSON REPORT_JSON exec CODE

``ALLOWED_JSON`` lists canonical distribution names. A ``sys.meta_path`` finder refuses (with
``ImportError``, as if absent) every top-level module that belongs to an installed distribution
outside that list; the standard library and the repository's own packages always import, and
so does a module no distribution claims. Then each MODULE is imported, ``services.cli.main``
runs with the ARGs, or CODE runs. At exit ``REPORT_JSON`` gets the refused imports and the top-level modules
loaded. The exit status is that of the imports (1 on the first failure) or of the command.
"""

from __future__ import annotations

import atexit
import importlib
import importlib.abc
import json
import re
import sys
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ALWAYS = {"services", "shared", "deploy", "tests"}


def _canon(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


class Blocker(importlib.abc.MetaPathFinder):
    def __init__(self, allowed: set[str]) -> None:
        self.allowed = {_canon(d) for d in allowed}
        self.owners = {mod: {_canon(d) for d in dists} for mod, dists in metadata.packages_distributions().items()}
        self.refused: list[str] = []

    def find_spec(self, fullname, path=None, target=None):
        top = fullname.partition(".")[0]
        if top in sys.stdlib_module_names or top in ALWAYS or top in sys.builtin_module_names:
            return None
        owners = self.owners.get(top)
        if owners and not owners & self.allowed:
            if top not in self.refused:
                self.refused.append(top)
            raise ModuleNotFoundError(f"{top} is not in this install profile (from {sorted(owners)})", name=fullname)
        return None


def main(argv: list[str]) -> int:
    allowed_file, report_file, mode, *rest = argv
    blocker = Blocker(set(json.loads(Path(allowed_file).read_text())))
    sys.meta_path.insert(0, blocker)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))

    def report() -> None:
        loaded = sorted({m.partition(".")[0] for m in list(sys.modules)} - set(sys.stdlib_module_names))
        Path(report_file).write_text(json.dumps({"refused": blocker.refused, "loaded": loaded}))

    atexit.register(report)
    if mode == "import":
        for name in rest:
            try:
                importlib.import_module(name)
            except Exception as exc:  # noqa: BLE001 - reported, then a failing exit
                print(f"import {name} failed: {type(exc).__name__}: {exc}", file=sys.stderr)
                return 1
        return 0
    if mode == "cli":
        from services.cli import main as cli

        return cli(rest) or 0
    if mode == "exec":
        exec(compile(rest[0], "<blocked>", "exec"), {"__name__": "__blocked__"})
        return 0
    raise SystemExit(f"unknown mode {mode!r}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
