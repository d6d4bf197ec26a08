"""Segment state over time: active/historical transitions, geometry that leaves the window,
the aggregated DINOv3 feature, the CLIP gallery (III-F), the wire form and save/resume."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.layers.gallery import gallery_score
from services.fusion.layers.segments import SegmentLayer
from services.fusion.types import HypothesisMesh, TrackState
from shared.config.fusion import ReidConfig, SegmentsConfig
from shared.messages.graph import SegmentNode

K = 4


def mesh_at(*blocks: tuple[np.ndarray, list[tuple[int, float]]]) -> HypothesisMesh:
    """``blocks``: (positions (n, 3), [(track, weight), ...] held by every vertex of the block)."""
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


def row(n: int, x0: float = 0.0, y: float = 0.0) -> np.ndarray:
    """n points 0.2 m apart along x (farther apart than r_nn, so each covers only itself)."""
    p = np.zeros((n, 3), np.float32)
    p[:, 0] = x0 + 0.2 * np.arange(n)
    p[:, 1] = y
    return p


def unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


E0 = np.array([1, 0, 0, 0], np.float32)
E1 = np.array([0, 1, 0, 0], np.float32)


def new_layer(reid: bool = False) -> SegmentLayer:
    # The joins built here put a new track over a weaker one; they test the segment's state,
    # not the matching, so they use eq. 7 as the paper counts it (test_segments_updater.py
    # pins both ``containment`` modes).
    return SegmentLayer(SegmentsConfig(containment="presence"), ReidConfig(enabled=reid))


def test_active_historical_active() -> None:
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0), 2: TrackState(2, dino=E1)}
    here = row(30)
    ch = lay.update(mesh_at((here, [(1, 1.0)])), tracks)
    assert ch.added == [0] and lay.segments[0].active

    # Track 1 is gone from the window; a new surface far away appears.
    ch = lay.update(mesh_at((row(25, y=50.0), [(2, 1.0)])), tracks)
    seg = lay.segments[0]
    assert ch.added == [1] and ch.changed == [0]
    assert not seg.active and not seg.to_node().active
    assert seg.vertex_ids.size == 0
    np.testing.assert_array_equal(seg.positions, here)  # historical geometry is kept
    np.testing.assert_allclose(seg.bbox_min, [0, 0, 0])
    np.testing.assert_allclose(seg.bbox_max, [0.2 * 29, 0, 0], rtol=1e-6)
    assert (lay.vertex_segments() == 1).all()

    # Nothing about it changes while it stays out of the window.
    ch = lay.update(mesh_at((row(25, y=50.0), [(2, 1.0)])), tracks)
    assert 0 not in ch.changed

    ch = lay.update(mesh_at((here, [(1, 1.0)])), tracks)
    assert ch.changed == [0, 1]
    assert lay.segments[0].active and not lay.segments[1].active


def test_empty_mesh_makes_everything_historical() -> None:
    lay = new_layer()
    lay.update(mesh_at((row(20), [(1, 1.0)])), {1: TrackState(1, dino=E0)})
    ch = lay.update(HypothesisMesh.empty(K), {})
    assert ch.changed == [0] and not lay.segments[0].active
    assert lay.vertex_segments().shape == (0,)


def test_geometry_that_left_the_window_is_kept() -> None:
    """40 vertices, then only the first 20 are on the mesh: the other 20 are archived."""
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0)}
    full = row(40)
    lay.update(mesh_at((full, [(1, 1.0)])), tracks)
    lay.update(mesh_at((full[:20], [(1, 1.0)])), tracks)
    seg = lay.segments[0]
    assert seg.active and seg.num_vertices == 40
    np.testing.assert_array_equal(np.sort(seg.positions[:, 0]), np.sort(full[:, 0]))
    np.testing.assert_array_equal(seg.vertex_ids, np.arange(20))
    np.testing.assert_allclose(seg.centroid, full.mean(axis=0), rtol=1e-6)


def test_geometry_inside_the_window_but_off_the_mesh_is_dropped() -> None:
    """With the window given, the missing 20 vertices lie inside it: carved away, not archived."""
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0)}
    full = row(40)
    lay.update(mesh_at((full, [(1, 1.0)])), tracks)
    ch = lay.update(mesh_at((full[:20], [(1, 1.0)])), tracks, window=(np.zeros(3), 100.0))
    seg = lay.segments[0]
    assert ch.changed == [0] and seg.num_vertices == 20
    np.testing.assert_array_equal(seg.positions, full[:20])


def test_reobserved_geometry_is_replaced_not_duplicated() -> None:
    """The surface moves by 5 cm (< r_nn) between meshes: the old vertices are replaced."""
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0)}
    lay.update(mesh_at((row(30), [(1, 1.0)])), tracks)
    moved = row(30) + np.float32(0.05)
    lay.update(mesh_at((moved, [(1, 1.0)])), tracks)
    np.testing.assert_array_equal(lay.segments[0].positions, moved)


def test_vertices_lost_to_another_segment_are_dropped() -> None:
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0), 2: TrackState(2, dino=E1)}
    p = row(50)
    lay.update(mesh_at((p, [(1, 1.0)])), tracks)
    # Track 2 now wins the last 25 vertices (and is too dissimilar to join segment 0).
    lay.update(mesh_at((p[:25], [(1, 1.0)]), (p[25:], [(2, 2.0), (1, 1.0)])), tracks)
    np.testing.assert_array_equal(lay.segments[0].positions, p[:25])
    np.testing.assert_array_equal(lay.segments[1].positions, p[25:])


def test_dino_is_evidence_weighted_mean_including_displaced_weight() -> None:
    """Track 1: 20 vertices at l=2 plus 20 at l=0.5 -> 50. Track 2: 20 vertices at l=1 -> 20,
    plus 30 displaced -> 50. So f = unit(50 f1 + 50 f2)."""
    lay = new_layer()
    f2 = np.array([0.9, np.sqrt(0.19), 0, 0], np.float32)
    tracks = {1: TrackState(1, dino=E0), 2: TrackState(2, dino=f2, displaced_weight=30.0)}
    a, b = row(20), row(20, y=1.0)
    lay.update(mesh_at((a, [(1, 2.0)]), (b, [(2, 1.0), (1, 0.5)])), tracks)
    seg = lay.segments[0]
    assert seg.tracks == {1, 2}
    assert seg.track_weight(1) == pytest.approx(50.0)
    assert seg.track_weight(2) == pytest.approx(50.0)
    np.testing.assert_allclose(seg.dino, unit(50 * unit(E0) + 50 * unit(f2)), atol=1e-6)

    # Track 2 is fully displaced from the mesh (no slot left) and has lost 70 more: its last
    # mesh weight (20) plus the displaced 100 now count.
    tracks[2] = TrackState(2, dino=f2, displaced_weight=100.0)
    ch = lay.update(mesh_at((a, [(1, 2.0)])), tracks)
    assert seg.track_weight(1) == pytest.approx(40.0)
    assert seg.track_weight(2) == pytest.approx(120.0)
    np.testing.assert_allclose(seg.dino, unit(40 * unit(E0) + 120 * unit(f2)), atol=1e-6)
    assert 0 in ch.changed


def test_dino_follows_the_track_ema() -> None:
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0)}
    mesh = mesh_at((row(20), [(1, 1.0)]))
    lay.update(mesh, tracks)
    tracks[1].dino = unit([0.8, 0.6, 0, 0]).astype(np.float32)
    ch = lay.update(mesh, tracks)
    assert ch.changed == [0]
    np.testing.assert_allclose(lay.segments[0].dino, [0.8, 0.6, 0, 0], atol=1e-6)


def test_gallery_tracks_the_running_clip_mean() -> None:
    lay = new_layer()
    c1 = np.array([1, 0, 0], np.float32)
    tracks = {1: TrackState(1, dino=E0), 2: TrackState(2, dino=E0)}
    p = row(40)
    mesh1 = mesh_at((p[:20], [(1, 1.0)]))
    lay.update(mesh1, tracks)
    assert lay.segments[0].gallery == {}  # no CLIP feature yet
    assert lay.segments[0].to_node().gallery.shape[0] == 0

    tracks[1].clip, tracks[1].clip_count = c1, 1
    ch = lay.update(mesh1, tracks)
    assert ch.changed == [0]
    np.testing.assert_array_equal(lay.segments[0].gallery[1], c1)

    # Eq. 4: a second CLIP feature folds into the mean; the gallery row follows it.
    f = np.array([0, 1, 0], np.float32)
    tracks[1].clip, tracks[1].clip_count = (1 * c1 + f) / 2, 2
    ch = lay.update(mesh1, tracks)
    assert ch.changed == [0]
    np.testing.assert_array_equal(lay.segments[0].gallery[1], [0.5, 0.5, 0])
    assert lay.segments[0].gallery[1] is not tracks[1].clip  # a copy, not an alias

    # Track 2 joins the segment and brings its row.
    tracks[2].clip = np.array([0, 0, 1], np.float32)
    lay.update(mesh_at((p[:20], [(1, 1.0)]), (p[20:], [(2, 2.0), (1, 1.0)])), tracks)
    node = lay.segments[0].to_node()
    assert node.gallery_tracks == [1, 2]
    np.testing.assert_array_equal(node.gallery, [[0.5, 0.5, 0], [0, 0, 1]])


def test_historical_gallery_still_syncs() -> None:
    """CLIP features arrive asynchronously, possibly after the segment left the window."""
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0)}
    lay.update(mesh_at((row(20), [(1, 1.0)])), tracks)
    lay.update(HypothesisMesh.empty(K), tracks)
    tracks[1].clip = np.array([0, 1], np.float32)
    ch = lay.update(HypothesisMesh.empty(K), tracks)
    assert ch.changed == [0] and not lay.segments[0].active
    np.testing.assert_array_equal(lay.segments[0].gallery[1], [0, 1])


def test_forgotten_track_keeps_its_rows() -> None:
    lay = new_layer()
    tracks = {1: TrackState(1, dino=E0, clip=np.array([1, 0], np.float32))}
    mesh = mesh_at((row(20), [(1, 1.0)]))
    lay.update(mesh, tracks)
    before = lay.segments[0].dino.copy()
    ch = lay.update(mesh, {})
    assert ch.changed == []
    np.testing.assert_array_equal(lay.segments[0].gallery[1], [1, 0])
    np.testing.assert_array_equal(lay.segments[0].dino, before)


def test_gallery_score_is_max_cosine() -> None:
    rows = np.array([[1, 0], [0, 2], [0, 0]], np.float32)
    assert gallery_score(rows, np.array([0.0, 3.0])) == pytest.approx(1.0)
    assert gallery_score(rows, np.array([1.0, 1.0])) == pytest.approx(np.sqrt(0.5))
    assert gallery_score(np.zeros((0, 2), np.float32), np.array([1.0, 0.0])) == float("-inf")


def test_to_node_is_a_valid_segment_node() -> None:
    lay = new_layer()
    tracks = {4: TrackState(4, dino=E0, clip=np.array([0.6, 0.8], np.float32))}
    p = row(20, x0=1.0, y=2.0)
    lay.update(mesh_at((p, [(4, 1.0)])), tracks)
    node = lay.segments[0].to_node(room=3)
    assert isinstance(node, SegmentNode)
    assert node.id == 0 and node.tracks == [4] and node.gallery_tracks == [4]
    assert node.num_vertices == 20 and node.active and node.room == 3
    np.testing.assert_allclose(node.bbox_min, [1.0, 2.0, 0.0])
    np.testing.assert_allclose(node.bbox_max, [1.0 + 0.2 * 19, 2.0, 0.0], rtol=1e-6)
    np.testing.assert_allclose(node.centroid, [1.0 + 0.1 * 19, 2.0, 0.0], rtol=1e-6)
    assert node.dino.dtype == np.float32 and node.gallery.dtype == np.float32
    assert [n.id for n in lay.nodes()] == [0]


def _assert_state_equal(a, b) -> None:
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys()
        for k in a:
            _assert_state_equal(a[k], b[k])
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _assert_state_equal(x, y)
    else:
        assert type(a) is type(b) and a == b


def test_state_round_trip_is_exact() -> None:
    lay = SegmentLayer(SegmentsConfig(), ReidConfig())
    rng = np.random.default_rng(0)
    d = lambda: unit(rng.normal(size=8)).astype(np.float32)  # noqa: E731
    tracks = {
        t: TrackState(
            t, dino=d(), clip=rng.normal(size=5).astype(np.float32), displaced_weight=0.5 * t
        )
        for t in range(1, 6)
    }
    lay.update(mesh_at((row(30), [(1, 1.0)]), (row(25, y=1.0), [(2, 1.5), (1, 0.25)])), tracks)
    lay.update(mesh_at((row(30, y=40.0), [(3, 1.0)])), tracks)
    lay.update(mesh_at((row(22, y=40.0), [(3, 1.0)]), (row(21, y=80.0), [(4, 1.0)])), tracks)

    state = lay.state_dict()
    twin = SegmentLayer(SegmentsConfig(), ReidConfig())
    twin.load_state_dict(state)
    _assert_state_equal(twin.state_dict(), state)
    assert {s.id: s.active for s in twin.segments.values()} == {
        s.id: s.active for s in lay.segments.values()
    }

    # Both carry on identically, including ids handed out after the resume.
    mesh = mesh_at((row(30), [(1, 1.0)]), (row(20, y=120.0), [(5, 1.0)]))
    assert twin.update(mesh, tracks) == lay.update(mesh, tracks)
    _assert_state_equal(twin.state_dict(), lay.state_dict())
    assert max(twin.segments) == max(lay.segments)


def test_state_format_is_checked() -> None:
    lay = new_layer()
    with pytest.raises(ValueError, match="format"):
        lay.load_state_dict({"format": 99})
