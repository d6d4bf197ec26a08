"""OpenCLIP and CLIP-ONNX backends on random weights, loaded the way real weights are.

A real OpenCLIP architecture is built with random weights, its state dict saved to a file,
and the encoders are made by ``make_vl_encoder`` from that file: this proves the loading,
preprocessing, batching, shapes and ONNX parity, though not the accuracy.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from shared.perception import KeyframeImage, Masks
from shared.perception.encoders import make_vl_encoder
from shared.perception.encoders.config import vl_config
from shared.perception.encoders.weights import resolve_checkpoint

open_clip = pytest.importorskip("open_clip")
torch = pytest.importorskip("torch")

ARCH = "ViT-S-32"
"""A registered OpenCLIP architecture small enough for CPU tests (384-d, 12 layers)."""

TEXTS = ["a chair", "a red sofa next to a window", "lamp", "picture frame"]


def _save_random(arch: str, path) -> None:
    torch.manual_seed(0)
    model = open_clip.create_model(arch, pretrained=None)
    torch.save(model.state_dict(), path)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    path = tmp_path_factory.mktemp("clip") / "random_vit_s32.bin"
    _save_random(ARCH, path)
    return path


@pytest.fixture(scope="module")
def encoder(weights):
    return make_vl_encoder(vl_config(backend="openclip", model=ARCH, weights=str(weights), batch_size=3))


@pytest.fixture(scope="module")
def onnx_dir(weights, tmp_path_factory):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from shared.perception.encoders.clip_onnx import export_clip_onnx

    return export_clip_onnx(ARCH, weights, tmp_path_factory.mktemp("clip_onnx"))


def _keyframe(h: int = 120, w: int = 160, seed: int = 0) -> tuple[KeyframeImage, Masks]:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    rgb[20:70, 30:90] = (200, 40, 40)
    rects = [(20, 70, 30, 90), (0, 120, 0, 160), (100, 120, 140, 160), (5, 9, 5, 150), (40, 110, 100, 104)]
    masks = np.zeros((len(rects), h, w), bool)
    for j, (y0, y1, x0, x1) in enumerate(rects):
        masks[j, y0:y1, x0:x1] = True
    boxes = np.array([[x0, y0, x1, y1] for y0, y1, x0, x1 in rects], np.float32)
    return KeyframeImage(frame_index=3, rgb=rgb), Masks(masks, boxes, np.ones(len(rects), np.float32))


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_openclip_shapes_norms_and_name(encoder):
    image, masks = _keyframe()
    assert encoder.name == f"openclip:{ARCH}"
    assert encoder.dim == 384
    crops = encoder.encode_crops(image, masks)
    assert crops.shape == (len(masks), 384) and crops.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(crops, axis=1), 1.0, atol=1e-5)
    text = encoder.encode_text(TEXTS)
    assert text.shape == (len(TEXTS), 384) and text.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(text, axis=1), 1.0, atol=1e-5)
    whole = encoder.encode_image(image.rgb)
    assert whole.shape == (384,) and abs(np.linalg.norm(whole) - 1.0) < 1e-5
    assert encoder.encode_crops(image, Masks.empty(120, 160)).shape == (0, 384)
    assert encoder.encode_text([]).shape == (0, 384)


def test_openclip_batches_match_single_crops(encoder):
    image, masks = _keyframe(seed=1)
    batched = encoder.encode_crops(image, masks)  # batch_size 3: a full batch and a partial one
    encoder.batch_size = 1
    try:
        single = encoder.encode_crops(image, masks)
    finally:
        encoder.batch_size = 3
    np.testing.assert_allclose(batched, single, atol=1e-5)


def test_openclip_view_is_the_whole_frame_through_the_image_tower(encoder):
    image, _ = _keyframe(seed=4)
    view = encoder.encode_view(image)
    assert view.shape == (384,) and view.dtype == np.float32 and abs(np.linalg.norm(view) - 1.0) < 1e-5
    np.testing.assert_array_equal(view, encoder.encode_image(image.rgb))
    other, _ = _keyframe(seed=5)
    assert not np.allclose(view, encoder.encode_view(other))


def test_numpy_preprocessing_matches_open_clip_transform(encoder):
    from PIL import Image

    from shared.perception.encoders.clip_onnx import clip_preprocess

    pp = encoder.model.visual.preprocess_cfg
    rng = np.random.default_rng(2)
    for h, w in [(224, 224), (37, 500), (500, 37), (1, 3), (225, 224), (301, 299), (64, 64)]:
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        ours = clip_preprocess(rgb, pp["size"], pp["mean"], pp["std"], pp["interpolation"], pp["resize_mode"])
        theirs = encoder.preprocess(Image.fromarray(rgb)).numpy()
        assert ours.shape == theirs.shape == (3, 224, 224)
        np.testing.assert_allclose(ours, theirs, atol=1e-5)


def test_checkpoint_folder_resolves_to_its_weights_file(tmp_path, weights):
    (tmp_path / "open_clip_pytorch_model.bin").symlink_to(weights)
    assert resolve_checkpoint(tmp_path, ARCH).name == weights.name
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="holds none"):
        resolve_checkpoint(empty, ARCH)


@pytest.mark.parametrize("backend", ["openclip", "clip_onnx"])
def test_missing_weights_name_the_path(tmp_path, backend):
    missing = tmp_path / "nowhere" / "open_clip_vit_h14.bin"
    with pytest.raises(FileNotFoundError) as err:
        make_vl_encoder(vl_config(backend=backend, model="ViT-H-14", weights=str(missing)))
    assert str(missing) in str(err.value)
    if backend == "openclip":
        assert "laion/CLIP-ViT-H-14-laion2B-s32B-b79K" in str(err.value)


def test_unknown_architecture_is_refused(weights):
    with pytest.raises(ValueError, match="unknown OpenCLIP architecture"):
        make_vl_encoder(vl_config(backend="openclip", model="ViT-Nope", weights=str(weights)))
    with pytest.raises(ValueError, match="built-in name"):
        make_vl_encoder(vl_config(backend="openclip", model="hf-hub:laion/x", weights=str(weights)))


@pytest.mark.slow
def test_onnx_export_agrees_with_torch(encoder, onnx_dir):
    meta = json.loads((onnx_dir / "clip_onnx.json").read_text())
    assert meta["arch"] == ARCH and meta["dim"] == 384 and meta["image_size"] == [224, 224]
    onnx = make_vl_encoder(vl_config(backend="clip_onnx", model=ARCH, weights=str(onnx_dir), batch_size=2))
    assert onnx.name == encoder.name and onnx.dim == encoder.dim
    image, masks = _keyframe(seed=3)
    a, b = onnx.encode_crops(image, masks), encoder.encode_crops(image, masks)
    assert a.shape == b.shape == (len(masks), 384)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    assert _rel_err(a, b) < 1e-3
    assert _rel_err(onnx.encode_text(TEXTS), encoder.encode_text(TEXTS)) < 1e-3
    assert _rel_err(onnx.encode_text(TEXTS[:1]), encoder.encode_text(TEXTS[:1])) < 1e-3  # batch of one
    assert _rel_err(onnx.encode_image(image.rgb), encoder.encode_image(image.rgb)) < 1e-3


@pytest.mark.slow
def test_onnx_view_is_the_whole_frame_through_the_image_tower(encoder, onnx_dir):
    onnx = make_vl_encoder(vl_config(backend="clip_onnx", model=ARCH, weights=str(onnx_dir)))
    image, _ = _keyframe(seed=4)
    view = onnx.encode_view(image)
    assert view.shape == (384,) and view.dtype == np.float32 and abs(np.linalg.norm(view) - 1.0) < 1e-5
    np.testing.assert_array_equal(view, onnx.encode_image(image.rgb))
    assert _rel_err(view, encoder.encode_view(image)) < 1e-3


@pytest.mark.slow
def test_onnx_export_refuses_another_architecture(onnx_dir):
    with pytest.raises(ValueError, match="exported from"):
        make_vl_encoder(vl_config(backend="clip_onnx", model="ViT-B-32", weights=str(onnx_dir)))


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("TRACKGRAPH_TEST_VIT_H14") != "1",
    reason="ViT-H-14 on CPU takes 65-130 s and about 9 GB of memory; set TRACKGRAPH_TEST_VIT_H14=1 to run it",
)
def test_paper_vit_h14_loads_through_the_same_path(tmp_path):
    """The paper's ViT-H-14 (about 1B parameters, 4 GB of fp32 weights) on random weights."""
    t0 = time.perf_counter()
    path = tmp_path / "random_vit_h14.bin"
    _save_random("ViT-H-14", path)
    enc = make_vl_encoder(vl_config(backend="openclip", model="ViT-H-14", weights=str(path), batch_size=2))
    path.unlink()
    image, masks = _keyframe()
    feats = enc.encode_crops(image, Masks(masks.masks[:2], masks.boxes[:2], masks.scores[:2]))
    text = enc.encode_text(TEXTS[:2])
    assert enc.dim == 1024 and feats.shape == (2, 1024) and text.shape == (2, 1024)
    np.testing.assert_allclose(np.linalg.norm(feats, axis=1), 1.0, atol=1e-5)
    print(f"ViT-H-14 build, save, load and encode: {time.perf_counter() - t0:.1f} s")
