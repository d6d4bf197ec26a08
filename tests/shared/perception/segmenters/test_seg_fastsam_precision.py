"""FastSAM in each precision the CPU runs (autocast around ultralytics' predict)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from shared.perception import KeyframeImage
from shared.perception.segmenters import make_segmenter
from shared.perception.segmenters.config import segmenter_config

if importlib.util.find_spec("ultralytics") is None:  # imported through import_ultralytics only
    pytest.skip("needs ultralytics", allow_module_level=True)
torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    from services.models.random_weights import save_random_fastsam

    return save_random_fastsam(tmp_path_factory.mktemp("fastsam") / "FastSAM-s.pt", "s", seed=0, alive=True)


def _segment(weights, precision: str, image: KeyframeImage):
    cfg = segmenter_config(backend="fastsam", weights=str(weights), imgsz=320, conf=0.4, min_area_px=0, precision=precision)
    seg = make_segmenter(cfg, device="cpu")
    return seg, seg.segment(image)


def test_auto_is_fp32_on_the_cpu(weights):
    image = KeyframeImage(frame_index=0, rgb=np.zeros((64, 64, 3), np.uint8))
    assert _segment(weights, "auto", image)[0].precision == "fp32"


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_half_precisions_give_about_the_fp32_masks(weights, precision):
    rgb = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    image = KeyframeImage(frame_index=0, rgb=rgb)
    _, ref = _segment(weights, "fp32", image)
    seg, got = _segment(weights, precision, image)
    assert seg.precision == precision and not seg.fp16  # CPU: autocast, not ultralytics' half
    assert len(ref) > 10
    assert abs(len(got) - len(ref)) <= 0.15 * len(ref)
    # most fp32 masks have a near-equal mask in the half-precision run
    a = ref.masks.reshape(len(ref), -1).astype(np.float32)
    b = got.masks.reshape(len(got), -1).astype(np.float32)
    inter = a @ b.T
    iou = inter / (a.sum(1)[:, None] + b.sum(1)[None] - inter)
    assert np.mean(iou.max(axis=1) > 0.9) > 0.8
