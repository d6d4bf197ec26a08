"""``trackgraph map`` with the ``paper`` config on random weights in each precision the CPU
runs (issue 20). The paper's models are swapped for the smallest of their families (FastSAM-s,
OpenCLIP ViT-S-32, DINOv3 at 224 px) so three maps fit in CI; the code path is the paper
config's: FastSAM, OpenCLIP and DINOv3 through their torch backends."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import yaml

from services.cli import main
from services.models.random_weights import random_weight_overrides
from shared.config import TrackGraphConfig
from shared.config.base import deep_merge

if importlib.util.find_spec("ultralytics") is None:  # imported through import_ultralytics only
    pytest.skip("needs ultralytics", allow_module_level=True)
pytest.importorskip("open_clip")
pytest.importorskip("timm")

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    from shared.synth import run_synth

    tmp = tmp_path_factory.mktemp("precision")
    seq = tmp / "small"
    run_synth("small", 0, seq)
    doc = yaml.safe_load((ROOT / "deploy" / "configs" / "paper.yaml").read_text())
    doc["keyframe_vl"]["segmenter"].update(weights="weights/FastSAM-s.pt", imgsz=320)
    doc["keyframe_vl"]["vl"].update(model="ViT-S-32")
    doc["tracker"]["features"].update(short_side=224)
    doc["tracker"]["keyframe_interval"] = 5
    doc = deep_merge(doc, random_weight_overrides(TrackGraphConfig.model_validate(doc), tmp / "weights", max_masks=8))
    return tmp, seq, doc


@pytest.mark.parametrize("precision", ["fp32", "bf16", "fp16"])
def test_the_paper_config_maps_in_each_cpu_precision(setup, precision, capsys):
    tmp, seq, doc = setup
    doc = deep_merge(doc, {
        "keyframe_vl": {"device": "cpu", "segmenter": {"precision": precision}, "vl": {"precision": precision}},
        "tracker": {"device": "cpu", "features": {"precision": precision}},
    })  # fmt: skip
    cfg = tmp / f"paper_{precision}.yaml"
    cfg.write_text(yaml.safe_dump(doc))
    out = tmp / f"map_{precision}"
    assert main(["map", str(seq), "--config", str(cfg), "--out", str(out), "--json", "--max-frames", "10"]) == 0
    run = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert run["frames"] == 10
    assert run["backends"] == {"tracker": "propagation", "dense_features": "dinov3", "segmenter": "fastsam", "vl_encoder": "openclip"}
    assert run["precision"] == {"dense_features": precision, "segmenter": precision, "vl_encoder": precision}
    assert run["segments"] > 0
