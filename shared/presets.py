"""Config presets and launch files, addressed by name or by path.

The presets (``deploy/configs/NAME.yaml``) and launch files (``deploy/NAME.yaml``) are package
data of the ``deploy`` package, so an installed TrackGraph finds them wherever it runs: a file
dropped into those folders is registered under its stem when the ``deploy`` package is imported.
``--config paper`` and ``trackgraph launch local`` name them; any argument that is an existing
file, or looks like a path, is a path.
"""

from __future__ import annotations

from pathlib import Path

from shared.config.base import ConfigError
from shared.registry import Registry

PRESETS: Registry[Path] = Registry("config preset", modules=("deploy",))
"""System configs by name: ``oracle``, ``synthetic``, ``classical``, ``paper``, ``onboard``."""

LAUNCH_FILES: Registry[Path] = Registry("launch file", modules=("deploy",))
"""Launch files by name: ``local``, ``robot``, ``gpu-server``, ``base-station``, ``demo``, ..."""


def _resolve(registry: Registry[Path], name_or_path: str | Path, what: str) -> Path:
    text = str(name_or_path)
    path = Path(text).expanduser()
    if path.is_file():
        return path
    looks_like_path = "/" in text or "\\" in text or text.endswith((".yaml", ".yml"))
    if not looks_like_path and text in registry:
        return registry.get(text)
    if looks_like_path:
        raise ConfigError(f"{text}: no such {what} file")
    raise ConfigError(f"{text}: neither a file nor {registry.unknown(text).replace('unknown ', 'a known ')}")


def config_path(name_or_path: str | Path) -> Path:
    """The system config file a ``--config`` argument names: a preset or a path."""
    return _resolve(PRESETS, name_or_path, "config")


def launch_path(name_or_path: str | Path) -> Path:
    """The launch file ``trackgraph launch`` is given: a name or a path."""
    return _resolve(LAUNCH_FILES, name_or_path, "launch")
