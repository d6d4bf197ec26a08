"""The query core (eq. 10): gallery max against the mean ablation, filters, ranking order,
and clear refusals for bad queries."""

from __future__ import annotations

import numpy as np
import pytest

from services.query.core import QueryEngine, QueryError, QueryIndex, hit_rows
from shared.config.query import QueryConfig
from shared.messages.graph import SegmentNode
from shared.messages.rpc import EmbedRequest, QueryRequest

E = np.eye(4, dtype=np.float32)


def seg(i: int, rows: list[np.ndarray], room: int | None = None, at: tuple = (0.0, 0.0, 0.0)) -> SegmentNode:
    c = np.asarray(at, np.float64)
    tracks = [10 * i + k for k in range(len(rows))]
    return SegmentNode(
        id=i, centroid=c, bbox_min=c - 0.1, bbox_max=c + 0.1, tracks=tracks, dino=E[0],
        gallery=np.stack(rows).astype(np.float32) if rows else np.zeros((0, 4), np.float32),
        gallery_tracks=tracks, active=True, room=room,
    )  # fmt: skip


def unit(v) -> np.ndarray:
    v = np.asarray(v, np.float32)
    return v / np.linalg.norm(v)


def engine(**cfg) -> QueryEngine:
    texts = {"x": E[0], "y": E[1], "mix": unit([1, 1, 0, 0]), "short": np.ones(3, np.float32)}

    def embed(req: EmbedRequest) -> np.ndarray:
        if req.text is None:
            return E[2]
        return texts[req.text]

    return QueryEngine(QueryConfig(**cfg), embed)


# Segment 1 saw the object from two views, one of them like "x"; segment 2 is "x"-ish on
# average but never clearly; segment 3 is "y"; segment 4 has no CLIP feature yet.
SEGMENTS = [
    seg(1, [E[0], E[1]], room=0, at=(0, 0, 0)),
    seg(2, [unit([0.8, 0.6, 0, 0]), unit([0.8, -0.6, 0, 0])], room=1, at=(5, 0, 0)),
    seg(3, [E[1]], room=1, at=(5, 1, 0)),
    seg(4, [], room=0),
]


def test_eq10_max_over_the_gallery_and_the_best_view():
    index = QueryIndex.build(7, SEGMENTS, [0, 1])
    assert len(index) == 3 and index.dim == 4  # the segment without a gallery is not ranked
    reply = engine().answer(index, QueryRequest(text="x"))
    assert reply.error is None and reply.graph_seq == 7
    assert [h.segment for h in reply.hits] == [1, 2, 3]
    assert reply.hits[0].score == pytest.approx(1.0) and reply.hits[0].best_track == 10
    assert reply.hits[1].score == pytest.approx(0.8)
    y = engine().answer(index, QueryRequest(text="y")).hits
    assert [h.segment for h in y][:2] == [1, 3] and y[0].best_track == 11  # segment 1's other view


def test_mean_gallery_ablation_ranks_the_consistent_segment_first():
    index = QueryIndex.build(1, SEGMENTS)
    mean = engine(gallery="mean").answer(index, QueryRequest(text="x")).hits
    # Segment 2's two views average (normalised) to exactly "x"; segment 1's lie 45 degrees off.
    assert [h.segment for h in mean][:2] == [2, 1]
    assert mean[0].score == pytest.approx(1.0) and mean[1].score == pytest.approx(np.sqrt(0.5), abs=1e-6)
    # A request can pick the scoring itself.
    assert engine(gallery="mean").answer(index, QueryRequest(text="x", gallery="max")).hits[0].segment == 1


def test_filters_and_top_k():
    index = QueryIndex.build(1, SEGMENTS, [0, 1, 2])
    eng = engine()
    assert [h.segment for h in eng.answer(index, QueryRequest(text="x", room=1)).hits] == [2, 3]
    assert eng.answer(index, QueryRequest(text="x", room=2)).hits == []  # a room with no segment
    near = eng.answer(index, QueryRequest(text="x", center=np.array([5.0, 0.2, 0.0]), radius=0.5)).hits
    assert [h.segment for h in near] == [2]
    assert len(eng.answer(index, QueryRequest(text="x", top_k=2)).hits) == 2
    assert len(engine(default_top_k=1).answer(index, QueryRequest(text="x")).hits) == 1


