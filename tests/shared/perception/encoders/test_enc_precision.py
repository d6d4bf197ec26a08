"""OpenCLIP precisions, crop modes and the on-device crop path, on random ViT-S-32 weights."""

from __future__ import annotations

import numpy as np
import pytest

from shared.perception import KeyframeImage, Masks
from shared.perception.encoders import make_vl_encoder
from shared.perception.encoders.config import vl_config
from shared.perception.encoders.crops import pad_to_square, padded_boxes, padded_crops, shape_crops

torch = pytest.importorskip("torch")
pytest.importorskip("open_clip")

ARCH = "ViT-S-32"


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    from services.models.random_weights import save_random_openclip

    return save_random_openclip(tmp_path_factory.mktemp("clip") / "random_vit_s32.bin", ARCH)


def _encoder(weights, **cfg):
    return make_vl_encoder(vl_config(backend="openclip", model=ARCH, weights=str(weights), **cfg), device="cpu")


def _keyframe(seed: int = 0) -> tuple[KeyframeImage, Masks]:
    h, w = 120, 160
    rgb = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    rects = [(20, 70, 30, 90), (0, 120, 0, 160), (5, 9, 5, 150), (40, 110, 100, 104)]  # incl. 4x145 and 70x4
    masks = np.zeros((len(rects), h, w), bool)
    for j, (y0, y1, x0, x1) in enumerate(rects):
        masks[j, y0:y1, x0:x1] = True
    boxes = np.array([[x0, y0, x1, y1] for y0, y1, x0, x1 in rects], np.float32)
    return KeyframeImage(frame_index=0, rgb=rgb), Masks(masks, boxes, np.ones(len(rects), np.float32))


def _cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a * b).sum(axis=1)


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_each_precision_runs_on_the_cpu_close_to_fp32(weights, precision):
    image, masks = _keyframe()
    ref = _encoder(weights, precision="fp32")
    enc = _encoder(weights, precision=precision)
    assert enc.precision == precision and ref.precision == "fp32"
    a, b = enc.encode_crops(image, masks), ref.encode_crops(image, masks)
    assert a.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    assert _cos(a, b).min() > 0.999
    assert _cos(enc.encode_text(["a chair", "lamp"]), ref.encode_text(["a chair", "lamp"])).min() > 0.999


def test_auto_precision_is_fp32_on_the_cpu(weights):
    assert _encoder(weights).precision == "fp32"


def test_pad_square_keeps_every_column_of_an_elongated_crop():
    # A 6x165 crop whose columns are numbered: centre crop keeps 6 of them, padding all 165.
    crop = np.zeros((6, 165, 3), np.uint8)
    crop[:, :, 0] = np.arange(165, dtype=np.uint8)[None]
    squared = pad_to_square(crop, (122, 116, 104))
    assert squared.shape == (165, 165, 3)
    rows = np.flatnonzero((squared != (122, 116, 104)).any(axis=(1, 2)) | (squared[:, :, 0] < 122).any(axis=1))
    assert rows.min() == (165 - 6) // 2 and rows.max() == (165 - 6) // 2 + 5
    np.testing.assert_array_equal(squared[(165 - 6) // 2, :, 0], np.arange(165))
    assert np.all(squared[0] == (122, 116, 104))
    assert shape_crops([crop], "center_crop", (0, 0, 0))[0] is crop


def test_what_clip_sees_under_each_crop_mode(weights):
    """Through OpenCLIP's own transform: a 6x165 crop whose red channel numbers its columns.
    pad_square shows CLIP every column; centre crop only the middle few."""
    enc = _encoder(weights)
    from PIL import Image

    crop = np.zeros((6, 165, 3), np.uint8)
    crop[:, :, 0] = np.arange(165, dtype=np.uint8)[None]
    crop[:, :, 1] = 255  # marks the object's pixels against the fill colour
    mean, std = np.asarray(enc.mean)[:, None, None], np.asarray(enc.std)[:, None, None]
    seen = {}
    for mode in ("pad_square", "center_crop"):
        x = enc.preprocess(Image.fromarray(shape_crops([crop], mode, enc.fill)[0])).numpy()
        pixels = np.rint((x * std + mean) * 255)
        red = pixels[0][pixels[1] > 250]  # object pixels only
        seen[mode] = (red.min(), red.max())
    lo, hi = seen["pad_square"]
    assert lo <= 2 and hi >= 162  # both ends of the crop reach CLIP
    lo, hi = seen["center_crop"]
    assert lo >= 75 and hi <= 89  # the middle 6 columns (79-84) and their resampling blur


@pytest.mark.parametrize("mode", ["pad_square", "center_crop"])
def test_device_crop_path_equals_the_pil_path(weights, mode):
    image, masks = _keyframe(1)
    pil = _encoder(weights, crop_mode=mode)
    dev = _encoder(weights, crop_mode=mode)
    dev.tensor_crops = True
    assert not pil.tensor_crops  # the CPU default is OpenCLIP's own PIL transform
    from PIL import Image

    boxes = padded_boxes(masks.masks, masks.boxes, pil.crop_padding)
    x_dev = dev.crop_pixels(image.rgb, boxes)
    crops = shape_crops(padded_crops(image.rgb, masks.masks, pil.crop_padding, masks.boxes), mode, pil.fill)
    x_pil = torch.stack([pil.preprocess(Image.fromarray(c)) for c in crops])
    assert x_dev.shape == x_pil.shape == (len(masks), 3, *pil.size)
    # PIL resamples in fixed point: a few edge pixels differ by some levels, the rest by at most one
    diff = (x_dev - x_pil).abs()
    assert float(diff.mean()) < 0.01
    assert float((diff > 0.05).float().mean()) < 0.01
    assert _cos(dev.encode_crops(image, masks), pil.encode_crops(image, masks)).min() > 0.9999


def test_unknown_crop_mode_is_refused():
    with pytest.raises(ValueError, match="crop_mode"):
        vl_config(crop_mode="stretch")
