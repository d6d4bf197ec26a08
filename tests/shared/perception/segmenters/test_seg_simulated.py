"""The simulated segmenter: exact at zero noise, plausibly wrong at default noise, repeatable."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from seg_room import render_room, truth

from shared.datasets.ground_truth import GroundTruthError
from shared.eval.segmenter import mean_best_iou
from shared.perception import KeyframeImage
from shared.perception.segmenters import make_segmenter
from shared.perception.segmenters.config import SegmenterBackend, segmenter_config
from shared.perception.segmenters.simulated import SimulatedSegmenter
from shared.perception.segmenters.simulated_config import SimulatedSegmenterNoise

ZERO = SimulatedSegmenterNoise(
    boundary_jitter_px=0, split_prob=0, merge_prob=0, miss_below_px=0, spurious_per_frame=0
)


TRUTH = truth(render_room())
"""The room fixture's ids as frames 0-31: the segmenter reads them by frame index."""


def simulated(cfg: SegmenterBackend) -> SimulatedSegmenter:
    return SimulatedSegmenter(cfg, TRUTH)


def _gt_masks(instances, cfg):
    ids, area = np.unique(instances[instances >= 0], return_counts=True)
    ok = (area >= cfg.min_area_px) & (area <= cfg.max_area_frac * instances.size)
    return {tuple(np.flatnonzero(instances.ravel() == i)) for i in ids[ok]}


@pytest.mark.parametrize("min_area_px", [0, 1500])
def test_zero_noise_reproduces_ground_truth(room, min_area_px):
    cfg = segmenter_config(backend="simulated", noise=ZERO, min_area_px=min_area_px, max_area_frac=1.0)
    out = simulated(cfg).segment(room)
    got = {tuple(np.flatnonzero(m.ravel())) for m in out.masks}
    assert got == _gt_masks(room.instances, cfg)
    assert len(got) == len(out)
    assert out.masks.shape[1:] == room.instances.shape
    assert (np.diff(out.scores) <= 0).all()


def test_default_noise_is_within_band(room):
    seg = simulated(segmenter_config(backend="simulated"))
    values = []
    for i in range(12):
        out = seg.segment(dataclasses.replace(room, frame_index=i))
        values.append(mean_best_iou(out.masks, room.instances)[0])
    mean = float(np.mean(values))
    assert 0.6 <= mean <= 0.95, values
    assert min(values) < 1.0  # the noise does something


def test_deterministic_per_seed_and_frame(room):
    cfg = segmenter_config(backend="simulated", noise=SimulatedSegmenterNoise(spurious_per_frame=2.0, split_prob=0.3))
    a = simulated(cfg).segment(room)
    b = simulated(cfg).segment(room)
    np.testing.assert_array_equal(a.masks, b.masks)
    np.testing.assert_array_equal(a.scores, b.scores)
    other_frame = simulated(cfg).segment(dataclasses.replace(room, frame_index=7))
    other_seed = simulated(cfg.model_copy(update={"seed": 1})).segment(room)
    assert not np.array_equal(a.scores, other_frame.scores)
    assert not np.array_equal(a.scores, other_seed.scores)


def test_each_noise_kind_acts(room):
    base = ZERO.model_copy()

    def run(**noise):
        cfg = segmenter_config(backend="simulated", noise=base.model_copy(update=noise), min_area_px=0, max_area_frac=1.0)
        return simulated(cfg).segment(room)

    n_gt = len(np.unique(room.instances))
    assert len(run(split_prob=1.0)) > n_gt
    assert len(run(merge_prob=1.0)) < n_gt
    small = int(np.unique(room.instances, return_counts=True)[1].min())
    assert len(run(miss_below_px=small + 1)) < n_gt
    # The share of the image, unless an absolute threshold is set.
    assert len(run(miss_below_px=None, miss_below_frac=(small + 1) / room.instances.size)) < n_gt
    assert len(run(miss_below_px=None, miss_below_frac=(small - 0.5) / room.instances.size)) == n_gt
    assert len(run(miss_below_px=0, miss_below_frac=1.0)) == n_gt
    assert len(run(spurious_per_frame=20.0)) > n_gt
    jittered = run(boundary_jitter_px=2.0)
    assert len(jittered) == n_gt
    assert 0.7 < mean_best_iou(jittered.masks, room.instances)[0] < 1.0


def test_ground_truth_comes_from_its_source_not_the_image(room, tmp_path):
    """No ground truth rides on the image: without a source the segmenter refuses to be made,
    naming the config key, and a keyframe its source does not know is refused by index."""
    with pytest.raises(GroundTruthError, match="keyframe_vl.segmenter.ground_truth is not set"):
        make_segmenter(segmenter_config(backend="simulated"))
    with pytest.raises(GroundTruthError, match="keyframe_vl.segmenter.ground_truth: .* is not a folder"):
        make_segmenter(segmenter_config(backend="simulated", ground_truth=str(tmp_path / "nowhere")))
    with pytest.raises(GroundTruthError, match="no instances/"):
        make_segmenter(segmenter_config(backend="simulated", ground_truth=str(tmp_path)))
    seg = simulated(segmenter_config(backend="simulated"))
    with pytest.raises(GroundTruthError, match="keyframe 99: .*frame_index 99"):
        seg.segment(KeyframeImage(frame_index=99, rgb=room.rgb))
    with pytest.raises(GroundTruthError, match="keyframe 0: .*64x48"):
        seg.segment(KeyframeImage(frame_index=0, rgb=room.rgb[:48, :64]))
    # A plain KeyframeImage of a known frame is enough: the ids come from the source.
    assert len(seg.segment(KeyframeImage(frame_index=3, rgb=room.rgb))) > 0
