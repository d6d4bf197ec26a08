"""Keyframe correction by hand (paper III-B): eq. 2 prototypes, eq. 3 scores, both gates, the
greedy one-to-one order, the DINOv3 EMA and the eq. 4 CLIP running mean."""

from __future__ import annotations

import numpy as np
import pytest

from services.tracker.association import (
    associate,
    associate_iou,
    ema,
    mask_iou,
    mask_prototypes,
    running_mean,
    sparse_mask_iou,
)
from services.tracker.tracks import Track, TrackBook
from shared.config.tracker import AssociationConfig

CFG = AssociationConfig()  # the paper's: w 0.5 / 0.5, IoU >= 0.15, s >= 0.35, eta 0.2
E = np.eye(3, dtype=np.float32)


def test_paper_defaults():
    assert (CFG.w_iou, CFG.w_feat, CFG.iou_min, CFG.score_min, CFG.ema) == (0.5, 0.5, 0.15, 0.35, 0.2)


def test_eq3_scores_and_both_gates():
    # Track 0 and detection 0 overlap well but look unrelated (cos 0): s = 0.3 < 0.35.
    # Track 1 and detection 1 look identical but barely overlap (IoU 0.1 < 0.15).
    # Track 1 and detection 0: IoU 0.2, cos 1 -> s = 0.6, both gates pass.
    iou = np.array([[0.6, 0.0], [0.2, 0.1]], np.float32)
    tracks = np.stack([E[0], E[1]])
    dets = np.stack([E[1], E[1]])
    a = associate_iou(iou, tracks, dets, CFG)
    np.testing.assert_allclose(a.scores, [[0.3, 0.0], [0.6, 0.55]], atol=1e-6)
    assert a.matches == [(1, 0)]
    assert a.new_detections == [1]
    assert a.retired_tracks == [0]


def test_negative_cosine_counts_as_zero():
    a = associate_iou(np.array([[0.8]], np.float32), E[:1], -E[:1], CFG)
    assert a.scores[0, 0] == pytest.approx(0.4)
    assert a.matches == [(0, 0)]


def test_greedy_takes_the_best_score_first_not_the_best_total():
    # cos = [[1, 0.71], [0.71, 0]] and IoU = [[0.8, 0.6], [0.7, 0]] give
    # s = [[0.9, 0.65], [0.70, invalid]]. Greedy takes (0, 0) and leaves track 1 and
    # detection 1 unmatched, although (0, 1) + (1, 0) would score more in total.
    iou = np.array([[0.8, 0.6], [0.7, 0.0]], np.float32)
    tracks = np.stack([E[0], (E[0] + E[1]) / np.sqrt(2)])
    dets = np.stack([E[0], (E[0] - E[1]) / np.sqrt(2)])
    a = associate_iou(iou, tracks, dets, CFG)
    assert a.scores[0, 0] == pytest.approx(0.9)
    assert a.scores[0, 1] + a.scores[1, 0] > a.scores[0, 0]
    assert a.matches == [(0, 0)]
    assert a.new_detections == [1] and a.retired_tracks == [1]


def test_greedy_order_and_tie_breaks():
    half = np.array([0.5, np.sqrt(0.75), 0.0], np.float32)  # cos 0.5 with E[0]
    dets = np.stack([E[0], half])
    # s_00 = 0.5 * 0.4 + 0.5 = 0.7 beats s_01 = 0.5 * 0.6 + 0.25 = 0.55 despite the IoU.
    a = associate_iou(np.array([[0.4, 0.6]], np.float32), E[:1], dets, CFG)
    assert a.matches == [(0, 0)]
    # Equal scores (0.75 each, exact in binary): the pair with the higher IoU goes first.
    a2 = associate_iou(np.array([[0.5, 1.0]], np.float32), E[:1], dets, CFG)
    assert a2.scores[0, 0] == a2.scores[0, 1] == 0.75
    assert a2.matches == [(0, 1)]
    # Equal scores and IoUs: the lower track row first.
    a3 = associate_iou(np.array([[0.5], [0.5]], np.float32), np.stack([E[0], E[0]]), E[:1], CFG)
    assert a3.matches == [(0, 0)] and a3.retired_tracks == [1]


