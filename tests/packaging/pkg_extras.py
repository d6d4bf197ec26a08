"""pyproject.toml's install profiles as requirement lists and as sets of installed distributions.

``profile_requirements`` flattens ``trackgraph[...]`` self-references the way pip does, with the
markers evaluated for a chosen environment (this machine's, or a Jetson's); ``closure`` follows
the result through the installed distributions' metadata, which is what an install of the
profile would hold (the installed versions standing in for the ones pip would pick).
"""

from __future__ import annotations

import sys
from importlib import metadata
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - the test venvs are 3.11; tomli is pip's vendored copy elsewhere
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[2]
PROJECT = "trackgraph"

JETSON_ENV = {
    # JetPack 6 (Ubuntu 22.04): aarch64, CPython 3.10, glibc 2.35.
    "implementation_name": "cpython",
    "implementation_version": "3.10.12",
    "os_name": "posix",
    "platform_machine": "aarch64",
    "platform_python_implementation": "CPython",
    "platform_release": "5.15.136-tegra",
    "platform_system": "Linux",
    "platform_version": "#1 SMP PREEMPT",
    "python_full_version": "3.10.12",
    "python_version": "3.10",
    "sys_platform": "linux",
}


def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def profile_requirements(extras: list[str], env: dict | None = None) -> list[Requirement]:
    """The base dependencies plus ``extras``' requirements, self-references expanded, markers
    evaluated in ``env`` (this interpreter's by default) and dropped where false."""
    project = pyproject()
    optional = project.get("optional-dependencies", {})
    env = {**default_environment(), **(env or {})}
    out: list[Requirement] = []
    seen: set[str] = set()

    def add(req_text: str, extra: str) -> None:
        req = Requirement(req_text)
        if req.marker is not None and not req.marker.evaluate({**env, "extra": extra}):
            return
        if canonicalize_name(req.name) == PROJECT:
            for sub in sorted(req.extras):
                expand(sub)
            return
        out.append(req)

    def expand(extra: str) -> None:
        if extra in seen:
            return
        if extra not in optional:
            raise KeyError(f"pyproject.toml has no extra {extra!r}")
        seen.add(extra)
        for text in optional[extra]:
            add(text, extra)

    for text in project.get("dependencies", []):
        add(text, "")
    for extra in extras:
        expand(extra)
    return out


def closure(extras: list[str]) -> set[str]:
    """Canonical names of the installed distributions a ``trackgraph[extras]`` install holds
    (trackgraph included). A requirement that is not installed here fails: the test would
    otherwise pass by checking less."""
    env = default_environment()
    dists = {PROJECT}
    visited: set[tuple[str, frozenset[str]]] = set()
    todo = profile_requirements(extras)
    missing = []
    while todo:
        req = todo.pop()
        key = (canonicalize_name(req.name), frozenset(req.extras))
        if key in visited:
            continue
        visited.add(key)
        try:
            dist = metadata.distribution(req.name)
        except metadata.PackageNotFoundError:
            missing.append(str(req))
            continue
        dists.add(key[0])
        for text in dist.requires or []:
            sub = Requirement(text)
            if sub.marker is None or any(sub.marker.evaluate({**env, "extra": e}) for e in (req.extras or {""})):
                todo.append(sub)
    if missing:
        raise LookupError(f"not installed here, so the closure cannot be checked: {sorted(missing)}")
    return dists
