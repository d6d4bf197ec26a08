"""An all-ONNX map equals the torch one (issue 20): ``trackgraph map`` on the ``small`` synthetic
preset with FastSAM as its .pt checkpoint and as ``trackgraph export-onnx``'s export of it.

Both runs use the same random-weight FastSAM-s (``random_weight_overrides``: ``alive``, every
detection taken, 24 masks a keyframe); the square export the ONNX path had before gave other
masks on every 240x320 frame. Simulated CLIP and classical dense features keep the run short and
leave the segmenter the only difference between the two maps.
"""

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
pytest.importorskip("onnxruntime")

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]
FRAMES = 48
"""Six keyframes at the synthetic config's interval of 8: enough segments to compare, about a
minute a map on two cores."""


def _map(seq: Path, config: Path, out: Path, capsys) -> dict:
    assert main(["map", str(seq), "--config", str(config), "--out", str(out), "--json", "--max-frames", str(FRAMES)]) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_onnx_map_has_the_torch_maps_segments(tmp_path, capsys):
    from shared.synth import run_synth

    seq = tmp_path / "small"
    run_synth("small", 0, seq)
    doc = yaml.safe_load((ROOT / "deploy" / "configs" / "synthetic.yaml").read_text())
    doc["keyframe_vl"]["segmenter"] = {"backend": "fastsam", "weights": "weights/FastSAM-s.pt"}
    doc = deep_merge(doc, random_weight_overrides(TrackGraphConfig.model_validate(doc), tmp_path / "weights"))
    pt_cfg = tmp_path / "pt.yaml"
    pt_cfg.write_text(yaml.safe_dump(doc))

    assert main(["export-onnx", "--config", str(pt_cfg), "--out", str(tmp_path / "onnx"), "--only", "segmenter"]) == 0
    exported = tmp_path / "onnx" / "fastsam.onnx"
    assert f"segmenter: {exported}" in capsys.readouterr().out
    doc["keyframe_vl"]["segmenter"].update(backend="fastsam_onnx", weights=str(exported))
    onnx_cfg = tmp_path / "onnx.yaml"
    onnx_cfg.write_text(yaml.safe_dump(doc))

    torch_run = _map(seq, pt_cfg, tmp_path / "map_pt", capsys)
    onnx_run = _map(seq, onnx_cfg, tmp_path / "map_onnx", capsys)
    assert torch_run["backends"]["segmenter"] == "fastsam" and onnx_run["backends"]["segmenter"] == "fastsam_onnx"
    print(f"segments: torch {torch_run['segments']} in {torch_run['seconds']:.0f} s, ONNX {onnx_run['segments']} in {onnx_run['seconds']:.0f} s")
    assert torch_run["frames"] == onnx_run["frames"] == FRAMES
    assert torch_run["segments"] > 10
    assert abs(onnx_run["segments"] - torch_run["segments"]) <= 0.05 * torch_run["segments"]
