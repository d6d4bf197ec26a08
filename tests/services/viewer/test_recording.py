"""Rerun recordings of a hand-built graph: entity paths, empty graphs, frames, map export."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from services.viewer import recording as vr
from shared.geometry import Intrinsics
from shared.messages.frames import Frame, TrackedFrame, TrackObservation
from shared.messages.graph import Edge, GraphSnapshot, MeshChunk, PlaceNode, RoomNode, SegmentNode
from shared.messages.rpc import QueryHit

# ---------------------------------------------------------------- a small scene by hand

_CUBE_V = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], np.float32)
_CUBE_F = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
     [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int32,
)  # fmt: skip
BOXES = {0: ((0.5, 0.5, 0.0), (1.5, 1.5, 0.8)), 1: ((4.0, 0.5, 0.0), (5.0, 1.2, 1.0)), 2: ((2.5, 2.8, 0.0), (3.5, 3.6, 0.5))}
"""Segment id -> (bbox_min, bbox_max) in a 6 x 4 m z-up room."""


def make_segment(i: int, lo, hi, room: int | None) -> SegmentNode:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    rng = np.random.default_rng(i)
    return SegmentNode(
        id=i, centroid=(lo + hi) / 2, bbox_min=lo, bbox_max=hi, tracks=[i, 10 + i],
        dino=rng.standard_normal(8).astype(np.float32), gallery=rng.standard_normal((1, 4)).astype(np.float32),
        gallery_tracks=[i], active=i != 2, room=room, num_vertices=8,
    )  # fmt: skip


def make_mesh() -> MeshChunk:
    """One cube per segment plus a floor quad of unassigned (-1) vertices."""
    verts, faces, ids = [], [], []
    for sid, (lo, hi) in BOXES.items():
        faces.append(_CUBE_F + sum(len(v) for v in verts))
        verts.append(np.asarray(lo, np.float32) + _CUBE_V * (np.asarray(hi, np.float32) - np.asarray(lo, np.float32)))
        ids.append(np.full(8, sid, np.int32))
    # A 6 x 4 m floor as a grid, so the top-down render has a surface.
    gx, gy = np.meshgrid(np.linspace(0, 6, 61), np.linspace(0, 4, 41))
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1).astype(np.float32)
    base = sum(len(v) for v in verts)
    q = np.arange(61 * 41).reshape(41, 61)[:-1, :-1].ravel()
    faces.append(np.concatenate([np.stack([q, q + 1, q + 62], 1), np.stack([q, q + 62, q + 61], 1)]).astype(np.int32) + base)
    verts.append(floor)
    ids.append(np.full(len(floor), -1, np.int32))
    v = np.concatenate(verts)
    return MeshChunk(
        vertices=v, colors=np.full((len(v), 3), 200, np.uint8), faces=np.concatenate(faces).astype(np.int32),
        segment_ids=np.concatenate(ids),
    )  # fmt: skip


def make_snapshot(with_mesh: bool = True, graph_seq: int = 3) -> GraphSnapshot:
    rooms = [RoomNode(id=0, centroid=np.array([1.5, 2.0, 1.0]), name="kitchen"), RoomNode(id=1, centroid=np.array([4.5, 2.0, 1.0]))]
    places = [
        PlaceNode(id=k, position=np.array([x, y, 1.0]), radius=0.6, room=0 if x < 3 else 1)
        for k, (x, y) in enumerate([(1.0, 1.0), (2.0, 3.0), (4.0, 2.5), (5.0, 3.0)])
    ]
    segments = [make_segment(i, lo, hi, room=0 if lo[0] < 3 else 1) for i, (lo, hi) in BOXES.items()]
    edges = (
        [Edge(kind="segment_place", source=0, target=0), Edge(kind="segment_place", source=1, target=2),
         Edge(kind="segment_place", source=2, target=1)]
        + [Edge(kind="place_place", source=a, target=b) for a, b in ((0, 1), (1, 2), (2, 3))]
        + [Edge(kind="place_room", source=p.id, target=p.room) for p in places]
        + [Edge(kind="room_building", source=r.id, target=0) for r in rooms]
    )  # fmt: skip
    return GraphSnapshot(
        graph_seq=graph_seq, frame_index=9, segments=segments, places=places, rooms=rooms, edges=edges,
        mesh=make_mesh() if with_mesh else None,
    )  # fmt: skip


def make_hits(ids=(1, 0)) -> list[QueryHit]:
    out = []
    for rank, i in enumerate(ids):
        lo, hi = (np.asarray(x, float) for x in BOXES[i])
        out.append(QueryHit(segment=i, score=0.9 - 0.2 * rank, centroid=(lo + hi) / 2, bbox_min=lo, bbox_max=hi, room=0))
    return out


def make_trajectory(n: int = 20) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n)
    return np.stack([3 + 2 * np.cos(t), 2 + 1.2 * np.sin(t), np.full(n, 1.5)], axis=1)


def make_frame(index: int = 4, h: int = 24, w: int = 32) -> Frame:
    rng = np.random.default_rng(index)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 1.5]
    return Frame(
        frame_index=index, rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth=rng.integers(1000, 9000, (h, w), dtype=np.uint16), depth_scale=6553.5,
        intrinsics=Intrinsics(fx=30, fy=30, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h), T_world_cam=T,
    )  # fmt: skip


def make_tracked(index: int = 4) -> TrackedFrame:
    frame = make_frame(index)
    ids = np.full(frame.depth.shape, -1, np.int32)
    ids[2:10, 3:12], ids[12:20, 15:30] = 3, 7
    obs = [TrackObservation(track_id=t, keyframe=False, frames_since_keyframe=1) for t in (3, 7)]
    return TrackedFrame(frame=frame, track_ids=ids, tracks=obs)


def record(path, fn) -> None:
    rec = vr.new_recording()
    rec.save(path)
    fn(rec)
    rec.flush()
    rec.disconnect()


# ---------------------------------------------------------------- tests


def test_snapshot_recording_has_the_hierarchy(tmp_path):
    out = tmp_path / "snap.rrd"

    def go(rec):
        vr.log_world_frame(rec)
        vr.log_snapshot(rec, make_snapshot(), time_seq=3)
        vr.log_trajectory(rec, make_trajectory())
        vr.log_query_hits(rec, "Red armchair!", make_hits())
        vr.log_tracked_frame(rec, make_tracked())

    record(out, go)
    assert out.stat().st_size > 5_000
    paths = vr.entity_paths(out)
    expected = {
        vr.WORLD, vr.MESH, vr.SEGMENT_BOXES, vr.SEGMENT_CENTROIDS, vr.PLACES, vr.ROOMS, vr.BUILDING,
        vr.TRAJECTORY, vr.CAMERA, vr.IMAGE, vr.RGB_IMAGE, vr.TRACKS_IMAGE, "world/queries/red_armchair",
        *(f"{vr.EDGES}/{k}" for k in vr.EDGE_KINDS),
    }  # fmt: skip
    assert {"/" + p for p in expected} <= paths


def test_segment_boxes_and_timeline_in_the_file(tmp_path):
    from rerun.chunk import RrdReader

    out = tmp_path / "boxes.rrd"
    record(out, lambda rec: vr.log_snapshot(rec, make_snapshot(), time_seq=5))
    chunks = [c for c in RrdReader(out).stream().to_chunks() if str(c.entity_path) == "/" + vr.SEGMENT_BOXES]
    assert chunks and vr.GRAPH_TIMELINE in chunks[0].timeline_names
    batch = chunks[0].to_record_batch()
    assert len(batch.column("Boxes3D:centers")[0]) == len(BOXES)
    labels = batch.column("Boxes3D:labels")[0].as_py()
    assert labels[0] == "0 (room 0)"


def test_empty_graph_and_empty_inputs_log(tmp_path):
    out = tmp_path / "empty.rrd"

    def go(rec):
        vr.log_snapshot(rec, GraphSnapshot(graph_seq=0, frame_index=-1))
        vr.log_snapshot(rec, GraphSnapshot(graph_seq=1, frame_index=-1, mesh=MeshChunk(
            vertices=np.zeros((0, 3), np.float32), colors=np.zeros((0, 3), np.uint8),
            faces=np.zeros((0, 3), np.int32), segment_ids=np.zeros(0, np.int32))), time_seq=1)  # fmt: skip
        vr.log_trajectory(rec, np.zeros((0, 3)))
        vr.log_trajectory(rec, np.zeros((1, 3)))
        vr.log_query_hits(rec, "", [])

    record(out, go)
    assert "/" + vr.SEGMENT_BOXES in vr.entity_paths(out)


def test_edges_skip_missing_nodes_and_building_is_raised():
    snap = make_snapshot(with_mesh=False)
    snap.edges.append(Edge(kind="segment_place", source=99, target=0))
    lines = vr.edge_lines(snap)
    assert {k: len(v) for k, v in lines.items()} == {"segment_place": 3, "place_place": 3, "place_room": 4, "room_building": 2}
    b = vr.building_position(snap)
    np.testing.assert_allclose(b, [3.0, 2.0, 1.0 + vr.BUILDING_RAISE_M])
    assert vr.building_position(GraphSnapshot(graph_seq=0, frame_index=-1)) is None


def test_segment_colours_stable_distinct_and_grey_for_none():
    ids = np.arange(60)
    a, b = vr.segment_colors(ids), vr.segment_colors(ids[::-1])[::-1]
    np.testing.assert_array_equal(a, b)
    assert a.dtype == np.uint8 and a.shape == (60, 3)
    d = np.linalg.norm(a[:, None, :].astype(float) - a[None, :, :].astype(float), axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d[:12, :12].min() > 40, "the first dozen segments must be clearly distinct"
    assert len({tuple(c) for c in a}) == 60
    assert tuple(vr.segment_colors(np.array([-1]))[0]) == vr.NONE_COLOR
    assert vr.segment_color(5) == tuple(int(x) for x in a[5])


def test_slug():
    assert vr.slug("Red armchair!") == "red_armchair"
    assert vr.slug("  ") == "query"
    assert vr.slug("a" * 100) == "a" * 40


def test_pick_even():
    assert vr.pick_even(list(range(10)), 3) == [0, 4, 9]
    assert vr.pick_even(list(range(100)), 60)[-1] == 99 and len(vr.pick_even(list(range(100)), 60)) == 60
    assert vr.pick_even([1, 2], 5) == [1, 2]
    assert vr.pick_even([1, 2], 0) == []


def _write_map(map_dir, snapshot=None):
    from shared.graph.store import MapStore

    MapStore(map_dir / "graph", write_dsg=False).save(snapshot or make_snapshot(), extra_state={"trajectory": make_trajectory()})


def _write_sequence(seq_dir, n: int = 4, h: int = 24, w: int = 32) -> None:
    (seq_dir / "results").mkdir(parents=True)
    rng = np.random.default_rng(0)
    lines = []
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(seq_dir / "results" / f"frame{i:06d}.png")
        Image.fromarray(np.full((h, w), 6553, np.uint16)).save(seq_dir / "results" / f"depth{i:06d}.png")
        T = np.eye(4)
        T[:3, 3] = [1.0 + 0.1 * i, 2.0, 1.5]
        lines.append(" ".join(f"{v:.6f}" for v in T.ravel()))
    (seq_dir / "traj.txt").write_text("\n".join(lines) + "\n")
    (seq_dir / "intrinsics.json").write_text(json.dumps({"fx": 30, "fy": 30, "cx": 15.5, "cy": 11.5, "width": w, "height": h}))


def test_write_map_recording_with_queries_and_frames(tmp_path):
    from shared.eval.track_io import TrackWriter

    map_dir, seq_dir = tmp_path / "map", tmp_path / "seq"
    _write_map(map_dir)
    _write_sequence(seq_dir)
    with TrackWriter(map_dir) as tw:
        for i in range(4):
            ids = np.full((24, 32), -1, np.int32)
            ids[4:12, 4 + i : 14 + i] = 2
            tw.write(i, ids, keyframe=i == 0)
    out = tmp_path / "out" / "map.rrd"
    got = vr.write_map_recording(map_dir, out, queries={"chair": make_hits()}, sequence_dir=seq_dir, max_frames=3)
    assert got == out and out.stat().st_size > 5_000
    assert [p.name for p in out.parent.iterdir()] == ["map.rrd"], "no temporary file may be left"
    paths = vr.entity_paths(out)
    assert {"/" + vr.MESH, "/" + vr.TRAJECTORY, "/world/queries/chair", "/" + vr.TRACKS_IMAGE, "/" + vr.RGB_IMAGE} <= paths
    from rerun.chunk import RrdReader

    frames = [c for c in RrdReader(out).stream().to_chunks() if str(c.entity_path) == "/" + vr.RGB_IMAGE]
    assert sum(c.num_rows for c in frames) == 3


def test_write_map_recording_without_tracks_logs_the_graph(tmp_path, caplog):
    map_dir, seq_dir = tmp_path / "map", tmp_path / "seq"
    _write_map(map_dir)
    _write_sequence(seq_dir)
    out = vr.write_map_recording(map_dir, tmp_path / "m.rrd", sequence_dir=seq_dir)
    paths = vr.entity_paths(out)
    assert "/" + vr.SEGMENT_BOXES in paths and "/" + vr.RGB_IMAGE not in paths
    assert "--save-tracks" in caplog.text


def test_write_map_recording_errors_on_an_empty_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match=str(tmp_path)):
        vr.write_map_recording(tmp_path, tmp_path / "x.rrd")
    assert not (tmp_path / "x.rrd").exists()
    assert [p for p in tmp_path.iterdir()] == []


def test_track_map_of_another_size_is_resized():
    ids = np.arange(6).reshape(2, 3)
    out = vr._fit(ids, 4, 6)
    assert out.shape == (4, 6) and out[0, 0] == 0 and out[3, 5] == 5


def test_package_import_is_light():
    code = (
        "import sys\nimport services.viewer\nimport services.viewer.render\n"
        "print(','.join(m for m in ('rerun', 'torch', 'open3d', 'zenoh') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""
