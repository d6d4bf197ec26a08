"""``--set KEY=VALUE`` reads VALUE by the type of the field it sets: text fields get the text as
written (YAML 1.1 would make ``off`` a boolean), the others what YAML reads."""

from __future__ import annotations

import pytest

from shared.config import ConfigError, TrackGraphConfig
from shared.config.base import validate
from shared.config.overrides import apply_sets


def _config(*sets: str) -> TrackGraphConfig:
    return validate(TrackGraphConfig, apply_sets({}, sets, TrackGraphConfig), "test")


@pytest.mark.parametrize("word", ["on", "off", "auto"])
def test_a_literal_of_words_takes_the_word(word: str) -> None:
    assert apply_sets({}, [f"fusion.refuse={word}"], TrackGraphConfig) == {"fusion": {"refuse": word}}
    assert _config(f"fusion.refuse={word}").fusion.refuse == word


def test_a_literal_still_refuses_a_word_it_does_not_list() -> None:
    with pytest.raises(ConfigError, match="fusion.refuse"):
        _config("fusion.refuse=yes")


@pytest.mark.parametrize("text", ["off", "no", "yes", "null", "123", "[a, b]", "a: b: c"])
def test_a_plain_text_field_takes_the_text_as_written(text: str) -> None:
    assert _config(f"ros2.output.frame_id={text}").ros2.output.frame_id == text


def test_a_quoted_text_is_unquoted_as_yaml_does() -> None:
    assert _config("ros2.output.frame_id='robot one'").ros2.output.frame_id == "robot one"


def test_an_optional_text_field_takes_null_as_none_and_words_as_text() -> None:
    assert _config("ros2.input.odom_frame=null").ros2.input.odom_frame is None
    assert _config("ros2.input.odom_frame=~").ros2.input.odom_frame is None
    assert _config("ros2.input.odom_frame=no").ros2.input.odom_frame == "no"
    assert _config("ros2.input.odom_frame=base_link").ros2.input.odom_frame == "base_link"


@pytest.mark.parametrize(("text", "want"), [("off", False), ("no", False), ("false", False), ("on", True), ("yes", True), ("true", True)])
def test_a_bool_field_keeps_the_yaml_booleans(text: str, want: bool) -> None:
    assert _config(f"transport.shared_memory={text}").transport.shared_memory is want


def test_an_int_field_takes_a_number() -> None:
    assert _config("ros2.link.max_payload_bytes=1024").ros2.link.max_payload_bytes == 1024
    with pytest.raises(ConfigError, match="max_payload_bytes"):
        _config("ros2.link.max_payload_bytes=lots")


def test_a_float_field_takes_a_number() -> None:
    assert _config("fusion.tsdf.voxel_size=0.05").fusion.tsdf.voxel_size == pytest.approx(0.05)
    assert _config("fusion.tsdf.voxel_size=1").fusion.tsdf.voxel_size == 1.0


def test_a_list_field_takes_a_yaml_list() -> None:
    cfg = _config("transport.connect=[tcp/10.0.0.1:7447, tcp/10.0.0.2:7447]")
    assert cfg.transport.connect == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    assert _config("ros2.link.connect=[]").ros2.link.connect == []


def test_a_field_of_a_backend_section_is_read_by_that_backend_type() -> None:
    cfg = _config("keyframe_vl.segmenter.backend=fastsam_onnx", "keyframe_vl.segmenter.weights=off")
    assert cfg.keyframe_vl.segmenter.backend == "fastsam_onnx"
    assert cfg.keyframe_vl.segmenter.weights == "off"


def test_a_bad_yaml_value_of_a_non_text_field_is_still_an_error() -> None:
    with pytest.raises(ConfigError, match=r"--set transport.connect: .* is not a YAML value"):
        apply_sets({}, ["transport.connect=[a, b"], TrackGraphConfig)


def test_the_command_line_takes_refuse_off() -> None:
    from services.cli import main

    assert main(["config", "check", "paper", "--set", "fusion.refuse=off"]) == 0
