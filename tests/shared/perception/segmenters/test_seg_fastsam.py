"""FastSAM through ultralytics and through an ONNX export, on a random-weight model of the real
architecture (YOLOv8-seg with one class; FastSAM-x is the x scale, n keeps the tests fast).
Nothing is downloaded: the checkpoint is built here and loaded through the same code path as
real weights."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from shared.perception import KeyframeImage, Masks
from shared.perception.segmenters import make_segmenter
from shared.perception.segmenters.config import SegmenterBackend, segmenter_config
from shared.perception.segmenters.fastsam import import_ultralytics
from shared.perception.segmenters.fastsam_onnx import export_fastsam_onnx

if importlib.util.find_spec("ultralytics") is None or importlib.util.find_spec("onnxruntime") is None:
    pytest.skip("needs ultralytics and onnxruntime", allow_module_level=True)

IMGSZ = 128
CONF = 0.3
"""The random head below scores anchors all over (0, 1); this keeps about half of them."""


def save_tiny_fastsam(path, seed: int = 0):
    """A FastSAM-style checkpoint (YOLOv8n-seg, nc=1, random weights) saved the way ultralytics
    saves its own: the pickled half-precision module under "model", with train_args."""
    import_ultralytics()
    import torch
    from ultralytics.nn.tasks import SegmentationModel, yaml_model_load

    torch.manual_seed(seed)
    spec = yaml_model_load("yolov8n-seg.yaml")  # ships inside ultralytics: no download
    spec["nc"] = 1
    model = SegmentationModel(spec, ch=3, nc=1, verbose=False)
    model.task = "segment"
    # PyTorch's default init shrinks activations layer by layer until the head sees ~1e-11 and
    # every anchor of a level gets the same prior score. He init keeps them alive, so scores
    # spread, thresholds and NMS order mean something and no ties hang on rounding.
    for module in model.modules():
        if isinstance(module, torch.nn.Conv2d) and module.weight.requires_grad:  # not the fixed DFL conv
            torch.nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
    # Still faint at the head: scale its last layers up to logits of order one, so mask
    # thresholds at zero are not decided by rounding either.
    head = model.model[-1]
    with torch.no_grad():
        for conv in (seq[-1] for seq in head.cv3):
            torch.nn.init.normal_(conv.weight, 0.0, 40.0)
            torch.nn.init.constant_(conv.bias, -1.5)
        for conv in (seq[-1] for seq in head.cv4):
            conv.weight.mul_(100.0)
        for conv in (seq[-1] for seq in head.cv2):  # box sides: a few strides, varying by anchor
            torch.nn.init.normal_(conv.weight, 0.0, 30.0)
            torch.nn.init.constant_(conv.bias, 1.0)
    torch.save({"model": model.half(), "ema": None, "train_args": {"task": "segment", "imgsz": IMGSZ}}, path)
    return path


@pytest.fixture(scope="module")
def tiny_pt(tmp_path_factory):
    return save_tiny_fastsam(tmp_path_factory.mktemp("fastsam") / "tiny-fastsam.pt")


@pytest.fixture(scope="module")
def tiny_onnx(tiny_pt, tmp_path_factory):
    """A static square export: the tests below check its fixed-size letterbox (the dynamic
    default is in test_seg_fastsam_onnx_parity.py)."""
    return export_fastsam_onnx(tiny_pt, tmp_path_factory.mktemp("onnx") / "tiny-fastsam.onnx", IMGSZ, dynamic=False)


@pytest.fixture(scope="module")
def square_image():
    from seg_room import render_room

    return render_room(IMGSZ, IMGSZ)


def _cfg(weights, backend="fastsam", **kw):
    base = dict(conf=CONF, iou=0.7, imgsz=IMGSZ, min_area_px=0, max_area_frac=1.0, max_masks=300)
    base.update(kw)
    return segmenter_config(backend=backend, weights=str(weights), **base)


def _check_masks(out: Masks, h: int, w: int, cfg: SegmenterBackend):
    assert isinstance(out, Masks)
    assert out.masks.dtype == bool and out.masks.shape[1:] == (h, w)
    assert out.boxes.dtype == np.float32 and out.boxes.shape == (len(out), 4)
    assert out.scores.dtype == np.float32 and out.scores.shape == (len(out),)
    assert len(out) <= cfg.max_masks
    assert (np.diff(out.scores) <= 0).all()
    area = out.masks.sum(axis=(1, 2))
    assert (area >= max(cfg.min_area_px, 1)).all() and (area <= cfg.max_area_frac * h * w).all()


@pytest.mark.parametrize("backend", ["fastsam", "fastsam_onnx"])
def test_missing_weights_name_the_path(tmp_path, backend):
    missing = tmp_path / "weights" / "FastSAM-x.pt"
    with pytest.raises(FileNotFoundError, match=str(missing.name)) as err:
        make_segmenter(segmenter_config(backend=backend, weights=str(missing)))
    assert str(missing) in str(err.value)


def test_fastsam_backend_on_random_weights(tiny_pt, room):
    loose = _cfg(tiny_pt)
    out = make_segmenter(loose).segment(room)
    _check_masks(out, *room.rgb.shape[:2], loose)
    assert len(out) > 0
    strict = _cfg(tiny_pt, min_area_px=3000, max_area_frac=0.3, max_masks=5)
    filtered = make_segmenter(strict).segment(room)
    _check_masks(filtered, *room.rgb.shape[:2], strict)
    assert len(filtered) < len(out)


def test_onnx_backend_on_random_weights(tiny_onnx, room):
    cfg = _cfg(tiny_onnx, backend="fastsam_onnx", min_area_px=200, max_masks=10)
    out = make_segmenter(cfg).segment(room)
    _check_masks(out, *room.rgb.shape[:2], cfg)
    assert len(out) > 0


def test_onnx_raw_outputs_match_torch(tiny_pt, tiny_onnx, square_image):
    import torch

    from shared.perception.segmenters.fastsam import load_fastsam

    seg = make_segmenter(_cfg(tiny_onnx, backend="fastsam_onnx"))
    _, out0, protos = seg.raw(square_image.rgb)
    from shared.perception.segmenters import yolo_post

    lb = yolo_post.plan_letterbox(square_image.rgb.shape[:2], (IMGSZ, IMGSZ), auto=False, stride=32)
    x = torch.from_numpy(yolo_post.letterbox_image(square_image.rgb, lb))
    model = load_fastsam(tiny_pt).model.float().eval()
    with torch.no_grad():
        (t_out0, t_protos), _ = model(x)
    for ours, ref in ((out0, t_out0.numpy()), (protos, t_protos.numpy())):
        assert ours.shape == ref.shape
        rel = np.abs(ours - ref).max() / np.abs(ref).max()
        assert rel < 1e-3, rel


def _matched_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each mask of ``a``, the best IoU with a mask of ``b``."""
    fa = a.reshape(len(a), -1).astype(np.float32)
    fb = b.reshape(len(b), -1).astype(np.float32)
    inter = fa @ fb.T
    union = fa.sum(1)[:, None] + fb.sum(1)[None, :] - inter
    return (inter / np.maximum(union, 1)).max(axis=1)


