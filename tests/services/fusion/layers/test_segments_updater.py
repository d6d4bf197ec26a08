"""The track-to-segment rules of the 3D segment updater (paper III-D, eq. 7), on hand-built meshes.

Every vertex of a block holds the same hypotheses; blocks are laid out 0.2 m apart along x, so
geometry never interferes with the rule under test.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.layers.segments import SegmentLayer
from services.fusion.types import HypothesisMesh, TrackState
from shared.config.fusion import ReidConfig, SegmentsConfig

K = 4


def build_mesh(*blocks: tuple[int, list[tuple[int, float]]], y: float = 0.0) -> HypothesisMesh:
    """``blocks``: (vertex count, [(track, weight), ...]) held by every vertex of the block."""
    v = sum(n for n, _ in blocks)
    vertices = np.zeros((v, 3), np.float32)
    vertices[:, 0] = 0.2 * np.arange(v)
    vertices[:, 1] = y
    ids = np.full((v, K), -1, np.int32)
    weights = np.zeros((v, K), np.float32)
    row = 0
    for n, hyps in blocks:
        for j, (t, w) in enumerate(hyps):
            ids[row : row + n, j] = t
            weights[row : row + n, j] = w
        row += n
    return HypothesisMesh(
        vertices, np.zeros((v, 3), np.uint8), np.zeros((0, 3), np.int32), ids, weights
    )


def dino(cos: float, axis: int = 1) -> np.ndarray:
    """Unit vector at cosine ``cos`` to e0, tilted towards e_axis."""
    v = np.zeros(4, np.float32)
    v[0] = cos
    v[axis] = np.sqrt(1.0 - cos * cos)
    return v


def states(**dinos: np.ndarray) -> dict[int, TrackState]:
    """``states(t1=..., t2=...)`` -> {1: TrackState(1, dino=...), ...}."""
    return {int(k[1:]): TrackState(int(k[1:]), dino=d) for k, d in dinos.items()}


def layer(**seg) -> SegmentLayer:
    # Re-identification off: these tests pin the active-window rules alone. They pin eq. 7 as
    # the paper counts it (``containment: presence``) unless they say otherwise; the
    # evidence-weighted rho_q->i has its own tests below.
    seg.setdefault("containment", "presence")
    return SegmentLayer(SegmentsConfig(**seg), ReidConfig(enabled=False))


E0 = dino(1.0)


@pytest.mark.parametrize(("winning", "expect_segment"), [(19, False), (20, True)])
def test_min_vertices_gate(winning: int, expect_segment: bool) -> None:
    lay = layer()
    ch = lay.update(build_mesh((winning, [(1, 1.0)])), states(t1=E0))
    assert (lay.segment_of_track(1) is not None) is expect_segment
    assert ch.added == ([0] if expect_segment else [])


def test_min_vertices_counts_winning_vertices_only() -> None:
    """A track present on 30 vertices but winning only 19 of them gets no segment."""
    lay = layer()
    mesh = build_mesh((19, [(1, 2.0)]), (11, [(2, 2.0), (1, 1.0)]))
    lay.update(mesh, states(t1=E0, t2=dino(0.0)))
    assert lay.segment_of_track(1) is None


def _two_step(
    n_shared: int, n_only_i: int, n_only_q: int, q_dino: np.ndarray = E0, **seg
) -> SegmentLayer:
    """Segment 0 from track 1; then track 2 arrives over it.

    Second mesh: n_shared vertices hold (2, 1) and track 2 wins; n_only_i hold only track 1;
    n_only_q hold only track 2. So |V_q| = n_shared + n_only_q, |V_i| = n_shared + n_only_i.
    """
    lay = layer(**seg)
    lay.update(build_mesh((30, [(1, 1.0)])), states(t1=E0))
    assert lay.segment_of_track(1) == 0
    blocks = [(n_shared, [(2, 2.0), (1, 1.0)]), (n_only_i, [(1, 1.0)]), (n_only_q, [(2, 1.0)])]
    lay.update(build_mesh(*[b for b in blocks if b[0]]), states(t1=E0, t2=q_dino))
    return lay


@pytest.mark.parametrize(
    ("n_shared", "n_only_i", "n_only_q", "joins"),
    [
        (20, 80, 0, True),  # rho_q->i = 1.0: the track lies inside the segment
        (15, 85, 5, True),  # rho_q->i = 0.75 exactly (>=)
        (14, 86, 6, False),  # rho_q->i = 0.70, rho_i->q = 0.14
        (15, 5, 30, True),  # rho_i->q = 0.75 exactly: the segment lies inside the track
        (14, 6, 30, False),  # rho_i->q = 0.70, rho_q->i = 0.32
    ],
)
def test_rho_threshold_in_either_direction(
    n_shared: int, n_only_i: int, n_only_q: int, joins: bool
) -> None:
    lay = _two_step(n_shared, n_only_i, n_only_q)
    assert lay.segment_of_track(2) == (0 if joins else 1)
    assert len(lay.segments) == (1 if joins else 2)


@pytest.mark.parametrize(("n_shared", "joins"), [(5, True), (4, False)])
def test_min_shared_gate(n_shared: int, joins: bool) -> None:
    """rho_i->q is 5/6 or 4/5, both above 0.75; only the shared count decides."""
    lay = _two_step(n_shared, 1, 20)
    assert lay.segment_of_track(2) == (0 if joins else 1)


def test_min_shared_is_configurable() -> None:
    lay = _two_step(4, 1, 20, min_shared=4)
    assert lay.segment_of_track(2) == 0


@pytest.mark.parametrize(("cos", "joins"), [(0.81, True), (0.79, False)])
def test_dino_similarity_gate(cos: float, joins: bool) -> None:
    lay = _two_step(20, 80, 0, q_dino=dino(cos))
    assert lay.segment_of_track(2) == (0 if joins else 1)


def test_only_active_segments_are_candidates() -> None:
    """Track 1 is on every shared vertex but wins none, so segment 0 is historical: no match."""
    lay = _two_step(20, 0, 0)
    assert lay.segment_of_track(2) == 1
    assert not lay.segments[0].active
    assert lay.segments[1].active


def _three_tracks(
    second_mesh: list[tuple[int, list[tuple[int, float]]]], d1: np.ndarray, d2: np.ndarray
) -> SegmentLayer:
    """Segment 0 = track 1 and segment 1 = track 2 (apart), then track 3 over both."""
    lay = layer()
    lay.update(build_mesh((20, [(1, 1.0)]), (20, [(2, 1.0)])), states(t1=d1, t2=d2))
    assert (lay.segment_of_track(1), lay.segment_of_track(2)) == (0, 1)
    lay.update(build_mesh(*second_mesh), states(t1=d1, t2=d2, t3=E0))
    return lay


def test_mutual_overlap_beats_containment_with_more_shared_vertices() -> None:
    """|V_q| = 40. Segment 0: 30 shared, |V_0| = 32 -> rho 0.75 / 0.94 (mutual).
    Segment 1: 38 shared, |V_1| = 100 -> rho 0.95 / 0.38 (containment), and more similar."""
    mesh = [
        (30, [(3, 3.0), (1, 1.0), (2, 1.0)]),
        (8, [(3, 3.0), (2, 1.0)]),
        (2, [(3, 3.0)]),
        (2, [(1, 1.0)]),
        (62, [(2, 1.0)]),
    ]
    lay = _three_tracks(mesh, dino(0.9), dino(0.95, axis=2))
    assert lay.segment_of_track(3) == 0


def test_shared_count_breaks_ties_between_containments() -> None:
    """Both segments contain the track (|V_q| = 30, |V_i| = 100); 30 vs 25 shared vertices
    decides, though segment 1 is more similar."""
    mesh = [
        (25, [(3, 3.0), (1, 1.0), (2, 1.0)]),
        (5, [(3, 3.0), (1, 1.0)]),
        (70, [(1, 1.0)]),
        (75, [(2, 1.0)]),
    ]
    lay = _three_tracks(mesh, dino(0.85), dino(0.95, axis=2))
    assert lay.segment_of_track(3) == 0


def test_similarity_breaks_ties_of_equal_shared_count() -> None:
    mesh = [(30, [(3, 3.0), (1, 1.0), (2, 1.0)]), (70, [(1, 1.0)]), (70, [(2, 1.0)])]
    lay = _three_tracks(mesh, dino(0.85), dino(0.95, axis=2))
    assert lay.segment_of_track(3) == 1
    lay = _three_tracks(mesh, dino(0.95), dino(0.85, axis=2))
    assert lay.segment_of_track(3) == 0


def test_unmatched_track_gets_a_new_segment() -> None:
    lay = layer()
    lay.update(build_mesh((20, [(1, 1.0)])), states(t1=E0))
    ch = lay.update(build_mesh((20, [(1, 1.0)]), (25, [(2, 1.0)])), states(t1=E0, t2=E0))
    assert ch.added == [1]
    assert lay.segment_of_track(2) == 1
    assert lay.segments[1].tracks == {2}


def test_tracks_of_one_update_consolidate() -> None:
    """Two new tracks on one surface: the better-supported one seeds the segment, the other joins."""
    lay = layer()
    mesh = build_mesh((40, [(7, 2.0), (3, 1.0)]), (20, [(3, 2.0), (7, 1.0)]))
    ch = lay.update(mesh, states(t3=E0, t7=dino(0.9)))
    assert ch.added == [0]
    assert lay.segments[0].tracks == {3, 7}
    assert lay.segment_of_track(3) == lay.segment_of_track(7) == 0


def test_track_without_dino_waits_for_its_feature() -> None:
    lay = layer()
    mesh = build_mesh((30, [(1, 1.0)]))
    ch = lay.update(mesh, {1: TrackState(1)})
    assert ch.added == [] and lay.segment_of_track(1) is None
    ch = lay.update(mesh, states(t1=E0))
    assert ch.added == [0]


def test_assigned_tracks_stay_with_their_segment() -> None:
    """Matching applies to unassigned tracks only: an assigned track that later overlaps
    another segment is not moved."""
    lay = layer()
    lay.update(build_mesh((20, [(1, 1.0)]), (20, [(2, 1.0)])), states(t1=E0, t2=dino(0.5)))
    lay.update(build_mesh((40, [(2, 2.0), (1, 1.0)]), (5, [(1, 1.0)])), states(t1=E0, t2=E0))
    assert (lay.segment_of_track(1), lay.segment_of_track(2)) == (0, 1)


def test_vertices_follow_the_winning_track() -> None:
    lay = layer()
    mesh = build_mesh((20, [(1, 1.0)]), (3, [(9, 1.0)]), (25, [(2, 3.0), (1, 1.0)]))
    lay.update(mesh, states(t1=E0, t2=dino(0.2)))
    # Track 2 wins more vertices, so it is processed, and numbered, first.
    assert (lay.segment_of_track(2), lay.segment_of_track(1)) == (0, 1)
    expect = np.array([1] * 20 + [-1] * 3 + [0] * 25, np.int32)
    np.testing.assert_array_equal(lay.vertex_segments(), expect)
    np.testing.assert_array_equal(lay.segments[1].vertex_ids, np.arange(20))
    np.testing.assert_array_equal(lay.segments[0].vertex_ids, np.arange(23, 48))
    np.testing.assert_array_equal(lay.segments[0].positions, mesh.vertices[23:48])


@pytest.mark.parametrize(("n_shared", "joins"), [(5, True), (4, False)])
def test_vertex_counts_once_per_segment(n_shared: int, joins: bool) -> None:
    """Segment 0 holds tracks 1 and 2, both on the shared vertices: each counts once, so
    |V_q ∩ V_0| is n_shared, not 2 n_shared."""
    lay = layer()
    lay.update(
        build_mesh((40, [(1, 2.0), (2, 1.0)]), (20, [(2, 2.0), (1, 1.0)])), states(t1=E0, t2=E0)
    )
    assert lay.segments[0].tracks == {1, 2}
    mesh = build_mesh(
        (n_shared, [(3, 3.0), (1, 1.0), (2, 1.0)]), (1, [(1, 1.0), (2, 0.5)]), (20, [(3, 1.0)])
    )
    lay.update(mesh, states(t1=E0, t2=E0, t3=E0))
    assert lay.segment_of_track(3) == (0 if joins else 1)


def test_large_track_ids_and_retired_tracks() -> None:
    """Ids far beyond the mesh size take the sorting path; a retired track still gets a segment."""
    big = 10_000_000
    lay = layer()
    mesh = build_mesh((20, [(big + 1, 2.0), (big, 1.0)]), (25, [(big, 1.0)]))
    tracks = {big: TrackState(big, dino=E0, retired=True), big + 1: TrackState(big + 1, dino=E0)}
    ch = lay.update(mesh, tracks)
    assert ch.added == [0]
    assert lay.segments[0].tracks == {big, big + 1}
    np.testing.assert_array_equal(lay.vertex_segments(), np.zeros(45, np.int32))


# -- rho_q->i weighted by evidence (SegmentsConfig.containment: evidence) ----------------------


def _over_segment(
    shared: list[tuple[int, float, float]],
    n_new_only: int = 0,
    l_new_only: float = 1.0,
    containment: str = "evidence",
) -> SegmentLayer:
    """Segment 0 = track 1 (100 vertices of its own at l = 5); then track 2 arrives.

    ``shared``: blocks of (vertex count, l of track 2, l of track 1) holding both tracks;
    ``n_new_only`` more vertices hold only track 2 (at ``l_new_only``). Track 2's DINOv3 feature equals
    the segment's, and rho_i->q stays far below theta_rho: only rho_q->i can decide.
    """
    lay = layer(containment=containment)
    lay.update(build_mesh((100, [(1, 5.0)])), states(t1=E0))
    blocks = [(100, [(1, 5.0)])] + [(n, [(2, lq), (1, li)]) for n, lq, li in shared]
    if n_new_only:
        blocks.append((n_new_only, [(2, l_new_only)]))
    lay.update(build_mesh(*blocks), states(t1=E0, t2=E0))
    return lay


@pytest.mark.parametrize(("containment", "joins"), [("presence", True), ("evidence", False)])
def test_stray_hypotheses_do_not_make_a_track_part_of_a_segment(containment: str, joins: bool) -> None:
    """Track 1 left weak hypotheses (l = 0.3) over the 40 vertices where track 2 then wins at
    l = 1 (a mask that once fused a rug with the floor): by presence track 2 lies inside the
    segment (rho 1.0); by evidence only 0.3 of its weight is matched."""
    lay = _over_segment([(40, 1.0, 0.3)], containment=containment)
    assert lay.segment_of_track(2) == (0 if joins else 1)


@pytest.mark.parametrize("containment", ["presence", "evidence"])
def test_a_track_on_the_segments_own_surface_joins_in_both_modes(containment: str) -> None:
    """Track 2 is weaker than track 1 on the 80 shared vertices (a new track over a surface the
    segment was fused on) and alone on 20, at l = 0.5 throughout: rho_q->i is 0.8 both ways."""
    lay = _over_segment([(80, 0.5, 2.0)], n_new_only=20, l_new_only=0.5, containment=containment)
    assert lay.segment_of_track(2) == 0


@pytest.mark.parametrize(("l_segment", "joins"), [(0.75, True), (0.7, False)])
def test_evidence_rho_threshold(l_segment: float, joins: bool) -> None:
    """sum min(l_q, l_i) / sum l_q = l_segment / 1.0 on every vertex of V_q; 0.75 passes (>=)."""
    lay = _over_segment([(40, 1.0, l_segment)])
    assert lay.segment_of_track(2) == (0 if joins else 1)


def test_evidence_is_matched_vertex_by_vertex() -> None:
    """The segment holds far more weight on V_q in total (20 x 10 + 20 x 0.1 against 40), but
    only on half of its vertices: rho_q->i = (20 x 1 + 20 x 0.1) / 40 = 0.55."""
    lay = _over_segment([(20, 1.0, 10.0), (20, 1.0, 0.1)])
    # Track 2 wins only the 20 vertices where track 1 is weak, so it still reaches min_vertices.
    assert lay.segment_of_track(2) == 1
    lay = _over_segment([(20, 1.0, 10.0), (20, 1.0, 0.1)], containment="presence")
    assert lay.segment_of_track(2) == 0


def test_evidence_sums_the_weight_of_all_the_segments_tracks() -> None:
    """Segment 0 holds tracks 1 and 3; on the 40 vertices track 2 wins at l = 1 each holds 0.5,
    so the segment matches all of track 2's weight. With track 1 alone there, half of it."""
    first = [(40, [(1, 3.0), (3, 1.0)]), (20, [(3, 2.0), (1, 1.9)])]
    for hyps, joins in (([(2, 1.0), (1, 0.5), (3, 0.5)], True), ([(2, 1.0), (1, 0.5)], False)):
        lay = layer(containment="evidence")
        lay.update(build_mesh(*first), states(t1=E0, t3=E0))
        assert lay.segments[0].tracks == {1, 3}
        lay.update(build_mesh(*first, (40, hyps)), states(t1=E0, t2=E0, t3=E0))
        assert lay.segment_of_track(2) == (0 if joins else 1)


def test_evidence_leaves_the_segment_inside_the_track_to_presence() -> None:
    """rho_i->q = 15 / 20 = 0.75 although track 2 outweighs the segment on the shared vertices
    (a fuller new view of a segment seen less): the segment joins the track in both modes."""
    lay = _two_step(15, 5, 30, containment="evidence")
    assert lay.segment_of_track(2) == 0