def test_views_of_tracks_that_barely_make_up_a_segment_do_not_speak_for_it():
    # A wall segment that absorbed a clock's track: 99% wall, 1% clock.
    wall = seg(1, [E[0], E[1]]).model_copy(update={"gallery_weights": [0.99, 0.01]})
    clock = seg(2, [unit([0.1, 0.9, 0, 0])])
    for share, top in ((0.0, 1), (0.02, 2)):
        index = QueryIndex.build(1, [wall, clock], min_view_share=share)
        assert engine().answer(index, QueryRequest(text="y")).hits[0].segment == top
    # A segment always keeps its best-supported view, however small all shares are.
    thin = seg(3, [E[2], E[3]]).model_copy(update={"gallery_weights": [0.01, 0.015]})
    (kept,) = QueryIndex.build(1, [thin], min_view_share=0.5).segments
    assert kept.gallery_tracks == [31] and kept.gallery_weights == [0.015]


def test_equal_scores_rank_by_segment_id():
    index = QueryIndex.build(1, [seg(5, [E[0]]), seg(2, [E[0]]), seg(9, [E[0]])])
    assert [h.segment for h in engine().answer(index, QueryRequest(text="x")).hits] == [2, 5, 9]


@pytest.mark.parametrize(
    "req, words",
    [
        (QueryRequest(text="x" * 600), "600 characters"),
        (QueryRequest(text="x", top_k=1000), "top_k 1000"),
        (QueryRequest(text="x", room=42), "unknown room 42"),
        (QueryRequest(text="short"), "3-d"),
        (QueryRequest(image=np.zeros((3000, 3000, 3), np.uint8)), "9000000 pixels"),
    ],
)
def test_bad_queries_are_refused_with_the_reason(req, words):
    reply = engine(max_image_pixels=1000 * 1000).answer(QueryIndex.build(1, SEGMENTS, [0, 1]), req)
    assert reply.hits == [] and words in reply.error


def test_empty_and_malformed_requests_fail_validation():
    with pytest.raises(ValueError, match="empty"):
        QueryRequest(text="   ")
    with pytest.raises(ValueError, match="exactly one"):
        QueryRequest()
    with pytest.raises(ValueError, match="center and radius"):
        QueryRequest(text="x", radius=1.0)


def test_embedding_failure_is_a_reply_not_an_exception():
    def broken(req: EmbedRequest) -> np.ndarray:
        raise QueryError("cannot embed the query: encoder down")

    reply = QueryEngine(QueryConfig(), broken).answer(QueryIndex.build(1, SEGMENTS), QueryRequest(text="x"))
    assert "encoder down" in reply.error


def test_index_refuses_mixed_dimensions_and_empty_graph_answers_nothing():
    with pytest.raises(QueryError, match="segment 2"):
        QueryIndex.build(1, [seg(1, [E[0]]), seg(2, [np.ones(3)])])
    assert engine().answer(QueryIndex.empty(), QueryRequest(text="x")).hits == []


def test_json_rows_have_the_contract_keys():
    hits = engine().answer(QueryIndex.build(1, SEGMENTS), QueryRequest(text="x", top_k=1)).hits
    (row,) = hit_rows(hits)
    assert {"segment", "score", "centroid", "bbox"} <= set(row)
    assert row["segment"] == 1 and len(row["bbox"]) == 2 and len(row["centroid"]) == 3


def test_a_rebuild_reuses_unchanged_segments_and_equals_a_fresh_build():
    first = QueryIndex.build(1, SEGMENTS, min_view_share=0.0)
    changed = seg(2, [unit([0.1, 0.9, 0.3, 0]), E[3], E[0]], room=0, at=(1, 2, 3))
    now = [SEGMENTS[0], changed, seg(7, [E[2]])]  # 3 and 4 gone, 2 changed, 7 new
    again = QueryIndex.build(2, now, [0, 1], previous=first)
    fresh = QueryIndex.build(2, now, [0, 1])
    assert again.blocks[1] is first.blocks[1]  # same segment object: not normalised again
    assert again.blocks[2] is not first.blocks[2] and set(again.blocks) == {1, 2, 7}
    for name in ("gallery", "row_start", "row_segment", "mean", "centroids", "rooms"):
        np.testing.assert_array_equal(getattr(again, name), getattr(fresh, name), err_msg=name)
    assert [s.id for s in again.segments] == [1, 2, 7] and again.room_ids == fresh.room_ids
    for text in ("x", "y", "mix"):
        assert engine().answer(again, QueryRequest(text=text)) == engine().answer(fresh, QueryRequest(text=text))
