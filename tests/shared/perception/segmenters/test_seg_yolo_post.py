"""The numpy YOLOv8-seg pre/post-processing against the ultralytics and torch functions it
mirrors."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from shared.perception.segmenters import yolo_post
from shared.perception.segmenters.fastsam import import_ultralytics


@pytest.mark.parametrize("shape", [(240, 320), (480, 640), (100, 37), (333, 333), (720, 1280)])
@pytest.mark.parametrize("auto", [False, True])
def test_letterbox_matches_ultralytics(shape, auto):
    if importlib.util.find_spec("ultralytics") is None:
        pytest.skip("needs ultralytics")
    import_ultralytics()
    from ultralytics.data.augment import LetterBox

    rng = np.random.default_rng(sum(shape))
    rgb = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    ref = LetterBox((256, 256), auto=auto, stride=32)(image=rgb)
    lb = yolo_post.plan_letterbox(shape, (256, 256), auto=auto, stride=32)
    ours = yolo_post.letterbox_image(rgb, lb)[0].transpose(1, 2, 0)
    assert ours.shape == ref.shape
    np.testing.assert_array_equal(np.round(ours * 255).astype(np.uint8), ref)


@pytest.mark.parametrize("n_in,n_out", [(32, 128), (80, 240), (96, 64), (7, 7), (128, 37)])
def test_resize_matrix_matches_torch_bilinear(n_in, n_out):
    torch = pytest.importorskip("torch")
    x = np.random.default_rng(0).standard_normal((n_in, 5)).astype(np.float32)
    ref = torch.nn.functional.interpolate(torch.from_numpy(x.T[None, :, :, None].copy()), size=(n_out, 1), mode="bilinear")
    ours = yolo_post.resize_matrix(n_out, n_in) @ x
    np.testing.assert_allclose(ours, ref[0, :, :, 0].numpy().T, atol=1e-5)


def test_nms_matches_torchvision():
    torch = pytest.importorskip("torch")
    torchvision = pytest.importorskip("torchvision")
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 200, (400, 2))
    wh = rng.uniform(5, 60, (400, 2))
    boxes = np.concatenate([xy, xy + wh], axis=1).astype(np.float32)
    scores = rng.random(400).astype(np.float32)
    for thr in (0.3, 0.5, 0.9):
        ref = torchvision.ops.nms(torch.from_numpy(boxes), torch.from_numpy(scores), thr).numpy()
        np.testing.assert_array_equal(yolo_post.nms(boxes, scores, thr), ref)
        # Stopping at max_det keeps the same first boxes (decode's early exit).
        np.testing.assert_array_equal(yolo_post.nms(boxes, scores, thr, max_keep=7), ref[:7])


def test_decode_filters_and_orders():
    # Three anchors: two overlapping boxes and one below the confidence threshold.
    out = np.zeros((1, 4 + 1 + 2, 3), np.float32)
    out[0, :4, 0] = [50, 50, 20, 20]
    out[0, :4, 1] = [51, 50, 20, 20]
    out[0, :4, 2] = [10, 10, 4, 4]
    out[0, 4] = [0.6, 0.9, 0.1]
    out[0, 5:, 1] = [1.0, -1.0]
    det = yolo_post.decode(out, n_masks=2, conf=0.25, iou=0.5, max_det=10)
    np.testing.assert_allclose(det.scores, [0.9])
    np.testing.assert_allclose(det.boxes, [[41, 40, 61, 60]])
    np.testing.assert_allclose(det.coeffs, [[1.0, -1.0]])


def test_scale_boxes_round_trip():
    lb = yolo_post.plan_letterbox((240, 320), (256, 256), auto=False, stride=32)
    assert lb.input_hw == (256, 256) and (lb.top, lb.left) == (32, 0)
    inside = np.array([[0, 32, 256, 224], [128, 128, 192, 160]], np.float32)
    np.testing.assert_allclose(yolo_post.scale_boxes_to_image(inside, lb), [[0, 0, 320, 240], [160, 120, 240, 160]])