@pytest.mark.parametrize("retina", [True, False])
def test_numpy_post_processing_matches_ultralytics(tiny_pt, tiny_onnx, square_image, retina):
    """A square image gets the same letterbox on both paths (none), so both backends must agree."""
    ref = make_segmenter(_cfg(tiny_pt, retina_masks=retina)).segment(square_image)
    ours = make_segmenter(_cfg(tiny_onnx, backend="fastsam_onnx", retina_masks=retina)).segment(square_image)
    assert len(ref) > 5
    assert abs(len(ref) - len(ours)) <= max(1, len(ref) // 50)
    n = min(len(ref), len(ours))
    np.testing.assert_allclose(ours.scores[:n], ref.scores[:n], atol=1e-4)
    iou = _matched_iou(ref.masks, ours.masks)
    assert np.median(iou) > 0.99 and (iou > 0.9).mean() > 0.95, np.sort(iou)[:5]
    same = (ours.masks[:n] == ref.masks[:n]).all(axis=(1, 2))
    np.testing.assert_allclose(ours.boxes[:n][same], ref.boxes[:n][same])


def test_non_square_image_same_letterbox(tiny_pt, tiny_onnx, room):
    """A 4:3 image letterboxed to the square ONNX input, against ultralytics told to do the
    same (``rect=False``): identical masks and scores."""
    from shared.perception.segmenters.base import finalize
    from shared.perception.segmenters.fastsam import load_fastsam

    cfg = _cfg(tiny_onnx, backend="fastsam_onnx")
    ours = make_segmenter(cfg).segment(room)
    result = load_fastsam(tiny_pt).predict(
        np.ascontiguousarray(room.rgb[:, :, ::-1]), imgsz=IMGSZ, conf=CONF, iou=0.7, retina_masks=True,
        max_det=300, rect=False, verbose=False, device="cpu",
    )[0]
    ref = finalize(result.masks.data.bool().numpy(), result.boxes.conf.numpy(), cfg)
    assert len(ref) > 5
    assert abs(len(ref) - len(ours)) <= max(1, len(ref) // 50)
    iou = _matched_iou(ref.masks, ours.masks)
    assert np.median(iou) > 0.99 and (iou > 0.9).mean() > 0.95


@pytest.mark.slow
def test_dynamic_export_letterboxes_like_the_pt_path(tiny_pt, tmp_path, room):
    """A dynamic-shape export is letterboxed to the minimal stride rectangle, like .pt weights."""
    onnx = export_fastsam_onnx(tiny_pt, tmp_path / "dyn.onnx", IMGSZ, dynamic=True)
    seg = make_segmenter(_cfg(onnx, backend="fastsam_onnx"))
    assert seg.dynamic
    ours = seg.segment(room)
    ref = make_segmenter(_cfg(tiny_pt)).segment(room)
    assert len(ref) > 5 and abs(len(ref) - len(ours)) <= max(1, len(ref) // 50)
    iou = _matched_iou(ref.masks, ours.masks)
    assert np.median(iou) > 0.99


def test_onnx_input_is_grey_padded(tiny_onnx):
    seg = make_segmenter(_cfg(tiny_onnx, backend="fastsam_onnx"))
    img = KeyframeImage(frame_index=0, rgb=np.zeros((64, 128, 3), np.uint8))
    lb, out0, protos = seg.raw(img.rgb)
    assert lb.input_hw == (IMGSZ, IMGSZ) and (lb.top, lb.left) == (32, 0)
    assert out0.shape[:2] == (1, 4 + 1 + 32) and protos.shape == (1, 32, IMGSZ // 4, IMGSZ // 4)
