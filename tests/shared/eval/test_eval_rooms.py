"""``trackgraph eval rooms``: hand-made room grids against hand-made footprints, every IoU
worked out here on a 1 m lattice (a cell counts for a polygon when its centre is inside)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shared.eval.errors import EvalInputError
from shared.eval.rooms import (
    eval_rooms,
    load_gt_rooms,
    points_in_polygon,
    rasterise,
)
from shared.graph.roomgrid import RoomGrid, save_room_grid


def rect(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


# Ground truth: A is x 0..4, y 0..2 (8 cells), B is x 4..8, y 0..2 (8 cells).
A, B = rect(0, 0, 4, 2), rect(4, 0, 8, 2)


def write_gt(folder: Path, rooms: list[tuple[str, str, list]]) -> Path:
    gt = folder / "gt"
    gt.mkdir(parents=True)
    body = {"format": "trackgraph-rooms", "version": 1, "frame": "world, metres, z up",
            "rooms": [{"id": i, "name": n, "type": t, "footprint": f} for i, (n, t, f) in enumerate(rooms)]}  # fmt: skip
    (gt / "rooms.json").write_text(json.dumps(body))
    return folder


def write_map(folder: Path, columns: list[int], *, height: int = 2, names: dict[int, str] | None = None) -> Path:
    """A map whose room grid is 1 m cells from the origin, ``columns[i]`` the room id of every
    cell of column i (x in [i, i + 1))."""
    labels = np.repeat(np.array(columns, np.int32)[:, None], height, axis=1)
    ids = np.array(sorted({c for c in columns if c >= 0}), np.int64)
    names_list = [names.get(int(i), "") for i in ids] if names else []
    save_room_grid(folder / "rooms.npz", RoomGrid(labels, np.zeros(2), 1.0, ids, names_list))
    return folder


def test_rasterise_counts_cell_centres_inside():
    assert len(rasterise(np.array(A, float), np.zeros(2), 1.0)) == 8
    # x + y < 4.2 holds at the centres (i + 0.5, j + 0.5) with i + j <= 3: 10 of them, and a
    # clockwise outline gives the same cells.
    tri = np.array([[0, 0], [4.2, 0], [0, 4.2]], float)
    cells = rasterise(tri, np.zeros(2), 1.0)
    assert len(cells) == 10 and (cells.sum(axis=1) <= 3).all()
    np.testing.assert_array_equal(rasterise(tri[::-1], np.zeros(2), 1.0), cells)
    # An L-shaped room: the notch is outside.
    ell = np.array([[0, 0], [3, 0], [3, 1], [1, 1], [1, 3], [0, 3]], float)
    inside = points_in_polygon(np.array([[0.5, 0.5], [2.5, 0.5], [0.5, 2.5], [2.5, 2.5], [1.5, 1.5]]), ell)
    assert inside.tolist() == [True, True, True, False, False]


def test_a_perfect_map(tmp_path):
    gt = write_gt(tmp_path / "seq", [("room0", "office", A), ("hall", "hall", B)])
    pred = write_map(tmp_path / "map", [3, 3, 3, 3, 8, 8, 8, 8], names={3: "office", 8: "hall"})
    r = eval_rooms(pred, gt)
    assert (r["precision"], r["recall"], r["f1"], r["mean_iou"]) == (1.0, 1.0, 1.0, 1.0)
    assert (r["n_pred"], r["n_gt"], r["n_matched"], r["over_segmented"], r["under_segmented"]) == (2, 2, 2, 0, 0)
    assert r["type_accuracy"] == 1.0
    assert [(p["gt_name"], p["gt_type"], p["best_pred_id"], p["iou"], p["matched_pred_id"]) for p in r["per_room"]] == [
        ("room0", "office", 3, 1.0, 3), ("hall", "hall", 8, 1.0, 8)]  # fmt: skip
    json.dumps(r)


def test_a_room_split_in_two_is_over_segmented(tmp_path):
    # A is split into room 1 (x 0..3, 6 cells, IoU 6/8) and room 2 (x 3..4, 2 cells, IoU 2/8);
    # B is room 3 exactly. Matches: 1-A and 3-B; room 2 is a false positive.
    gt = write_gt(tmp_path / "seq", [("room0", "office", A), ("room1", "bedroom", B)])
    pred = write_map(tmp_path / "map", [1, 1, 1, 2, 3, 3, 3, 3], names={1: "office", 2: "office", 3: "dining room"})
    r = eval_rooms(pred, gt)
    assert r["precision"] == pytest.approx(2 / 3) and r["recall"] == 1.0
    assert r["f1"] == pytest.approx(2 * (2 / 3) / (2 / 3 + 1)) and r["f1"] == pytest.approx(0.8)
    assert r["over_segmented"] == 1 and r["over_segmented_rooms"] == ["room0"] and r["under_segmented"] == 0
    assert r["mean_iou"] == pytest.approx((0.75 + 1.0) / 2)
    assert r["per_room"][0]["best_pred_id"] == 1 and r["per_room"][0]["iou"] == pytest.approx(0.75)
    # room 1 is named right ("office"), room 3 wrong ("dining room" for a bedroom)
    assert r["type_accuracy"] == pytest.approx(0.5)
    # At IoU 0.8 only B still matches.
    strict = eval_rooms(pred, gt, iou=0.8)
    assert strict["n_matched"] == 1 and strict["recall"] == pytest.approx(0.5) and strict["per_room"][0]["matched_pred_id"] is None


def test_two_rooms_merged_are_under_segmented(tmp_path):
    # B2 is x 4..6 (4 cells); room 5 covers A and B2 (12 cells): IoU 8/12 with A, 4/12 with B2.
    gt = write_gt(tmp_path / "seq", [("room0", "living room", A), ("hall", "hall", rect(4, 0, 6, 2))])
    pred = write_map(tmp_path / "map", [5, 5, 5, 5, 5, 5])
    r = eval_rooms(pred, gt)
    assert (r["n_pred"], r["n_gt"], r["n_matched"]) == (1, 2, 1)
    assert r["precision"] == 1.0 and r["recall"] == 0.5 and r["f1"] == pytest.approx(2 / 3)
    assert r["under_segmented"] == 1 and r["under_segmented_rooms"] == [5] and r["over_segmented"] == 0
    assert [p["iou"] for p in r["per_room"]] == pytest.approx([8 / 12, 4 / 12])
    assert r["per_room"][1]["best_pred_id"] == 5 and r["per_room"][1]["matched_pred_id"] is None
    assert r["mean_iou"] == pytest.approx(0.5)
    assert r["type_accuracy"] is None and not r["named_rooms"], "the grid carries no names"


def test_ground_truth_beyond_the_grid_still_counts(tmp_path):
    # The map only reached x 0..2 of A: 4 of its 8 cells, IoU 4/8, nothing of B.
    gt = write_gt(tmp_path / "seq", [("room0", "office", A), ("room1", "office", B)])
    pred = write_map(tmp_path / "map", [0, 0])
    r = eval_rooms(pred, gt)
    assert r["per_room"][0]["iou"] == pytest.approx(0.5) and r["per_room"][0]["gt_cells"] == 8
    assert r["per_room"][1]["best_pred_id"] is None and r["per_room"][1]["iou"] == 0.0
    assert r["n_matched"] == 1 and r["recall"] == 0.5 and r["mean_iou"] == pytest.approx(0.25)


def test_a_map_without_rooms(tmp_path):
    gt = write_gt(tmp_path / "seq", [("room0", "office", A)])
    pred = write_map(tmp_path / "map", [-1, -1, -1])
    r = eval_rooms(pred, gt)
    assert (r["n_pred"], r["precision"], r["recall"], r["f1"], r["mean_iou"]) == (0, None, 0.0, 0.0, 0.0)
    assert r["per_room"][0]["best_pred_id"] is None


def test_scene_json_fallback(tmp_path):
    gt = tmp_path / "old" / "gt"
    gt.mkdir(parents=True)
    scene = {"rooms": [{"name": "room0", "kind": "dining", "footprint": rect(-0.5, -0.5, 4.5, 2.5), "inner": [0, 0, 4, 2]},
                       {"name": "hall", "kind": "hall", "footprint": rect(3.5, -0.5, 8.5, 2.5), "inner": [4, 0, 8, 2]}]}  # fmt: skip
    (gt / "scene.json").write_text(json.dumps(scene))
    rooms = load_gt_rooms(tmp_path / "old")
    assert [(r.id, r.name, r.type) for r in rooms] == [(0, "room0", "dining room"), (1, "hall", "hall")]
    np.testing.assert_array_equal(rooms[0].footprint, np.array(A, float))
    pred = write_map(tmp_path / "map", [1, 1, 1, 1, 2, 2, 2, 2])
    assert eval_rooms(pred, tmp_path / "old")["f1"] == 1.0
    # rooms.json wins when both are there
    write_gt(tmp_path / "both", [("only", "office", A)])
    (tmp_path / "both" / "gt" / "scene.json").write_text(json.dumps(scene))
    assert [r.name for r in load_gt_rooms(tmp_path / "both" / "gt")] == ["only"]


@pytest.mark.parametrize(
    "body, message",
    [
        ("{not json", "not valid JSON"),
        ('{"format": "trackgraph-rooms"}', "missing field 'rooms'"),
        ('{"rooms": []}', "lists no rooms"),
        ('{"rooms": [{"id": 0, "name": "a", "footprint": [[0, 0], [1, 0], [1, 1]]}]}', "rooms[0]: missing field 'type'"),
        ('{"rooms": [{"id": 0, "name": "a", "type": "hall", "footprint": [[0, 0], [1, 0]]}]}', "rooms[0].footprint"),
        ('{"rooms": [{"id": "0", "name": "a", "type": "hall", "footprint": []}]}', "rooms[0].id: expected int"),
    ],
)
def test_bad_ground_truth_names_the_file(tmp_path, body, message):
    (tmp_path / "rooms.json").write_text(body)
    with pytest.raises(EvalInputError, match=str(tmp_path / "rooms.json")) as err:
        load_gt_rooms(tmp_path)
    assert message in str(err.value)


def test_bad_scene_and_missing_files_name_them(tmp_path):
    (tmp_path / "scene.json").write_text(json.dumps({"rooms": [{"name": "x", "kind": "kitchen", "inner": [0, 0, 1, 1]}]}))
    with pytest.raises(EvalInputError, match=r"scene\.json: rooms\[0\]\.kind: 'kitchen'"):
        load_gt_rooms(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(EvalInputError, match="neither rooms.json nor scene.json"):
        load_gt_rooms(empty)
    gt = write_gt(tmp_path / "seq", [("room0", "office", A)])
    old_map = tmp_path / "old_map"
    old_map.mkdir()
    with pytest.raises(EvalInputError, match="rooms.npz: missing: the map was written before room footprints were saved; map again"):
        eval_rooms(old_map, gt)
    (old_map / "rooms.npz").write_bytes(b"garbage")
    with pytest.raises(EvalInputError, match=r"rooms\.npz: not a readable"):
        eval_rooms(old_map, gt)


def test_command_line(tmp_path, capsys):
    from services.cli import main

    gt = write_gt(tmp_path / "seq", [("room0", "office", A), ("room1", "bedroom", B)])
    pred = write_map(tmp_path / "map", [1, 1, 1, 2, 3, 3, 3, 3])
    assert main(["eval", "rooms", "--pred", str(pred), "--gt", str(gt), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["f1"] == pytest.approx(0.8) and out["over_segmented"] == 1
    assert [r["gt_name"] for r in out["per_room"]] == ["room0", "room1"]
    assert main(["eval", "rooms", "--pred", str(pred), "--gt", str(gt)]) == 0
    table = capsys.readouterr().out
    assert "room0" in table and "0.750" in table and "bedroom" in table
    assert main(["eval", "rooms", "--pred", str(tmp_path / "seq"), "--gt", str(gt)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "rooms.npz: missing" in err


def test_room_type_queries_hit_only_a_room_matched_to_that_type(tmp_path):
    """Three ground-truth rooms, two bedrooms and an office; the map has rooms 3 (matched to
    bedroom A), 8 (to the office B) and 9, which covers only a quarter of bedroom C (IoU 0.25,
    unmatched). "bedroom" answered by room 9 misses even though 9 lies in a bedroom; "office"
    answered by 8 hits. Without a ranker there are no room queries."""
    C = rect(8, 0, 12, 2)
    gt = write_gt(tmp_path / "seq", [("a", "bedroom", A), ("b", "office", B), ("c", "bedroom", C)])
    pred = write_map(tmp_path / "map", [3, 3, 3, 3, 8, 8, 8, 8, 9, -1, -1, -1])
    ranked = {"bedroom": [9, 3, 8], "office": [8, 3]}
    asked = []

    def rank(text):
        asked.append(text)
        return ranked[text]

    r = eval_rooms(pred, gt, rank_rooms=rank)
    assert asked == ["bedroom", "office"]
    assert r["room_type_top1"] == 0.5
    assert [(q["query"], q["top_room"], q["gt_room"], q["hit"]) for q in r["room_queries"]] == [
        ("bedroom", 9, None, False), ("office", 8, "b", True)]  # fmt: skip
    ranked["bedroom"] = [3, 9]
    assert eval_rooms(pred, gt, rank_rooms=rank)["room_type_top1"] == 1.0
    ranked["office"] = []  # a map whose rooms have no features answers nothing
    assert eval_rooms(pred, gt, rank_rooms=rank)["room_type_top1"] == 0.5
    assert eval_rooms(pred, gt)["room_queries"] is None and eval_rooms(pred, gt)["room_type_top1"] is None
