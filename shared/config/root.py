"""The whole system's config: one file configures every service."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

from pydantic import Field, field_validator

from shared.config.base import ConfigError, StrictModel, load_model, read_yaml, validate
from shared.config.fusion import FusionConfig
from shared.config.keyframe_vl import KeyframeVLConfig
from shared.config.query import QueryConfig
from shared.config.ros2 import Ros2Config
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
    ros2: Ros2Config = Field(default_factory=Ros2Config)
    """ROS 2 on the wire: the robot's topics in (``trackgraph source --ros2``), markers and
    queries out (``trackgraph serve ros2``)."""

    @field_validator("robot_id")
    @classmethod
    def _robot_id(cls, v: str) -> str:
        if not ROBOT_ID.match(v):
            raise ValueError("robot_id must be 1-64 characters of letters, digits, '_' or '-'")
        return v

    def ground_truth_fields(self) -> list[tuple[str, str | None]]:
        """(config key, value) of the ``ground_truth`` folder of every simulated backend this
        config uses: the simulated segmenter, the simulated VL encoder, the ground_truth tracker."""
        kvl = self.keyframe_vl
        fields = []
        if kvl.segmenter.backend == "simulated":
            fields.append(("keyframe_vl.segmenter.ground_truth", kvl.segmenter.ground_truth))
        if kvl.vl.backend == "simulated":
            fields.append(("keyframe_vl.vl.ground_truth", kvl.vl.ground_truth))
        if self.tracker.mode == "ground_truth":
            fields.append(("tracker.ground_truth", self.tracker.ground_truth))
        return fields

    def with_ground_truth(self, seq_dir: str | Path) -> TrackGraphConfig:
        """This config with every unset ``ground_truth`` of :meth:`ground_truth_fields` set to
        the sequence ``seq_dir`` (absolute, since the resolved config is saved with the map and
        read from elsewhere), when the sequence is synthetic (has ``instances/``). A
        ``ground_truth`` that is set must be a folder: ConfigError naming the key otherwise."""
        seq = Path(seq_dir)
        data = self.model_dump()
        changed = False
        for key, value in self.ground_truth_fields():
            if value is not None:
                if not Path(value).expanduser().is_dir():
                    raise ConfigError(f"{key}: {value} is not a folder (the simulated backend needs a synthetic sequence with instances/)")
                continue
            if (seq / "instances").is_dir():
                *parents, leaf = key.split(".")
                node = data
                for part in parents:
                    node = node[part]
                node[leaf] = str(seq.resolve())
                changed = True
        return TrackGraphConfig.model_validate(data) if changed else self


def load_config(path: str | Path, sets: Sequence[str] = ()) -> TrackGraphConfig:
    """Load a system config: a YAML file, or a preset by name (``paper``; shared/presets.py),
    with ``sets`` (``KEY=VALUE`` items, shared/config/overrides.py) laid on top; missing keys
    take the paper's defaults. Errors name the file, the key and, for ``--set``, the item."""
    from shared.config.overrides import apply_sets
    from shared.presets import config_path

    file = config_path(path)
    if not sets:
        return load_model(TrackGraphConfig, file)
    data = apply_sets(read_yaml(file), sets, TrackGraphConfig)
    return validate(TrackGraphConfig, data, f"{file} with --set {' '.join(sets)}")
