"""Which text encoder scores a saved map: MiniLM for simulated maps, the map's own CLIP
otherwise (a 1024-d CLIP map cannot be scored in MiniLM's 384-d space)."""

from __future__ import annotations

import numpy as np
import pytest

from services.query.offline import MapTextEncoder, map_text_encoder
from shared.config import TrackGraphConfig
from shared.config.base import validate


def test_a_simulated_map_is_scored_with_minilm(tmp_path):
    from shared.text.minilm import MiniLMTextEncoder

    cfg = validate(TrackGraphConfig, {"keyframe_vl": {"vl": {"backend": "simulated"}}}, "test")
    assert isinstance(map_text_encoder(tmp_path, cfg), MiniLMTextEncoder)


def test_a_clip_map_is_scored_with_its_own_text_tower(tmp_path):
    open_clip = pytest.importorskip("open_clip")
    torch = pytest.importorskip("torch")
    torch.manual_seed(0)
    weights = tmp_path / "vit_s32.bin"
    torch.save(open_clip.create_model("ViT-S-32", pretrained=None).state_dict(), weights)
    cfg = validate(TrackGraphConfig, {"keyframe_vl": {"vl": {"backend": "openclip", "model": "ViT-S-32", "weights": str(weights)}}}, "test")
    (tmp_path / "map").mkdir()
    (tmp_path / "map" / "config.yaml").write_text(
        f"keyframe_vl:\n  vl:\n    backend: openclip\n    model: ViT-S-32\n    weights: {weights}\n"
    )
    enc = map_text_encoder(tmp_path / "map")
    assert isinstance(enc, MapTextEncoder) and "ViT-S-32" in enc.name
    rows = enc.encode(["a chair", "a red armchair"])
    assert rows.shape == (2, enc.dim)
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-4)
    assert map_text_encoder(tmp_path, cfg).dim == enc.dim
