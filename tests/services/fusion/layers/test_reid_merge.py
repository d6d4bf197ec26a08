"""Long-term re-identification (paper III-E, eqs. 8-9) and the merge into the historical segment.

A historical segment H is a 10 x 10 grid in z = 0 with 0.2 m pitch. A query of 100 vertices
puts ``n_close`` of them 5 cm above H's vertices (within r_nn = 0.10 m) and the rest 0.5 m
above (farther than r_nn from all of H), so o_qh = n_close / 100 exactly.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.layers.reid import combined_score, overlap_fraction
from services.fusion.layers.segments import SegmentLayer
from services.fusion.types import HypothesisMesh, TrackState
from shared.config.fusion import ReidConfig, SegmentsConfig

K = 4


def mesh_at(*blocks: tuple[np.ndarray, list[tuple[int, float]]]) -> HypothesisMesh:
    vertices = np.concatenate([np.asarray(p, np.float32) for p, _ in blocks])
    v = len(vertices)
    ids = np.full((v, K), -1, np.int32)
    weights = np.zeros((v, K), np.float32)
    row = 0
    for p, hyps in blocks:
        for j, (t, w) in enumerate(hyps):
            ids[row : row + len(p), j] = t
            weights[row : row + len(p), j] = w
        row += len(p)
    return HypothesisMesh(
        vertices, np.zeros((v, 3), np.uint8), np.zeros((0, 3), np.int32), ids, weights
    )


def grid(x0: float = 0.0) -> np.ndarray:
    ii, jj = np.meshgrid(np.arange(10), np.arange(10), indexing="ij")
    p = np.zeros((100, 3), np.float32)
    p[:, 0] = x0 + 0.2 * ii.ravel()
    p[:, 1] = 0.2 * jj.ravel()
    return p


def query_over(h: np.ndarray, n_close: int) -> np.ndarray:
    """100 query vertices, the first ``n_close`` within r_nn of ``h``'s, the rest 0.5 m away."""
    q = h[:100].copy()
    q[:n_close, 2] += 0.05
    q[n_close:, 2] += 0.5
    return q


def dino(cos: float, axis: int = 1) -> np.ndarray:
    v = np.zeros(4, np.float32)
    v[0] = cos
    v[axis] = np.sqrt(1.0 - cos * cos)
    return v


E0 = dino(1.0)


def revisit(
    n_close: int, cos: float, **reid
) -> tuple[SegmentLayer, object, np.ndarray, np.ndarray]:
    """H = segment 0 from track 1; it leaves the window; track 2 re-meshes the place."""
    lay = SegmentLayer(SegmentsConfig(), ReidConfig(**reid))
    h = grid()
    tracks = {1: TrackState(1, dino=dino(cos), clip=np.array([1, 0], np.float32))}
    lay.update(mesh_at((h, [(1, 1.0)])), tracks)
    tracks[2] = TrackState(2, dino=E0, clip=np.array([0, 1], np.float32))
    q = query_over(h, n_close)
    ch = lay.update(mesh_at((q, [(2, 1.0)])), tracks)
    return lay, ch, h, q


@pytest.mark.parametrize(("n_close", "merges"), [(41, False), (42, True), (43, True)])
def test_overlap_gate(n_close: int, merges: bool) -> None:
    """cos = 0.95: J = 0.5 o + 0.475 clears 0.65 for all three; only o >= 0.42 decides."""
    lay, ch, _, _ = revisit(n_close, 0.95)
    assert combined_score(n_close / 100, 0.95, ReidConfig()) >= 0.65
    assert (ch.merged == {1: 0}) is merges
    assert len(lay.segments) == (1 if merges else 2)


@pytest.mark.parametrize(("cos", "merges"), [(0.69, False), (0.71, True)])
def test_cosine_gate(cos: float, merges: bool) -> None:
    """o = 1: J = 0.5 + cos / 2 passes 0.65 either way; only cos >= 0.70 decides."""
    lay, ch, _, _ = revisit(100, cos)
    assert (lay.segment_of_track(2) == 0) is merges


@pytest.mark.parametrize(
    ("n_close", "cos", "merges"),
    [(50, 0.75, False), (60, 0.75, True), (42, 0.87, False), (42, 0.89, True)],
)
def test_combined_score_gate(n_close: int, cos: float, merges: bool) -> None:
    """o and cos both pass their gates; J = 0.625, 0.675, 0.645, 0.655 against 0.65."""
    lay, ch, _, _ = revisit(n_close, cos)
    assert (ch.merged == {1: 0}) is merges


def test_weights_are_configurable() -> None:
    """With lambda_o = 0.8, o = 0.6 and cos = 0.75 give J = 0.63 < 0.65."""
    _, ch, _, _ = revisit(60, 0.75, lambda_o=0.8, lambda_a=0.2)
    assert ch.merged == {}


