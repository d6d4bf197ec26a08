"""Room features and names from segments and keyframe views (services/fusion/layers/roomnames.py)."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.layers.roomnames import (
    VIEW_RIDGE,
    RoomLookup,
    RoomVocabulary,
    describe_rooms,
    room_features,
    rooms_of_positions,
    unmix_views,
    view_shares,
)
from shared.graph.scene import SceneGraph
from shared.messages.graph import RoomNode, SegmentNode

D = 4
E = np.eye(D, dtype=np.float32)


def seg(sid: int, room: int | None, rows: list[np.ndarray]) -> SegmentNode:
    g = np.stack(rows).astype(np.float32) if rows else np.zeros((0, D), np.float32)
    return SegmentNode(
        id=sid, centroid=np.zeros(3), bbox_min=np.zeros(3), bbox_max=np.ones(3), tracks=list(range(max(len(rows), 1))), active=True,
        dino=E[0], gallery=g, gallery_tracks=list(range(len(rows))), gallery_weights=[1.0] * len(rows), room=room,
    )  # fmt: skip


def room(rid: int, name: str = "") -> RoomNode:
    return RoomNode(id=rid, centroid=np.zeros(3), name=name)


def test_contents_weigh_each_segment_once() -> None:
    """Room 1 holds a segment of three identical rows along e0 and one of a row along e1: the
    content feature is unit(e0 + e1), not (3 e0 + e1); room 2 has a segment without a gallery."""
    segs = {1: seg(1, 1, [E[0]] * 3), 2: seg(2, 1, [E[1]]), 3: seg(3, 2, []), 4: seg(4, None, [E[2]])}
    f = room_features([1, 2], segs, np.zeros((0, 2)), np.zeros((0, D)), view_weight=0.5)
    assert set(f) == {1}
    np.testing.assert_allclose(f[1], np.array([1, 1, 0, 0]) / np.sqrt(2), atol=1e-6)


@pytest.mark.parametrize("w", [0.25, 0.5, 0.8])
def test_views_and_contents_mix_by_the_view_weight(w: float) -> None:
    """Contents along e0; two views wholly of room 7 (2 e2 and e2 + e3) and one of room 3:
    room 7's look is the ridge solution (2 + lambda) f = 2 e2 + (e2 + e3), unit; the feature is
    unit((1 - w) e0 + w look)."""
    segs = {1: seg(1, 7, [E[0]])}
    views = np.stack([2 * E[2], E[2] + E[3], E[1]])
    shares = np.array([[0.0, 1.0], [0.0, 1.0], [1.0, 0.0]])  # columns: rooms 3, 7
    f = room_features([3, 7], segs, shares, views, view_weight=w)
    v = 3 * E[2] + E[3]
    want = (1 - w) * E[0] + w * v / np.linalg.norm(v)
    np.testing.assert_allclose(f[7], want / np.linalg.norm(want), atol=1e-6)
    np.testing.assert_allclose(f[3], E[1], atol=1e-6)  # views alone


def test_unmixing_gives_a_glimpsed_room_its_own_look() -> None:
    """Room A (e0) fills most of every view, room B (e1) 10-30% of three: each view is the
    share-weighted mix. B's look by unmixing is e1 up to the ridge's pull; the share-weighted
    mean of the views it appears in would point at A."""
    a, b = E[0].astype(np.float64), E[1].astype(np.float64)
    s_b = np.array([0.1, 0.2, 0.3, 0.0])
    shares = np.stack([1 - s_b, s_b], axis=1)
    views = shares @ np.stack([a, b])
    looks = unmix_views(shares, views, ridge=1e-6)
    np.testing.assert_allclose(looks, np.stack([a, b]), atol=1e-4)
    naive = (s_b[:, None] * views).sum(0)
    assert naive @ a > naive @ b  # the mean would have called B room A
    # With the default ridge B is still nearer its own look than A's.
    looks = unmix_views(shares, views)
    assert looks[1] @ b > 0.9 and looks[1] @ a < 0.3
    # A room no view shows gets no look.
    assert not unmix_views(np.c_[shares, np.zeros(4)], views).any(axis=1)[2]
    assert VIEW_RIDGE > 0


def test_view_shares_count_the_points_each_room_holds() -> None:
    """Rooms 10 (columns 0-3) and 20 (columns 6-9) on a 0.25 m grid: a view with 3 points in
    room 10, 1 in room 20 and 2 on no room has shares 0.75 / 0.25; one that sees no room
    counts for the camera's room; with the camera outside as well, none."""
    lab = np.full((4, 10), -1, np.int32)
    lab[:, :4] = 0
    lab[:, 6:] = 1
    ids = np.array([10, 20])
    seen = np.array([[0, 0], [1, 1], [2, 2], [3, 8], [20, 20], [-5, 0]])
    np.testing.assert_allclose(view_shares(lab, ids, [10, 20], seen, np.array([0, 0]), 0.25), [0.75, 0.25])
    nothing = np.array([[20, 20]])
    np.testing.assert_allclose(view_shares(lab, ids, [10, 20], nothing, np.array([2, 8]), 0.25), [0.0, 1.0])
    np.testing.assert_allclose(view_shares(lab, ids, [10, 20], nothing, np.array([30, 30]), 0.25), [0.0, 0.0])


