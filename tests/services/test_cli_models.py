"""CLI contract of `models check`, `export-onnx` and `eval segmenter` (docs/architecture.md,
"Command-line contract")."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.cli import main

REPO = Path(__file__).resolve().parents[2]
PRESETS = REPO / "deploy" / "configs"


def test_models_check_reports_missing_weights(capsys):
    assert main(["models", "check", "--config", str(PRESETS / "paper.yaml"), "--no-load", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False
    assert set(out["missing"]) == {"weights/FastSAM-x.pt", "weights/open_clip_vit_h14.bin", "weights/dinov3_vits16plus"}
    assert {m["role"] for m in out["models"]} == {"segmenter", "vl_encoder", "dense_features"}
    assert all(m["source"] for m in out["models"])


def test_models_check_weightless_config_is_ok(capsys):
    assert main(["models", "check", "--config", str(PRESETS / "classical.yaml"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"ok": True, "missing": [], "models": []}


@pytest.mark.slow
def test_models_check_loads_a_real_architecture(tmp_path, capsys):
    from services.models.random_weights import save_random_fastsam

    pt = save_random_fastsam(tmp_path / "FastSAM-n.pt", "n")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"keyframe_vl:\n  segmenter:\n    backend: fastsam\n    weights: {pt}\n  vl:\n    backend: simulated\ntracker:\n  features:\n    backend: classical\n")
    assert main(["models", "check", "--config", str(cfg), "--json"]) == 0
    (entry,) = json.loads(capsys.readouterr().out)["models"]
    assert entry["present"] and entry["loads"] and entry["error"] is None

    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint")
    cfg.write_text(cfg.read_text().replace(str(pt), str(broken)))
    assert main(["models", "check", "--config", str(cfg), "--json"]) == 1
    (entry,) = json.loads(capsys.readouterr().out)["models"]
    assert entry["present"] and entry["loads"] is False and entry["error"]


def test_export_onnx_needs_a_torch_backend(capsys):
    assert main(["export-onnx", "--config", str(PRESETS / "classical.yaml"), "--out", "/tmp/unused"]) != 0
    assert "nothing to export" in capsys.readouterr().err


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out)
    return out


@pytest.mark.slow
def test_eval_segmenter_classical_on_small(small_scene, capsys):
    assert main(["eval", "segmenter", "--seq", str(small_scene), "--config", str(PRESETS / "classical.yaml"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["objects"] > 20
    assert out["mean_best_iou"] >= 0.6
