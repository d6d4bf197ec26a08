"""The tracker core over a synthetic sequence (issue 6): late keyframe masks, a keyframe_vl
outage, the per-frame baseline, and the tracking acceptance on the ``small`` and ``revisit``
presets with the simulated segmenter at default noise and classical features
(deploy/configs/synthetic.yaml).

One ``small`` sequence (320 x 240, 120 frames) is generated per module run and shared; each
tracker pass over it takes a few seconds on a 2-core CPU.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pytest

from services.keyframe_vl.core import KeyframeVLCore
from services.mapping import prepare_config
from services.tracker.core import TrackerCore
from shared.config import load_config
from shared.datasets import open_sequence
from shared.eval.tracking import evaluate_track_maps
from shared.messages.frames import Frame, TrackedFrame
from shared.perception.features import make_dense_features

pytestmark = pytest.mark.slow

SYNTHETIC = Path(__file__).resolve().parents[3] / "deploy" / "configs" / "synthetic.yaml"


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> tuple[Path, list[Frame]]:
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out)
    reader = open_sequence(out, "replica")
    return out, [reader.frame(i) for i in range(len(reader))]


@pytest.fixture(scope="module")
def reference(small) -> list[TrackedFrame]:
    """The whole sequence through deploy/configs/synthetic.yaml with masks on time."""
    seq, frames = small
    core, kf = build(seq)
    return run(core, kf, frames)


def build(seq: Path, **tracker: object) -> tuple[TrackerCore, KeyframeVLCore]:
    cfg = prepare_config(load_config(SYNTHETIC), seq)
    if tracker:
        data = cfg.model_dump()
        data["tracker"].update(tracker)
        cfg = type(cfg).model_validate(data)
    cfg = cfg.model_copy(update={"tracker": cfg.tracker.model_copy(update={"device": "cpu"})})
    return TrackerCore(cfg.tracker, make_dense_features(cfg.tracker.features, "cpu")), KeyframeVLCore(cfg.keyframe_vl)


def run(
    core: TrackerCore,
    kf: KeyframeVLCore,
    frames: Iterable[Frame],
    *,
    delay: int = 0,
    drop: range = range(0),
    applied: dict[int, list[int]] | None = None,
) -> list[TrackedFrame]:
    """Frames through the core's protocol. Keyframe masks are applied ``delay`` frames after
    their request (after that frame's begin, before its end, as the node does), and dropped
    altogether for requests made at frame indices in ``drop`` (a keyframe_vl outage).
    ``applied`` receives the track id of every mask of every keyframe corrected."""
    pending: list[tuple[int, int, object]] = []
    out = []
    for k, frame in enumerate(frames):
        req = core.begin_frame(frame)
        if req is not None and req.frame_index not in drop:
            _, masks, _ = kf.segment(req)
            pending.append((k + delay, req.frame_index, masks))
        for item in [p for p in pending if p[0] <= k]:
            pending.remove(item)
            assert core.apply_masks(item[1], item[2])
            if applied is not None:
                applied[item[1]] = list(core.mask_tracks[item[1]])
        out.append(core.end_frame())
    return out


def metrics(tracked: list[TrackedFrame], seq: Path, frames: list[Frame], first: int = 0) -> dict:
    """Track quality against the ground truth, which the sequence's reader gives (no Frame
    carries it)."""
    reader = open_sequence(seq, "replica")
    keys = {t.frame.frame_index for t in tracked if t.keyframe}
    triples = (
        (f.frame_index, t.track_ids, reader.instances(f.frame_index)) for t, f in zip(tracked, frames, strict=True) if f.frame_index >= first
    )
    return evaluate_track_maps(triples, keys)


def test_late_masks_give_the_same_tracks_after_catch_up(small):
    seq, frames = small
    frames = frames[:60]
    core, kf = build(seq)
    ids_timely: dict[int, list[int]] = {}
    timely = run(core, kf, frames, applied=ids_timely)
    late_core, late_kf = build(seq)
    ids_late: dict[int, list[int]] = {}
    late = run(late_core, late_kf, frames, delay=5, applied=ids_late)
    K = core.cfg.keyframe_interval
    assert K > 5, "the delay must stay below the keyframe interval for this test"
    # Every keyframe corrected in both runs (the late run misses the last one) got the same ids.
    assert len(ids_late) == len(ids_timely) - 1 >= 5
    assert ids_late == {k: v for k, v in ids_timely.items() if k in ids_late}
    compared = 0
    for a, b in zip(timely, late, strict=True):
        if a.frame.frame_index % K >= 5:  # masks of the last keyframe applied by now
            np.testing.assert_array_equal(a.track_ids, b.track_ids, err_msg=f"frame {a.frame.frame_index}")
            compared += 1
    assert compared >= len(frames) // 3
    # Before catch-up the late run still shows the previous keyframe's tracks.
    assert not np.array_equal(timely[K + 1].track_ids, late[K + 1].track_ids)


def test_keyframe_outage_loses_no_frame_and_tracks_recover(small, reference):
    seq, frames = small
    core, kf = build(seq)
    K = core.cfg.keyframe_interval
    start = 2 * K
    outage = range(start, start + 50)  # no masks for 50 frames
    tracked = run(core, kf, frames, drop=outage)
    assert [t.frame.frame_index for t in tracked] == [f.frame_index for f in frames]
    for t in tracked:
        assert t.track_ids.shape == t.frame.depth.shape and t.track_ids.dtype == np.int32
    # Propagation carries the tracks through the outage.
    for t in tracked[outage.start : outage.stop]:
        assert not t.keyframe
        assert (t.track_ids >= 0).mean() > 0.5, t.frame.frame_index
    # The first keyframe after it gives back the identities seen before the outage, as the
    # run without an outage keeps them: re-identification, not a fresh start.
    resume = next(k for k, t in enumerate(tracked) if k >= outage.stop and t.keyframe)

    def kept(out: list[TrackedFrame]) -> float:
        now = {int(v) for v in np.unique(out[resume].track_ids) if v >= 0}
        return len(now & seen_before(out, start)) / max(len(now), 1)

    assert kept(tracked) >= kept(reference) - 0.2, (kept(tracked), kept(reference))
    # And tracking after the recovery is about as good as without an outage.
    after, ref_after = metrics(tracked, seq, frames, resume), metrics(reference, seq, frames, resume)
    assert after["gt_coverage"] >= ref_after["gt_coverage"] - 0.1, (after, ref_after)
    assert after["idf1"] >= ref_after["idf1"] - 0.15, (after, ref_after)


def seen_before(tracked: list[TrackedFrame], stop: int) -> set[int]:
    """Track ids present in the output before frame position ``stop``."""
    ids: set[int] = set()
    for t in tracked[:stop]:
        ids.update(int(v) for v in np.unique(t.track_ids) if v >= 0)
    return ids


def test_per_frame_mode_gives_the_same_output_type(small):
    seq, frames = small
    prop_core, kf = build(seq)
    pf_core, _ = build(seq, mode="per_frame")
    prop = run(prop_core, kf, frames[:6])
    per_frame = run(pf_core, kf, frames[:6])
    for a, b in zip(prop, per_frame, strict=True):
        assert type(a) is type(b) is TrackedFrame
        assert a.track_ids.shape == b.track_ids.shape and a.track_ids.dtype == b.track_ids.dtype == np.int32
        assert b.keyframe and all(o.keyframe for o in b.tracks)
    assert not prop[1].keyframe
    # Propagated frames say how sure eq. 1 was of each pixel's track; keyframe masks do not.
    assert prop[0].confidence is None and all(b.confidence is None for b in per_frame)
    conf = prop[1].confidence
    assert conf is not None and conf.shape == prop[1].track_ids.shape and conf.dtype == np.uint8
    assert conf.max() == 255 and conf.min() < 200
    # Identities carry over between consecutive per-frame segmentations.
    shared = set(np.unique(per_frame[0].track_ids)) & set(np.unique(per_frame[1].track_ids))
    assert len(shared - {-1}) >= 0.5 * (len(np.unique(per_frame[0].track_ids)) - 1)


def test_issue_acceptance_on_the_small_preset(small, reference):
    """Issue 6: mean IoU of propagated masks >= 0.6 on non-keyframes, IDF1 >= 0.7 and fewer
    than 1 identity switch per object per 100 frames, simulated segmenter at default noise,
    classical features, against the per-frame ground-truth instance images (measured: mean
    IoU 0.76, IDF1 0.714, 0.46 switches per object per 100 frames)."""
    seq, frames = small
    m = metrics(reference, seq, frames)
    assert m["n_frames"] == 120 and m["n_keyframes"] == 15
    assert m["mean_iou"] >= 0.6, m
    assert m["idf1"] >= 0.7, m
    assert m["id_switches_per_100_frames_per_object"] < 1.0, m


@pytest.mark.timeout(1200)
def test_issue_acceptance_on_the_revisit_preset(tmp_path_factory):
    """The same on the ``revisit`` preset (640 x 480, 600 frames: out of the first room for
    more than 8 m and back), where identities must survive leaving the view for hundreds of
    frames (measured: mean IoU 0.81, IDF1 0.734, 0.74 switches per object per 100 frames).
    About 5 minutes on 2 cores, half of it rendering; frames are scored as they come out, so
    the sequence is never held in memory."""
    from shared.synth import run_synth

    seq = tmp_path_factory.mktemp("synth") / "revisit"
    run_synth("revisit", 0, seq, progress=False)
    reader = open_sequence(seq, "replica")
    core, kf = build(seq)
    keys: set[int] = set()

    def scored() -> Iterable[tuple[int, np.ndarray, np.ndarray]]:
        for i in range(len(reader)):
            frame = reader.frame(i)
            (out,) = run(core, kf, [frame])
            if out.keyframe:
                keys.add(frame.frame_index)
            yield frame.frame_index, out.track_ids, reader.instances(i)

    m = evaluate_track_maps(scored(), keys)
    assert m["n_frames"] == 600 and m["n_keyframes"] == 75
    assert m["mean_iou"] >= 0.6, m
    assert m["idf1"] >= 0.7, m
    assert m["id_switches_per_100_frames_per_object"] < 1.0, m
