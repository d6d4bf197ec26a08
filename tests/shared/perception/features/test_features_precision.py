"""DINOv3 in each precision the CPU runs, through the factory a config uses."""

from __future__ import annotations

import numpy as np
import pytest

from shared.perception.features import make_dense_features
from shared.perception.features.config import dense_features_config

torch = pytest.importorskip("torch")
pytest.importorskip("timm")


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    from services.models.random_weights import save_random_dinov3_timm

    return save_random_dinov3_timm(tmp_path_factory.mktemp("dino") / "dinov3_timm.pth")


def _features(weights, precision: str):
    cfg = dense_features_config(backend="dinov3", loader="timm", weights=str(weights), short_side=64, precision=precision)
    return make_dense_features(cfg, device="cpu")


def test_auto_is_fp32_on_the_cpu(weights):
    assert _features(weights, "auto").precision == "fp32"


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_half_precisions_run_under_autocast_and_agree_with_fp32(weights, precision):
    rgb = np.random.default_rng(3).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    ref, half = _features(weights, "fp32"), _features(weights, precision)
    assert half.precision == precision
    # autocast: the weights stay fp32, so one model serves every precision
    assert next(half.model.parameters()).dtype == torch.float32
    a, b = half(rgb), ref(rgb)
    assert a.dtype == torch.float32 and a.shape == b.shape
    torch.testing.assert_close(a.norm(dim=-1), torch.ones(a.shape[:2]), atol=1e-4, rtol=0)
    assert float((a * b).sum(-1).min()) > 0.999
    # what propagation uses: patch-to-patch similarities
    fa, fb = a.reshape(-1, a.shape[-1]), b.reshape(-1, b.shape[-1])
    assert float((fa @ fa.T - fb @ fb.T).abs().max()) < 5e-3


def test_an_unknown_precision_is_refused(weights):
    from shared.perception.features.dinov3 import Dinov3Features, load_patch_tokens

    with pytest.raises(ValueError, match="precision 'int8'"):
        Dinov3Features(load_patch_tokens("timm", weights), 64, "cpu", "int8")