def test_the_views_of_one_update_share_one_distance_transform(monkeypatch) -> None:
    """The shares through a shared lookup equal each view's own, and the room grid's
    distance transform runs once for all views, not once per view (hundreds of keyframes
    over a building)."""
    from services.fusion.layers import roomnames

    rng = np.random.default_rng(5)
    lab = np.full((40, 30), -1, np.int32)
    lab[2:15, 3:20], lab[20:38, 5:28] = 0, 1
    ids = np.array([10, 20])
    views = [rng.integers(-3, 45, (25, 2)) for _ in range(12)]
    cams = [rng.integers(0, 40, 2) for _ in range(12)]
    own = [view_shares(lab, ids, [10, 20], v, c, 0.1) for v, c in zip(views, cams, strict=True)]
    calls = []
    edt = roomnames.ndimage.distance_transform_edt
    monkeypatch.setattr(roomnames.ndimage, "distance_transform_edt", lambda *a, **k: calls.append(1) or edt(*a, **k))
    lookup = RoomLookup(lab, ids, 0.1)
    shared = [view_shares(lab, ids, [10, 20], v, c, 0.1, lookup) for v, c in zip(views, cams, strict=True)]
    assert len(calls) == 1
    for a, b in zip(own, shared, strict=True):
        np.testing.assert_array_equal(a, b)
    assert sum(float(s.sum()) for s in own) > 5  # most views see a room


def test_views_alone_and_names() -> None:
    """A room with views only takes their look; the name is the nearest label and its score
    that cosine; a room with neither source has no feature and no name."""
    labels = ("kitchen", "bedroom", "office")
    vocab = RoomVocabulary(labels, np.stack([E[0], E[1], (E[1] + E[2]) / np.sqrt(2)]))
    views = np.stack([E[1] + 0.2 * E[2]])
    out = describe_rooms({5: room(5), 6: room(6, "stale")}, {}, np.array([[1.0, 0.0]]), views, vocab, 0.5)
    f = views[0] / np.linalg.norm(views[0])
    assert out[5].name == "bedroom"
    assert out[5].name_score == pytest.approx(float(f @ E[1]))
    np.testing.assert_allclose(out[5].feature, f, atol=1e-6)
    assert out[6].feature is None and out[6].name == "" and out[6].name_score is None


def test_without_a_vocabulary_a_room_keeps_its_previous_name() -> None:
    segs = {1: seg(1, 2, [E[3]])}
    out = describe_rooms({2: room(2)}, segs, np.zeros((0, 1)), np.zeros((0, D)), None, 0.5, previous={2: room(2, "office")})
    assert out[2].name == "office"
    assert out[2].feature is not None


def test_vocabulary_of_another_dimension_names_nothing() -> None:
    vocab = RoomVocabulary(("kitchen",), np.ones((1, D + 1), np.float32))
    out = describe_rooms({2: room(2)}, {1: seg(1, 2, [E[0]])}, np.zeros((0, 1)), np.zeros((0, D)), vocab, 0.5)
    assert out[2].name == "" and out[2].feature is not None


def test_vocabulary_checks_its_shape() -> None:
    with pytest.raises(ValueError, match="2 labels"):
        RoomVocabulary(("a", "b"), np.ones((3, D), np.float32))


def test_rooms_of_positions_reach_past_the_room_cells() -> None:
    """Rooms 10 (columns 0-3) and 20 (columns 6-9) on a 0.25 m grid, a wall gap at 4-5: a
    camera on column 5 is 0.25 m from room 20's cells, within a 0.3 m reach; with 0.2 m none;
    a cell outside the grid has no room."""
    lab = np.full((4, 10), -1, np.int32)
    lab[:, :4] = 0
    lab[:, 6:] = 1
    ids = np.array([10, 20])
    cells = np.array([[1, 1], [1, 5], [2, 8], [9, 9], [-1, 0]])
    np.testing.assert_array_equal(rooms_of_positions(lab, ids, cells, 0.25, reach_m=0.3), [10, 20, 20, -1, -1])
    np.testing.assert_array_equal(rooms_of_positions(lab, ids, cells, 0.25, reach_m=0.2), [10, -1, 20, -1, -1])


def test_scene_graph_describes_rooms_with_the_segments_new_rooms() -> None:
    """The describer sees each segment with the room of its place in this update."""
    from shared.graph.scene import PlaceGraph
    from shared.messages.graph import PlaceNode

    g = SceneGraph()
    places = PlaceGraph(nodes=[PlaceNode(id=0, position=np.zeros(3), radius=1.0, room=3)], edges=[], locate=None)
    seen = {}

    def describer(segs, rooms, previous):
        seen["rooms_of_segments"] = {s.id: s.room for s in segs.values()}
        seen["previous"] = dict(previous)
        return {rid: r.model_copy(update={"name": f"room {rid}"}) for rid, r in rooms.items()}

    delta = g.apply_update(segments_changed=[seg(1, None, [E[0]])], places=places, rooms=[room(3)], describe_rooms=describer)
    assert seen == {"rooms_of_segments": {1: 3}, "previous": {}}
    assert [r.name for r in delta.rooms] == ["room 3"]
    assert g.rooms[3].name == "room 3"


def test_a_map_without_rooms_has_nothing_to_describe() -> None:
    """No rooms yet (nothing mapped): no shares to reshape, no features, whatever the views."""
    assert room_features([], {1: seg(1, None, [E[0]])}, np.zeros((0, 0)), np.zeros((0, 0)), 0.5) == {}
    assert describe_rooms({}, {}, np.zeros((3, 0)), np.ones((3, D)), None, 0.5) == {}
