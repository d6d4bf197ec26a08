"""Typed, strict configs for every service, loaded from YAML in ``deploy/``."""

from shared.config.base import ConfigError, StrictModel, dump_yaml, load_model, save_resolved
from shared.config.fusion import FusionConfig
from shared.config.keyframe_vl import KeyframeVLConfig
from shared.config.query import QueryConfig
from shared.config.root import TrackGraphConfig, load_config
from shared.config.source import SourceConfig
from shared.config.tracker import TrackerConfig
from shared.config.transport import CodecConfig, TransportConfig

__all__ = [
    "CodecConfig",
    "ConfigError",
    "FusionConfig",
    "KeyframeVLConfig",
    "QueryConfig",
    "SourceConfig",
    "StrictModel",
    "TrackGraphConfig",
    "TrackerConfig",
    "TransportConfig",
    "dump_yaml",
    "load_config",
    "load_model",
    "save_resolved",
]
