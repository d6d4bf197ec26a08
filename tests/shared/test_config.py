"""TrackGraphConfig: the paper's defaults, documented fields, and YAML errors that name
the file and the dotted key."""

from __future__ import annotations

import typing
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from shared.config import (
    CodecConfig,
    ConfigError,
    FusionConfig,
    KeyframeVLConfig,
    QueryConfig,
    SourceConfig,
    TrackerConfig,
    TrackGraphConfig,
    TransportConfig,
    dump_yaml,
    load_config,
    save_resolved,
)
from shared.config.fusion import GraphConfig, ReidConfig, SegmentsConfig, TSDFConfig
from shared.config.tracker import AssociationConfig, PropagationConfig
from shared.perception.encoders.clip_config import ClipOnnxConfig, OpenClipConfig
from shared.perception.encoders.simulated_config import SimulatedVLConfig
from shared.perception.features.classical_config import ClassicalFeaturesConfig
from shared.perception.features.dinov3_config import Dinov3Config, Dinov3OnnxConfig
from shared.perception.segmenters.classical_config import ClassicalSegmenterConfig
from shared.perception.segmenters.fastsam_config import FastSAMConfig, FastSAMOnnxConfig
from shared.perception.segmenters.simulated_config import (
    SimulatedSegmenterConfig,
    SimulatedSegmenterNoise,
)


def write(tmp_path: Path, text: str, name: str = "trackgraph.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ---------------------------------------------------------------- defaults


def test_paper_defaults() -> None:
    cfg = TrackGraphConfig()

    tracker = cfg.tracker
    assert tracker.keyframe_interval == 24  # K_f
    assert tracker.features.short_side == 720
    assoc = tracker.association
    assert (assoc.w_iou, assoc.w_feat) == (0.5, 0.5)
    assert assoc.iou_min == 0.15
    assert assoc.score_min == 0.35
    assert assoc.ema == 0.2  # eta
    prop = tracker.propagation
    assert prop.context_frames == 7
    assert prop.window_radius == 12
    assert prop.topk == 5
    assert prop.temperature == 0.2

    tsdf = cfg.fusion.tsdf
    assert tsdf.alpha_p == 0.25
    assert tsdf.beta_p == 0.1
    assert tsdf.voxel_size == 0.03
    assert tsdf.hypotheses == 4  # K
    assert tsdf.active_window_m == 8.0

    seg = cfg.fusion.segments
    assert seg.min_vertices == 20
    assert seg.min_shared == 5
    assert seg.theta_rho == 0.75
    assert seg.theta_sim == 0.8

    reid = cfg.fusion.reid
    assert reid.enabled is True
    assert reid.r_nn == 0.10
    assert (reid.lambda_o, reid.lambda_a) == (0.5, 0.5)
    assert reid.o_min == 0.42
    assert reid.cos_min == 0.70
    assert reid.j_min == 0.65

    assert cfg.query.gallery == "max"


def test_integer_defaults_are_ints() -> None:
    cfg = TrackGraphConfig()
    for value in (
        cfg.tracker.keyframe_interval,
        cfg.tracker.features.short_side,
        cfg.tracker.propagation.context_frames,
        cfg.tracker.propagation.window_radius,
        cfg.tracker.propagation.topk,
        cfg.fusion.tsdf.hypotheses,
        cfg.fusion.segments.min_vertices,
        cfg.fusion.segments.min_shared,
    ):
        assert type(value) is int


def _nested_models(annotation: object) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _nested_models(arg)]


def walk_models(root: type[BaseModel]) -> set[type[BaseModel]]:
    seen: set[type[BaseModel]] = set()
    todo = [root]
    while todo:
        model = todo.pop()
        if model in seen:
            continue
        seen.add(model)
        for field in model.model_fields.values():
            todo.extend(_nested_models(field.annotation))
        registry = getattr(model, "__registry__", None)  # a backend section: every backend's model
        if registry is not None:
            todo.extend(m for _, m in registry.items())
    return seen


def test_walk_reaches_every_config_model() -> None:
    models = walk_models(TrackGraphConfig)
    assert models >= {
        TrackGraphConfig, TransportConfig, CodecConfig, SourceConfig, KeyframeVLConfig,
        FastSAMConfig, FastSAMOnnxConfig, ClassicalSegmenterConfig, SimulatedSegmenterConfig,
        SimulatedSegmenterNoise, OpenClipConfig, ClipOnnxConfig, SimulatedVLConfig, TrackerConfig,
        Dinov3Config, Dinov3OnnxConfig, ClassicalFeaturesConfig, PropagationConfig, AssociationConfig, FusionConfig, TSDFConfig,
        SegmentsConfig, ReidConfig, GraphConfig, QueryConfig,
    }


def test_every_field_is_documented() -> None:
    undocumented = [
        f"{model.__name__}.{name}"
        for model in walk_models(TrackGraphConfig)
        for name, field in model.model_fields.items()
        if not (field.description or "").strip()
    ]
    assert undocumented == []


def test_every_model_is_documented() -> None:
    for model in walk_models(TrackGraphConfig):
        assert (model.__doc__ or "").strip(), model.__name__


# ---------------------------------------------------------------- loading


def test_empty_file_gives_defaults(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, "")) == TrackGraphConfig()


def test_partial_file_overrides_only_its_keys(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, "fusion:\n  tsdf:\n    voxel_size: 0.05\nquery:\n  gallery: mean\n"))
    assert cfg.fusion.tsdf.voxel_size == 0.05
    assert cfg.query.gallery == "mean"
    expected = TrackGraphConfig()
    expected.fusion.tsdf.voxel_size = 0.05
    expected.query.gallery = "mean"
    assert cfg == expected


