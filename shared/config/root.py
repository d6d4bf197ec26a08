"""The whole system's config: one file configures every service."""

from __future__ import annotations

import re
from pathlib import Path

from pydantic import Field, field_validator

from shared.config.base import StrictModel, load_model
from shared.config.fusion import FusionConfig
from shared.config.keyframe_vl import KeyframeVLConfig
from shared.config.query import QueryConfig
from shared.config.source import SourceConfig
from shared.config.tracker import TrackerConfig
from shared.config.transport import TransportConfig

ROBOT_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


class TrackGraphConfig(StrictModel):
    """Every tunable of every service. Defaults are the paper's (docs/method.md, "Parameters")."""

    robot_id: str = "robot0"
    """Namespace of this robot's keys: ``trackgraph/<robot_id>/...``."""
    transport: TransportConfig = Field(default_factory=TransportConfig)
    """Zenoh session and wire encoding."""
    source: SourceConfig = Field(default_factory=SourceConfig)
    """Data source."""
    keyframe_vl: KeyframeVLConfig = Field(default_factory=KeyframeVLConfig)
    """Keyframe segmentation and CLIP."""
    tracker: TrackerConfig = Field(default_factory=TrackerConfig)
    """Source-track propagation."""
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    """TSDF, segments and the scene graph."""
    query: QueryConfig = Field(default_factory=QueryConfig)
    """Retrieval."""

    @field_validator("robot_id")
    @classmethod
    def _robot_id(cls, v: str) -> str:
        if not ROBOT_ID.match(v):
            raise ValueError("robot_id must be 1-64 characters of letters, digits, '_' or '-'")
        return v


def load_config(path: str | Path) -> TrackGraphConfig:
    """Load a system config from YAML; missing keys take the paper's defaults."""
    return load_model(TrackGraphConfig, path)
