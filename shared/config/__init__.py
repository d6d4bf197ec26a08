"""Typed, strict configs for every service, loaded from YAML in ``deploy/``.

The names below are imported on first use (PEP 562): the backend sections of
``keyframe_vl`` and ``tracker`` come from :mod:`shared.perception`, whose configs import
:mod:`shared.config.base` in turn, so an eager import here would be a circle whichever side
is imported first.
"""

from __future__ import annotations

import importlib

_WHERE = {
    "CodecConfig": "shared.config.transport",
    "ConfigError": "shared.config.base",
    "FusionConfig": "shared.config.fusion",
    "KeyframeVLConfig": "shared.config.keyframe_vl",
    "QueryConfig": "shared.config.query",
    "SourceConfig": "shared.config.source",
    "StrictModel": "shared.config.base",
    "TrackGraphConfig": "shared.config.root",
    "TrackerConfig": "shared.config.tracker",
    "TransportConfig": "shared.config.transport",
    "dump_yaml": "shared.config.base",
    "load_config": "shared.config.root",
    "load_model": "shared.config.base",
    "save_resolved": "shared.config.base",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