def test_merge_moves_tracks_gallery_and_vertices_and_reactivates() -> None:
    lay, ch, h, q = revisit(43, 0.95)
    assert ch.added == [] and ch.removed == [] and ch.changed == [0] and ch.merged == {1: 0}
    seg = lay.segments[0]
    assert set(lay.segments) == {0}
    assert seg.active and seg.to_node().active
    assert seg.tracks == {1, 2} and lay.segment_of_track(2) == 0
    assert sorted(seg.gallery) == [1, 2]
    np.testing.assert_array_equal(seg.gallery[2], [0, 1])
    np.testing.assert_array_equal(seg.vertex_ids, np.arange(100))
    assert (lay.vertex_segments() == 0).all()
    # H's 43 vertices the new mesh re-observes are replaced; its other 57 are kept.
    np.testing.assert_array_equal(seg.positions, np.concatenate([h[43:], q]))
    np.testing.assert_allclose(seg.centroid, np.concatenate([h[43:], q]).astype(np.float64).mean(0))
    # The aggregate now includes the query's track.
    assert float(seg.dino @ E0) > 0.95


def test_reid_disabled_keeps_the_duplicate() -> None:
    lay, ch, _, _ = revisit(100, 0.99, enabled=False)
    assert ch.added == [1] and ch.merged == {}
    assert len(lay.segments) == 2 and not lay.segments[0].active


def test_candidates_are_limited_by_the_centroid_radius() -> None:
    """A perfect overlap still needs H's centroid within search_radius_m of the query's."""
    _, ch, h, _ = revisit(100, 0.99, search_radius_m=0.4)  # centroids 0.05 m apart
    assert ch.merged == {1: 0}
    lay = SegmentLayer(SegmentsConfig(), ReidConfig(search_radius_m=0.4))
    tracks = {1: TrackState(1, dino=E0), 2: TrackState(2, dino=E0)}
    big = np.concatenate([h, grid(x0=4.0)])  # centroid moves 2 m away from the query's
    lay.update(mesh_at((big, [(1, 1.0)])), tracks)
    ch = lay.update(mesh_at((query_over(h, 100), [(2, 1.0)])), tracks)
    assert ch.merged == {}


def test_highest_combined_score_wins() -> None:
    """H1 (x in [0, 1.8]) and H2 (x in [2, 3.8]); the query overlaps 55 of H1 and 45 of H2.
    H1: o = 0.55, cos = 0.90 -> J = 0.725; H2: o = 0.45, cos = 0.99 -> J = 0.72."""
    lay = SegmentLayer(SegmentsConfig(), ReidConfig())
    h1, h2 = grid(), grid(x0=2.0)
    tracks = {
        1: TrackState(1, dino=dino(0.90)),
        3: TrackState(3, dino=dino(0.99, axis=2)),
        2: TrackState(2, dino=E0),
    }
    lay.update(mesh_at((h1, [(1, 1.0)]), (h2, [(3, 1.0)])), tracks)
    q = np.concatenate([h1[:55], h2[:45]]) + np.array([0, 0, 0.05], np.float32)
    ch = lay.update(mesh_at((q, [(2, 1.0)])), tracks)
    assert ch.merged == {2: 0}
    assert lay.segments[0].active and not lay.segments[1].active

    # Swap the appearances so H2 scores J = 0.5 * 0.45 + 0.5 * 0.99 vs 0.5 * 0.55 + 0.5 * 0.80.
    lay = SegmentLayer(SegmentsConfig(), ReidConfig())
    tracks[1].dino = dino(0.80)
    lay.update(mesh_at((h1, [(1, 1.0)]), (h2, [(3, 1.0)])), tracks)
    ch = lay.update(mesh_at((q, [(2, 1.0)])), tracks)
    assert ch.merged == {2: 1}


def test_existing_segment_merged_later_is_reported_removed() -> None:
    """The query segment is created away from H (o = 0), then grows over it: it is merged in a
    later update and so reported as removed."""
    lay = SegmentLayer(SegmentsConfig(), ReidConfig())
    h = grid()
    tracks = {1: TrackState(1, dino=E0), 2: TrackState(2, dino=E0)}
    lay.update(mesh_at((h, [(1, 1.0)])), tracks)
    away = h[:20] + np.array([0, 0, 1.0], np.float32)
    ch = lay.update(mesh_at((away, [(2, 1.0)])), tracks)
    assert ch.added == [1] and ch.merged == {}
    # Track 2 now covers H's place; the first 20 vertices stay stored as archived geometry,
    # so o = 80 / 100.
    ch = lay.update(mesh_at((h[:80] + np.array([0, 0, 0.05], np.float32), [(2, 1.0)])), tracks)
    assert ch.merged == {1: 0} and ch.removed == [1] and ch.added == [] and ch.changed == [0]
    assert set(lay.segments) == {0} and lay.segments[0].tracks == {1, 2}


def test_overlap_fraction_is_inclusive_at_r_nn() -> None:
    from scipy.spatial import cKDTree

    tree = cKDTree(np.zeros((1, 3)))
    pts = np.array([[0.1, 0, 0], [0.1000001, 0, 0], [0, 0.05, 0], [1, 1, 1]])
    assert overlap_fraction(pts, tree, 0.1) == pytest.approx(0.5)