def test_misspelt_key_names_file_and_dotted_key(tmp_path: Path) -> None:
    path = write(tmp_path, "fusion:\n  tsdf:\n    voxel_sze: 0.05\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert str(path) in msg
    assert "fusion.tsdf.voxel_sze" in msg
    assert "unknown key" in msg


def test_misspelt_top_level_key(tmp_path: Path) -> None:
    path = write(tmp_path, "fusoin:\n  tsdf: {}\n")
    with pytest.raises(ConfigError, match="fusoin") as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_negative_voxel_size_names_the_key(tmp_path: Path) -> None:
    path = write(tmp_path, "fusion:\n  tsdf:\n    voxel_size: -0.03\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert str(path) in msg
    assert "fusion.tsdf.voxel_size" in msg
    assert "-0.03" in msg


def test_each_problem_on_its_own_line(tmp_path: Path) -> None:
    path = write(tmp_path, "fusion:\n  tsdf:\n    voxel_size: -1\n    hypotheses: 0\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    lines = str(info.value).splitlines()
    assert any("fusion.tsdf.voxel_size" in line for line in lines)
    assert any("fusion.tsdf.hypotheses" in line for line in lines)
    assert all(line.startswith(f"{path}: ") for line in lines)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("tracker:\n  association:\n    w_iou: 0.7\n", ["tracker.association", "w_iou + w_feat"]),
        ("tracker:\n  association:\n    w_iou: 0.3\n    w_feat: 0.3\n", ["tracker.association"]),
        ("fusion:\n  reid:\n    lambda_o: 0.9\n", ["fusion.reid", "lambda_o + lambda_a"]),
        ("fusion:\n  tsdf:\n    depth_min: 6.0\n", ["fusion.tsdf", "depth_min"]),
        ("robot_id: 'robot 0'\n", ["robot_id"]),
        ("transport:\n  connect: ['127.0.0.1:7447']\n", ["transport.connect"]),
        ("query:\n  gallery: median\n", ["query.gallery"]),
        ("fusion: 3\n", ["fusion"]),
    ],
)
def test_invalid_values_are_config_errors(tmp_path: Path, text: str, words: list[str]) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert str(path) in msg
    for word in words:
        assert word in msg


def test_weights_summing_to_one_are_accepted(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, "tracker:\n  association:\n    w_iou: 0.7\n    w_feat: 0.3\n"))
    assert (cfg.tracker.association.w_iou, cfg.tracker.association.w_feat) == (0.7, 0.3)


@pytest.mark.parametrize("text", ["- a\n- b\n", "42\n", "just a string\n"])
def test_not_a_mapping_names_the_file(tmp_path: Path, text: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("text", ["fusion: [1, 2\n", "fusion:\n  tsdf: {voxel_size: 0.03\n", "a: b: c\n", "\tfusion: 1\n"])
def test_invalid_yaml_names_the_file(tmp_path: Path, text: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_python_tags_are_not_constructed(tmp_path: Path) -> None:
    path = write(tmp_path, "robot_id: !!python/object/apply:os.getcwd []\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_missing_file_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "nope" / "missing.yaml"
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_directory_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path)
    assert str(tmp_path) in str(info.value)


def test_non_utf8_file_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes(b"robot_id: caf\xe9\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)


# ---------------------------------------------------------------- saving


def test_save_resolved_round_trips_defaults(tmp_path: Path) -> None:
    cfg = TrackGraphConfig()
    path = save_resolved(cfg, tmp_path / "run" / "resolved.yaml")
    assert path == tmp_path / "run" / "resolved.yaml"
    assert load_config(path) == cfg


def test_save_resolved_round_trips_a_modified_config(tmp_path: Path) -> None:
    cfg = TrackGraphConfig(robot_id="spot-2")
    cfg.fusion.tsdf.voxel_size = 0.05
    cfg.tracker.association = AssociationConfig(w_iou=0.25, w_feat=0.75)
    cfg.source.path = "/data/replica/room0"
    cfg.source.max_frames = 100
    cfg.transport.connect = ["tcp/10.0.0.2:7447", "tls/base:7447"]
    cfg.transport.codec.rgb = "jpeg"
    cfg.keyframe_vl.segmenter = SimulatedSegmenterConfig(noise=SimulatedSegmenterNoise(split_prob=0.0))
    cfg.keyframe_vl.segmenter.noise.merge_prob = 0.5
    cfg.query.gallery = "mean"
    path = save_resolved(cfg, tmp_path / "resolved.yaml")
    loaded = load_config(path)
    assert loaded == cfg
    assert loaded != TrackGraphConfig()


def test_saved_yaml_is_fully_resolved(tmp_path: Path) -> None:
    """Every key is written, defaults included, so the run can be reproduced exactly."""
    cfg = TrackGraphConfig()
    data = yaml.safe_load(save_resolved(cfg, tmp_path / "resolved.yaml").read_text())
    assert data == cfg.model_dump(mode="json")
    assert data["fusion"]["tsdf"]["voxel_size"] == 0.03
    assert yaml.safe_load(dump_yaml(cfg)) == data


def test_save_resolved_overwrites_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "resolved.yaml"
    path.write_text("old: content\n")
    save_resolved(TrackGraphConfig(robot_id="r1"), path)
    assert load_config(path).robot_id == "r1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["resolved.yaml"]


def test_assignment_is_validated() -> None:
    cfg = TrackGraphConfig()
    with pytest.raises(ValueError, match="voxel_size"):
        cfg.fusion.tsdf.voxel_size = -1.0
    assert cfg.fusion.tsdf.voxel_size == 0.03
