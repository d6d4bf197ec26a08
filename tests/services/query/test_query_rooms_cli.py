"""``trackgraph query MAP_DIR TEXT --rooms`` and ``--in-room TEXT`` on a tiny saved map whose
rooms carry features written by the test; the encoder is a stand-in that embeds a handful of
words as unit axes, so every score is known here."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.cli import main
from shared.graph.store import MapStore
from shared.messages.graph import GraphSnapshot, RoomNode, SegmentNode

E = np.eye(4, dtype=np.float32)
WORDS = {"kitchen": E[0], "bedroom": E[1], "sink": E[2], "bed": E[3], "cooking or sleeping": (E[0] + E[1]) / np.sqrt(2)}


class AxesEncoder:
    """A VL encoder of four words; the map's own encoder in ``OfflineQueries``."""

    name = "axes"
    dim = 4

    def encode_text(self, texts: list[str]) -> np.ndarray:
        return np.stack([WORDS[t] for t in texts]).astype(np.float32)

    def encode_image(self, rgb: np.ndarray) -> np.ndarray:
        return E[1]


def seg(i: int, row: np.ndarray, room: int) -> SegmentNode:
    c = np.array([float(i), 0.0, 0.5])
    return SegmentNode(id=i, centroid=c, bbox_min=c - 0.2, bbox_max=c + 0.2, tracks=[i], dino=E[0],
                       gallery=row[None], gallery_tracks=[i], active=False, room=room)  # fmt: skip


def room(i: int, feature: np.ndarray | None, name: str) -> RoomNode:
    c = np.array([3.0 * i, 0.0, 1.2])
    return RoomNode(id=i, centroid=c, name=name, feature=feature, bbox_min=c - [1.5, 2.0, 1.2], bbox_max=c + [1.5, 2.0, 1.3])


def save_map(root, rooms: list[RoomNode]):
    """A map folder as ``trackgraph map`` leaves it, as far as ``trackgraph query`` reads it."""
    segments = [seg(1, E[2], 0), seg(2, E[3], 0), seg(3, E[2], 1), seg(4, E[3], 1)]  # a sink and a bed in each room
    MapStore(root / "graph", write_dsg=False).save(GraphSnapshot(graph_seq=9, frame_index=99, segments=segments, rooms=rooms))
    # No room labels: rooms rank by cosine here (the margin is pinned in test_query_rooms.py).
    (root / "config.yaml").write_text("keyframe_vl:\n  vl:\n    backend: simulated\nquery:\n  device: cpu\nfusion:\n  graph:\n    room_labels: []\n")
    return root


@pytest.fixture
def map_dir(tmp_path, monkeypatch):
    monkeypatch.setattr("shared.perception.encoders.make_vl_encoder", lambda *a, **kw: AxesEncoder())
    # Room 0 is mostly kitchen, room 1 the bedroom; room 2 has no feature yet.
    kitchen = (0.8 * E[0] + 0.6 * E[1]).astype(np.float32)
    return save_map(tmp_path / "map", [room(0, kitchen, "kitchen"), room(1, E[1], "bedroom"), room(2, None, "")])


def scores(text: str) -> dict[int, float]:
    q = WORDS[text]
    return {0: float(0.8 * q[0] + 0.6 * q[1]), 1: float(q[1])}


def test_rooms_json_ranks_the_rooms_with_a_feature(map_dir, capsys):
    for text in ("kitchen", "bedroom", "cooking or sleeping"):
        assert main(["query", str(map_dir), text, "--rooms", "--json"]) == 0
        rows = json.loads(capsys.readouterr().out)
        want = scores(text)
        order = sorted(want, key=lambda i: (-want[i], i))
        assert [r["room"] for r in rows] == order, text
        assert [r["score"] for r in rows] == pytest.approx([want[i] for i in order], abs=1e-6)
        assert all(set(r) == {"room", "score", "margin", "name", "centroid", "bbox"} for r in rows)
    first = rows[0]
    assert first["name"] == "kitchen" and first["centroid"] == [0.0, 0.0, 1.2]
    assert first["bbox"] == [[-1.5, -2.0, 0.0], [1.5, 2.0, 2.5]]
    assert main(["query", str(map_dir), "bedroom", "--rooms", "--json", "--top-k", "1"]) == 0
    assert [r["room"] for r in json.loads(capsys.readouterr().out)] == [1]


def test_rooms_table(map_dir, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "160")  # one line per room, whatever the terminal
    assert main(["query", str(map_dir), "bedroom", "--rooms"]) == 0
    out = capsys.readouterr().out
    assert "bedroom" in out and "kitchen" in out and "1.000" in out and "0.600" in out
    assert "3.00 x 4.00 x 2.50" in out  # the rooms' size from their boxes


def test_in_room_keeps_the_hit_rows_and_says_which_room(map_dir, capsys):
    assert main(["query", str(map_dir), "sink", "--json"]) == 0
    everywhere = json.loads(capsys.readouterr().out)
    assert main(["query", str(map_dir), "sink", "--in-room", "bedroom", "--json"]) == 0
    captured = capsys.readouterr()
    rows = json.loads(captured.out)  # stdout is only the contract's list of hit rows
    assert [r["segment"] for r in rows] == [3, 4] and all(r["room"] == 1 for r in rows)
    assert [set(r) for r in rows] == [set(everywhere[0])] * 2  # the same row shape as without --in-room
    assert "room 1 (bedroom, 1.000)" in captured.err  # logged, not printed
    assert main(["query", str(map_dir), "sink", "--in-room", "kitchen"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == "in room 0 (kitchen, 0.800)"


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--in-room", "kitchen", "--room", "1"], "--in-room TEXT and --room ID"),
        (["--in-room", "kitchen", "--rooms"], "--in-room TEXT filters segments"),
        (["--rooms", "--room", "1"], "room (a filter of segments) does not apply"),
    ],
)
def test_conflicting_room_flags_exit_with_one_line(map_dir, capsys, extra, words):
    assert main(["query", str(map_dir), "sink", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


def test_in_room_on_a_map_without_room_features_says_why(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr("shared.perception.encoders.make_vl_encoder", lambda *a, **kw: AxesEncoder())
    bare = save_map(tmp_path / "bare", [room(0, None, ""), room(1, None, "")])
    capsys.readouterr()  # what saving logged through an earlier command's log handler
    assert main(["query", str(bare), "sink", "--in-room", "kitchen"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no room has a feature yet" in err[0]
    assert main(["query", str(bare), "kitchen", "--rooms", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == []
