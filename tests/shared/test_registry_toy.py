"""Adding a backend, a service, a dataset reader or a preset is one registration beside it.

Everything below is registered from this one file, as a new module would register it, and
then found everywhere names are listed: the command line's choices, ``config check`` (which
accepts the toy's fields, refuses others naming the toy, and suggests the nearest), the
launcher and ``trackgraph serve``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import pytest
import yaml

from services.cli import build_parser, main
from services.launch import plan_launch
from services.serve import build_node
from shared.config import load_config
from shared.config.launch import load_launch
from shared.datasets import DATASETS, open_sequence
from shared.perception import Masks
from shared.perception.segmenters.config import SEGMENTERS, SegmenterBackend
from shared.presets import PRESETS
from shared.registry import SERVICES, ServiceEntry


class ToySegmenter:
    """One mask: the pixels brighter than the threshold."""

    name = "toy"

    def __init__(self, cfg: ToySegmenterConfig) -> None:
        self.cfg = cfg

    def segment(self, image) -> Masks:
        bright = image.rgb.mean(axis=2) > 255 * self.cfg.threshold
        h, w = bright.shape
        return Masks(bright[None], np.array([[0, 0, w, h]], np.float32), np.ones(1, np.float32))


class ToySegmenterConfig(SegmenterBackend):
    """A toy segmenter backend."""

    backend: Literal["toy"] = "toy"
    """The toy."""
    threshold: float = 0.5
    """Brightness share above which a pixel is in the mask."""

    def build(self, device: str = "cpu", fp16: bool = False) -> ToySegmenter:
        return ToySegmenter(self)


class ToyNode:
    """What ``trackgraph serve toy`` builds."""

    def __init__(self, cfg, out) -> None:
        self.cfg, self.out = cfg, out


def build_toy(cfg, *, out=None, resume: bool = False) -> ToyNode:
    return ToyNode(cfg, out)


class ToyReader:
    """A dataset reader that only remembers where it was opened."""

    def __init__(self, path) -> None:
        self.root = Path(path)

    @classmethod
    def open(cls, path, config) -> ToyReader:
        return cls(path)


@pytest.fixture
def toys(tmp_path: Path):
    preset = tmp_path / "toy.yaml"
    preset.write_text("keyframe_vl:\n  segmenter:\n    backend: toy\n    threshold: 0.25\n")
    SEGMENTERS.register("toy", ToySegmenterConfig)
    SERVICES.register("toy", ServiceEntry("a toy service", node=f"{__name__}:build_toy", out="file"))
    DATASETS.register("toyset", f"{__name__}:ToyReader")
    PRESETS.register("toy", preset)
    try:
        yield tmp_path
    finally:
        SEGMENTERS.unregister("toy")
        SERVICES.unregister("toy")
        DATASETS.unregister("toyset")
        PRESETS.unregister("toy")


def test_the_toy_segmenter_is_a_config_backend(toys: Path, capsys) -> None:
    cfg = load_config("toy")
    assert isinstance(cfg.keyframe_vl.segmenter, ToySegmenterConfig)
    assert cfg.keyframe_vl.segmenter.threshold == 0.25
    assert isinstance(cfg.keyframe_vl.segmenter.build(), ToySegmenter)
    assert "toy" in SEGMENTERS.names()
    assert main(["config", "check", "toy"]) == 0

    bad = toys / "bad.yaml"
    bad.write_text("keyframe_vl:\n  segmenter:\n    backend: toy\n    threshhold: 0.3\n")
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "keyframe_vl.segmenter.threshhold: unknown key for backend 'toy' (did you mean 'threshold'?)" in err

    bad.write_text("keyframe_vl:\n  segmenter:\n    backend: toi\n")
    assert main(["config", "check", str(bad)]) == 2
    assert "unknown segmenter backend 'toi' (did you mean 'toy'?)" in capsys.readouterr().err
    assert main(["config", "check", "paper", "--set", "keyframe_vl.segmenter.backend=toy", "--set", "keyframe_vl.segmenter.threshold=0.1"]) == 0


def test_the_toy_service_is_served_and_launched(toys: Path) -> None:
    args = build_parser().parse_args(["serve", "toy", "--config", "toy", "--out", str(toys / "toy.rrd")])
    assert args.service == "toy"
    node = build_node("toy", load_config("toy"), out=toys / "toy.rrd")
    assert isinstance(node, ToyNode) and node.out == toys / "toy.rrd"
    with pytest.raises(ValueError, match="needs --out"):
        build_node("toy", load_config("toy"))

    launch = toys / "launch.yaml"
    launch.write_text(yaml.safe_dump({"config": "toy", "services": [{"name": "toy", "args": ["--out", "toy.rrd"]}]}))
    assert [s.name for s in load_launch(launch).services] == ["toy"]
    plan = plan_launch(launch, log_dir=toys / "logs")
    cmd = plan.commands["toy"]
    assert cmd[cmd.index("serve") + 1] == "toy"
    assert "toy" in load_config("toy", ["transport.status_heartbeat=[toy]"]).transport.status_heartbeat


def test_the_toy_dataset_is_a_choice(toys: Path) -> None:
    args = build_parser().parse_args(["map", str(toys), "--config", "toy", "--out", str(toys / "map"), "--dataset", "toyset"])
    assert args.dataset == "toyset"
    assert isinstance(open_sequence(toys, "toyset"), ToyReader)
    assert load_config("toy", ["source.dataset=toyset"]).source.dataset == "toyset"


def test_without_the_toys_nothing_knows_them() -> None:
    for registry, name in ((SEGMENTERS, "toy"), (SERVICES, "toy"), (DATASETS, "toyset"), (PRESETS, "toy")):
        assert name not in registry.names()
    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", "toy"])
