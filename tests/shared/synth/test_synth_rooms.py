"""``gt/rooms.json``: every room of the layout with its type and inner floor, readable by the
room evaluation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.synth import run_synth
from shared.synth.config import PRESETS, preset_config
from shared.synth.layout import ROOM_TYPES, build_layout
from shared.synth.pipeline import rooms_json

TINY = {"camera": {"frames": 3, "width": 64, "height": 48}, "gt": {"point_spacing": 0.05}}
"""The cheapest sequence the synth tests make (three thumbnail frames)."""


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_layout_gets_typed_rooms(preset):
    cfg = preset_config(preset)
    layout = build_layout(cfg.layout, np.random.default_rng(4))
    body = rooms_json(layout)
    assert [r["name"] for r in body["rooms"]] == [r.name for r in layout.rooms]
    assert all(r["type"] == ROOM_TYPES[r["kind"]] for r in body["rooms"])
    if cfg.layout.kind == "revisit":
        assert "corridor" in [r["type"] for r in body["rooms"]]
    for room, r in zip(body["rooms"], layout.rooms, strict=True):
        x0, y0, x1, y1 = r.rect
        h = cfg.layout.wall_thickness / 2
        np.testing.assert_allclose(room["footprint"], [[x0 + h, y0 + h], [x1 - h, y0 + h], [x1 - h, y1 - h], [x0 + h, y1 - h]])


@pytest.mark.slow
def test_rooms_json_lists_typed_inner_footprints(tmp_path):
    from shared.eval.rooms import load_gt_rooms

    out = tmp_path / "seq"
    run_synth("small", 0, out, TINY, progress=False)
    rooms = json.loads((out / "gt" / "rooms.json").read_text())
    scene = json.loads((out / "gt" / "scene.json").read_text())
    assert rooms["frame"] == "world, metres, z up" and rooms["version"] == 1
    assert [r["id"] for r in rooms["rooms"]] == list(range(len(scene["rooms"])))
    assert [r["name"] for r in rooms["rooms"]] == [r["name"] for r in scene["rooms"]]
    assert [r["type"] for r in rooms["rooms"]] == [ROOM_TYPES[r["kind"]] for r in scene["rooms"]]
    assert "hall" in [r["type"] for r in rooms["rooms"]], "the small preset is one room and a hall"
    t = scene["wall_thickness"]
    for room, meta in zip(rooms["rooms"], scene["rooms"], strict=True):
        poly = np.array(room["footprint"])
        x0, y0, x1, y1 = meta["inner"]
        np.testing.assert_allclose(poly, [[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        # inside the wall centre lines by half a wall
        np.testing.assert_allclose(poly.min(axis=0), np.min(meta["footprint"], axis=0) + t / 2)
        # counter-clockwise: positive shoelace area
        x, y = poly[:, 0], poly[:, 1]
        assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0
    loaded = load_gt_rooms(out)
    assert [(r.name, r.type) for r in loaded] == [(r["name"], r["type"]) for r in rooms["rooms"]]
