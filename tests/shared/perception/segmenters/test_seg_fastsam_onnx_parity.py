"""The ``fastsam_onnx`` backend on ``trackgraph export-onnx``'s FastSAM export gives the masks of
the project's own .pt segmenter (issue 20): same letterbox (ultralytics' predict letterboxes a
480x640 frame to 768x1024 at imgsz 1024, not to a square), same post-processing.

A random-weight FastSAM-s (the real architecture, ``alive`` so that masks appear) stands in for
the real weights, which cannot be downloaded here. Random weights are far more sensitive to the
input than trained ones (a square export finds other masks on every frame), so equal masks here
mean the two paths feed the network the same input and decode it the same way.
"""

from __future__ import annotations

import importlib.util
import logging

import numpy as np
import pytest

from shared.perception import Masks
from shared.perception.segmenters import make_segmenter
from shared.perception.segmenters.config import SegmenterBackend, segmenter_config
from shared.perception.segmenters.fastsam_onnx import export_fastsam_onnx

if importlib.util.find_spec("ultralytics") is None or importlib.util.find_spec("onnxruntime") is None:
    pytest.skip("needs ultralytics and onnxruntime", allow_module_level=True)

pytestmark = pytest.mark.slow

IMGSZ = 1024
"""The configured default: the size at which the .pt and square ONNX letterboxes differ."""
CONF = 0.2
"""The random head's best scores lie around 0.2-0.3: this keeps a hundred or more masks."""
SHAPES = [(480, 640), (240, 320), (340, 600)]
"""4:3 at the sensor's size and at the synthetic presets' size, and a wide 30:17 frame whose
letterbox keeps grey padding (608x1024, 14 rows above and below; 680x1200 letterboxes the same
and only costs more mask pixels)."""
MIN_IOU = 0.99


def _cfg(weights, backend: str, **kw) -> SegmenterBackend:
    base = dict(conf=CONF, iou=0.9, imgsz=IMGSZ, min_area_px=100, max_area_frac=0.95, max_masks=300)
    base.update(kw)
    return segmenter_config(backend=backend, weights=str(weights), **base)


@pytest.fixture(scope="module")
def random_pt(tmp_path_factory):
    from services.models.random_weights import save_random_fastsam

    return save_random_fastsam(tmp_path_factory.mktemp("fastsam") / "FastSAM-s-random.pt", "s", seed=0, alive=True)


@pytest.fixture(scope="module")
def exported(random_pt, tmp_path_factory):
    """What ``trackgraph export-onnx`` writes for a FastSAM config, by default."""
    from services.models.export import export_all
    from shared.config import TrackGraphConfig

    cfg = TrackGraphConfig.model_validate({"keyframe_vl": {"segmenter": {"backend": "fastsam", "weights": str(random_pt), "imgsz": IMGSZ}}})
    return export_all(cfg, tmp_path_factory.mktemp("export"), only={"segmenter"})["segmenter"]


@pytest.fixture(scope="module")
def segmenters(random_pt, exported):
    """(.pt, ONNX) segmenters per ``retina_masks``, loaded once."""
    return {
        retina: (make_segmenter(_cfg(random_pt, "fastsam", retina_masks=retina)), make_segmenter(_cfg(exported, "fastsam_onnx", retina_masks=retina)))
        for retina in (True, False)
    }


@pytest.fixture(scope="module")
def images():
    from seg_room import render_room

    return {shape: render_room(shape[1], shape[0]) for shape in SHAPES}


def _iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    fa = a.reshape(len(a), -1).astype(np.float32)
    fb = b.reshape(len(b), -1).astype(np.float32)
    inter = fa @ fb.T
    union = fa.sum(1)[:, None] + fb.sum(1)[None, :] - inter
    return inter / np.maximum(union, 1)


def _greedy_match(iou: np.ndarray) -> np.ndarray:
    """IoU of each pair of a one-to-one matching that takes the best remaining pair first."""
    iou = iou.copy()
    out = []
    for _ in range(min(iou.shape)):
        i, j = np.unravel_index(np.argmax(iou), iou.shape)
        out.append(iou[i, j])
        iou[i, :] = -1
        iou[:, j] = -1
    return np.asarray(out)


def _parity(ref: Masks, ours: Masks) -> tuple[int, int, float]:
    iou = _greedy_match(_iou_matrix(ref.masks, ours.masks))
    return len(ref), len(ours), float(iou.min()) if len(iou) else 1.0


def test_export_is_dynamic_and_takes_the_pt_rectangle(segmenters, images):
    """The default export accepts the .pt path's 768x1024 letterbox of a 480x640 frame."""
    seg = segmenters[True][1]
    assert seg.dynamic, seg.session.get_inputs()[0].shape
    lb, out0, protos = seg.raw(images[(480, 640)].rgb)
    assert lb.input_hw == (768, 1024) and (lb.top, lb.left) == (0, 0)
    assert out0.shape[:2] == (1, 4 + 1 + 32) and protos.shape == (1, 32, 768 // 4, 1024 // 4)
    wide = seg.raw(images[(340, 600)].rgb)[0]
    assert wide.input_hw == (608, 1024) and (wide.top, wide.left) == (14, 0)


@pytest.mark.parametrize("retina", [True, False], ids=["retina", "input_scale"])
@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_onnx_masks_equal_the_pt_segmenter(segmenters, images, shape, retina):
    pt, onnx = segmenters[retina]
    image = images[shape]
    ref, ours = pt.segment(image), onnx.segment(image)
    n_ref, n_ours, min_iou = _parity(ref, ours)
    print(f"{shape} retina={retina}: {n_ref} .pt masks, {n_ours} ONNX masks, min matched IoU {min_iou:.4f}")
    assert n_ref >= 20, "the random checkpoint should give many masks"
    assert n_ours == n_ref
    assert min_iou >= MIN_IOU
    np.testing.assert_allclose(np.sort(ours.scores), np.sort(ref.scores), atol=1e-3)


def test_static_square_export_still_segments_with_a_warning(random_pt, images, tmp_path, caplog):
    """An export fixed at 320x320 pads a 240x320 frame to it (the .pt path to 256x320): it
    must still give masks of the frame's size, and say once that they differ from the .pt path's."""
    onnx = export_fastsam_onnx(random_pt, tmp_path / "square.onnx", 320, dynamic=False)
    seg = make_segmenter(_cfg(onnx, "fastsam_onnx", imgsz=320))
    assert not seg.dynamic and seg.new_hw == (320, 320)
    image = images[(240, 320)]
    with caplog.at_level(logging.WARNING, logger="shared.perception.segmenters.fastsam_onnx"):
        lb = seg.raw(image.rgb)[0]
        out = seg.segment(image)
    assert lb.input_hw == (320, 320) and (lb.top, lb.left) == (40, 0)
    assert out.masks.shape[1:] == (240, 320)
    warned = [r.getMessage() for r in caplog.records if "differ from the .pt path" in r.getMessage()]
    assert len(warned) == 1 and "240x320 frames" in warned[0] and "to 256x320" in warned[0], warned
    # A square frame gets the same letterbox on both paths: no warning for it.
    caplog.clear()
    square = np.full((160, 160, 3), 90, np.uint8)
    with caplog.at_level(logging.WARNING, logger="shared.perception.segmenters.fastsam_onnx"):
        assert seg.raw(square)[0].input_hw == (320, 320)
    assert not [r for r in caplog.records if "differ from the .pt path" in r.getMessage()]

