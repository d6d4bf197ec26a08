"""Random-weight stand-ins for the paper's models: the files they write load through the
configured backends, and the overrides point a config at them."""

from __future__ import annotations

import importlib.util

import pytest

from services.models.random_weights import random_weight_overrides
from shared.config import TrackGraphConfig
from shared.config.base import deep_merge, validate

pytest.importorskip("torch")


def _config(**kv) -> TrackGraphConfig:
    doc = {
        "keyframe_vl": {"segmenter": {"backend": "fastsam", "weights": "weights/FastSAM-n.pt"}, "vl": {"backend": "openclip", "model": "ViT-S-32"}},
        "tracker": {"features": {"backend": "dinov3", "loader": "transformers", "short_side": 64}},
    }
    return validate(TrackGraphConfig, deep_merge(doc, kv), "test config")


@pytest.mark.slow
def test_overrides_point_every_model_at_loadable_random_weights(tmp_path, capsys):
    if importlib.util.find_spec("ultralytics") is None:  # imported through import_ultralytics only
        pytest.skip("needs ultralytics")
    pytest.importorskip("open_clip")
    pytest.importorskip("timm")
    from services.cli import main

    cfg = _config()
    over = random_weight_overrides(cfg, tmp_path / "w", max_masks=7)
    seg, vl, feats = over["keyframe_vl"]["segmenter"], over["keyframe_vl"]["vl"], over["tracker"]["features"]
    assert seg["conf"] == 0.0 and seg["max_masks"] == 7 and seg["weights"].endswith("FastSAM-n-random.pt")
    assert vl["weights"].endswith("open_clip_ViT-S-32-random.bin") and feats["loader"] == "timm"
    written = sorted(p.name for p in (tmp_path / "w").iterdir())
    assert written == ["FastSAM-n-random.pt", "dinov3_vits16plus_timm.pth", "open_clip_ViT-S-32-random.bin"]
    # a second call reuses the files
    mtimes = {p: p.stat().st_mtime_ns for p in (tmp_path / "w").iterdir()}
    assert random_weight_overrides(cfg, tmp_path / "w", max_masks=7) == over
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "w").iterdir()} == mtimes

    import yaml

    path = tmp_path / "random.yaml"
    path.write_text(yaml.safe_dump(deep_merge(cfg.model_dump(mode="json"), over)))
    assert main(["models", "check", "--config", str(path), "--json"]) == 0
    import json

    models = json.loads(capsys.readouterr().out)["models"]
    assert {m["role"] for m in models} == {"segmenter", "vl_encoder", "dense_features"}
    assert all(m["loads"] for m in models), models


def test_only_the_configured_real_backends_get_weights(tmp_path):
    cfg = _config(keyframe_vl={"segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}}, tracker={"features": {"backend": "classical"}})
    assert random_weight_overrides(cfg, tmp_path) == {}
    assert not tmp_path.joinpath("w").exists()


def test_a_weights_name_without_a_scale_is_an_error(tmp_path):
    cfg = _config(keyframe_vl={"segmenter": {"weights": "weights/FastSAM-q.pt"}, "vl": {"backend": "simulated"}}, tracker={"features": {"backend": "classical"}})
    with pytest.raises(ValueError, match=r"keyframe_vl\.segmenter\.weights: 'weights/FastSAM-q.pt' names no FastSAM scale"):
        random_weight_overrides(cfg, tmp_path)