def test_associate_on_masks_matches_the_iou_path():
    pred = np.zeros((2, 6, 6), bool)
    pred[0, :3, :3] = True
    pred[1, 3:, 3:] = True
    det = np.zeros((3, 6, 6), bool)
    det[0, 3:, 2:] = True  # mostly track 1
    det[1, :3, :4] = True  # mostly track 0
    det[2, 0, 5] = True  # nothing
    feats = np.stack([E[0], E[0]])
    dfeats = np.stack([E[0], E[0], E[0]])
    a = associate(pred, det, feats, dfeats, CFG)
    np.testing.assert_allclose(a.iou, mask_iou(pred, det))
    assert sorted(a.matches) == [(0, 1), (1, 0)]
    assert a.new_detections == [2] and a.retired_tracks == []
    np.testing.assert_allclose(sparse_mask_iou(list(pred), det), a.iou, atol=1e-6)


def test_empty_inputs():
    a = associate(np.zeros((0, 4, 4), bool), np.zeros((2, 4, 4), bool), np.zeros((0, 3)), np.zeros((2, 3)), CFG)
    assert a.matches == [] and a.new_detections == [0, 1] and a.retired_tracks == []
    b = associate(np.zeros((2, 4, 4), bool), np.zeros((0, 4, 4), bool), np.zeros((2, 3)), np.zeros((0, 3)), CFG)
    assert b.matches == [] and b.new_detections == [] and b.retired_tracks == [0, 1]
    assert sparse_mask_iou([], np.zeros((2, 4, 4), bool)).shape == (0, 2)


def test_eq2_prototype_is_the_area_weighted_mean_of_unit_features():
    feats = np.zeros((1, 2, 3), np.float32)
    feats[0, 0] = E[0]
    feats[0, 1] = E[1]
    mask = np.zeros((1, 2, 4), bool)
    mask[0, :, :2] = True  # all of cell 0
    mask[0, 0, 2] = True  # a quarter of cell 1
    proto = mask_prototypes(feats, mask)
    expected = (E[0] + 0.25 * E[1]) / np.linalg.norm(E[0] + 0.25 * E[1])
    np.testing.assert_allclose(proto[0], expected, atol=1e-6)
    assert mask_prototypes(feats, np.zeros((0, 2, 4), bool)).shape == (0, 3)


def test_ema_with_eta_02():
    old, new = E[0], E[1]
    out = ema(old, new, 0.2)
    expected = np.array([0.8, 0.2, 0.0]) / np.linalg.norm([0.8, 0.2])
    np.testing.assert_allclose(out, expected, atol=1e-6)
    assert np.linalg.norm(out) == pytest.approx(1.0)
    t = Track(id=3, dino=E[0].copy(), last_detection=0)
    t.detected(E[1], count=24, eta=0.2)
    np.testing.assert_allclose(t.dino, expected, atol=1e-6)
    assert t.last_detection == 24


def test_eq4_running_mean():
    rng = np.random.default_rng(0)
    feats = rng.standard_normal((5, 8)).astype(np.float32)
    mean, n = None, 0
    for k, f in enumerate(feats):
        mean, n = running_mean(mean, n, f)
        np.testing.assert_allclose(mean, feats[: k + 1].mean(0), atol=1e-6)
        assert n == k + 1
    t = Track(id=0, dino=E[0], last_detection=0)
    for f in feats:
        t.add_clip(f)
    np.testing.assert_allclose(t.clip, feats.mean(0), atol=1e-6)
    assert t.clip_count == 5


def test_lost_pool_is_bounded_and_retires_the_oldest():
    book = TrackBook(max_lost=2)
    for _ in range(4):
        book.new(E[0], 0)
    book.lose([0, 1], count=5)
    book.lose([2], count=9)
    assert list(book.lost) == [1, 2] and book.retired == [0]
    book.revive(1)
    book.retire([2])
    assert not book.lost and book.retired == [0, 2]
    changed, retired = book.take_changes()
    assert [t.id for t in changed] == [0, 1, 2, 3] and retired == [0, 2]
    assert book.take_changes() == ([], [])


def test_a_retired_track_keeps_its_identity_but_not_its_footprint():
    """Only re-identification reads footprints; a live tracker retires tracks all the time."""
    from services.tracker.footprints import Footprint

    book = TrackBook(max_lost=1)
    for _ in range(3):
        t = book.new(E[0], 0)
        t.footprint = Footprint(np.zeros((4000, 3), np.float32), 0.01)
    book.lose([0, 1], count=5)  # the pool holds one: track 0 is retired
    book.retire([1])
    assert book.tracks[0].footprint is None and book.tracks[1].footprint is None
    assert book.tracks[2].footprint is not None  # active
    assert sorted(book.tracks) == [0, 1, 2] and book.tracks[0].dino is not None
    book.tracks[0].add_clip(E[1])  # a late CLIP feature of a retired track still folds in
    assert book.tracks[0].clip_count == 1
