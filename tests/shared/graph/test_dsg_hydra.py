"""The .sparkdsg as Hydra's tools see it, read through spark_dsg's own API, and the round trip
of the fields Hydra needs (place outlines, active flags, room boxes, the camera trajectory)."""

from __future__ import annotations

import base64
import datetime
import zlib

import numpy as np
import pytest

from shared.codec import encode
from shared.messages.graph import Edge, GraphSnapshot, MeshChunk, PlaceNode, RoomNode, SegmentNode

sd = pytest.importorskip("spark_dsg")
dsg = pytest.importorskip("shared.graph.dsg")
from shared.graph.colors import segment_colors  # noqa: E402 - after the importorskip guards
from shared.graph.dsg.hydra import agent_places  # noqa: E402
from shared.graph.dsg.layout import UNKNOWN_ROOM  # noqa: E402

L = sd.DsgLayers


def _rect(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64)


# Places: four rectangles along x, each with its own height and radius; p1 stands off the
# centre of its outline so a pose can lie in p1's outline yet nearer p2's position. p4 has no
# outline. Rooms: 0 = p0, p1 (named, with a box); 1 = p2, p3, p4 (no name, no box).
PLACES = [
    (0, (1.0, 1.5, 1.0), 0.4, _rect(0.0, 0.0, 2.0, 3.0), True),
    (1, (2.2, 1.5, 1.1), 0.5, _rect(2.0, 0.0, 4.0, 3.0), False),
    (2, (5.0, 1.5, 1.2), 0.6, _rect(4.0, 0.0, 6.0, 3.0), True),
    (3, (7.0, 1.0, 0.9), 0.3, np.array([[6.0, 0.0], [8.5, 0.5], [7.5, 2.5], [6.2, 2.0]]), False),
    (4, (9.5, 1.5, 1.0), 0.2, np.zeros((0, 2)), False),
]
ROOM_OF = {0: 0, 1: 0, 2: 1, 3: 1, 4: 1}


ROOM_FEATURE = (np.arange(8, dtype=np.float32) / np.linalg.norm(np.arange(8))).astype(np.float32)


def _snapshot(seed=3, with_mesh=True, trajectory=True):
    rng = np.random.default_rng(seed)
    places = [
        PlaceNode(id=i, position=np.array(c), radius=r, room=ROOM_OF[i], boundary=b, active=act)
        for i, c, r, b, act in PLACES
    ]
    rooms = [
        RoomNode(id=0, centroid=np.array([1.6, 1.5, 1.05]), name="kitchen", bbox_min=np.array([0.0, 0.0, 0.05]),
                 bbox_max=np.array([4.0, 3.0, 2.45]), area_m2=12.0, feature=ROOM_FEATURE, name_score=0.61),
        RoomNode(id=1, centroid=np.array([7.0, 1.3, 1.0]), area_m2=7.5),
    ]  # fmt: skip
    segs = []
    for i, c in enumerate([[1.0, 1.0, 0.4], [5.0, 1.2, 0.9], [7.0, 2.0, 1.3]]):
        c = np.array(c)
        tracks = [10 * i + k for k in range(2)]
        segs.append(SegmentNode(
            id=2 * i + 1, centroid=c, bbox_min=c - 0.2, bbox_max=c + 0.3, tracks=tracks,
            dino=rng.standard_normal(4).astype(np.float32), gallery=rng.standard_normal((1, 3)).astype(np.float32),
            gallery_tracks=tracks[:1], gallery_weights=[0.5], active=i != 2, room=ROOM_OF[2 * i], num_vertices=5,
        ))  # fmt: skip
    edges = (
        [Edge(kind="segment_place", source=s, target=p) for s, p in [(1, 0), (3, 2), (5, 3)]]
        + [Edge(kind="place_place", source=a, target=a + 1) for a in range(4)]
        + [Edge(kind="place_room", source=p, target=r) for p, r in ROOM_OF.items()]
        + [Edge(kind="room_building", source=r, target=0) for r in (0, 1)]
    )
    mesh = None
    if with_mesh:
        n = 40
        mesh = MeshChunk(
            vertices=rng.random((n, 3)).astype(np.float32), colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
            faces=rng.integers(0, n, (12, 3)).astype(np.int32), segment_ids=rng.choice([-1, 1, 3, 5], n).astype(np.int32),
        )  # fmt: skip
    traj, frames = np.zeros((0, 7)), np.zeros(0, np.int64)
    if trajectory:
        # x across every place, one pose past the last place's outline and one off the map.
        xs = np.array([0.5, 1.5, 3.9, 4.5, 6.8, 9.5, 12.0])
        pos = np.stack([xs, np.full_like(xs, 1.4), np.full_like(xs, 1.3)], axis=1)
        q = rng.standard_normal((xs.size, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        traj = np.concatenate([pos, q], axis=1)
        frames = np.arange(xs.size, dtype=np.int64) * 5 + 2
    return GraphSnapshot(graph_seq=9, frame_index=40, segments=segs, places=places, rooms=rooms, edges=edges,
                         mesh=mesh, trajectory=traj, trajectory_frames=frames)  # fmt: skip


def _bytes(snap):
    return encode(snap, robot_id="r", seq=0, stamp=0.0)


def _expected_agent_places(snap):
    """Independently of the writer: the nearest place whose outline contains the pose (the
    outlines here are convex, so a half-plane test decides), else the nearest place."""
    out = []
    for row in snap.trajectory:
        p = row[:3]

        def inside(b, p=p):
            if b.shape[0] < 3:
                return False
            e = np.roll(b, -1, axis=0) - b
            return bool(np.all(e[:, 0] * (p[1] - b[:, 1]) - e[:, 1] * (p[0] - b[:, 0]) >= 0))

        cands = [q for q in snap.places if inside(q.boundary)] or snap.places
        out.append(min(cands, key=lambda q: np.linalg.norm(q.position - p)).id)
    return out


@pytest.fixture()
def saved(tmp_path):
    snap = _snapshot()
    path = dsg.save_dsg(snap, tmp_path / "map.sparkdsg")
    return snap, sd.DynamicSceneGraph.load(str(path))


def test_layers_are_hydras(saved):
    _, g = saved
    names = g.layer_names
    for name in (L.OBJECTS, L.AGENTS, L.PLACES, L.MESH_PLACES, L.ROOMS, L.BUILDINGS):
        want = L.name_to_layer_id(name)
        assert (names[name].layer, names[name].partition) == (want.layer, want.partition), name
    assert g.get_layer(L.OBJECTS).num_nodes() == 3
    assert g.get_layer(L.PLACES).num_nodes() == 5
    assert g.get_layer(L.MESH_PLACES).num_nodes() == 4  # p4 has no outline
    assert g.get_layer(L.ROOMS).num_nodes() == 2 and g.get_layer(L.BUILDINGS).num_nodes() == 1
    # The hierarchy as Hydra's interlayer parents: segment -> place -> room -> building.
    assert g.get_node(sd.NodeSymbol("O", 3)).get_parent() == sd.NodeSymbol("p", 2).value
    for p, r in ROOM_OF.items():
        assert g.get_node(sd.NodeSymbol("p", p)).get_parent() == sd.NodeSymbol("R", r).value
    for r in (0, 1):
        assert g.get_node(sd.NodeSymbol("R", r)).get_parent() == sd.NodeSymbol("B", 0).value
    # Rooms joined where their places are (p1 - p2), as Hydra's room layer has it.
    assert g.has_edge(sd.NodeSymbol("R", 0), sd.NodeSymbol("R", 1))
    assert g.has_edge(sd.NodeSymbol("Q", 0), sd.NodeSymbol("Q", 1)) and not g.has_node(sd.NodeSymbol("Q", 4))


def test_places_carry_distance_active_flag_and_outline(saved):
    snap, g = saved
    places_layer, outlines_layer = g.get_layer(L.PLACES), g.get_layer(L.MESH_PLACES)
    for p in snap.places:
        node = places_layer.get_node(sd.NodeSymbol("p", p.id))
        assert isinstance(node.attributes, sd.PlaceNodeAttributes)
        assert node.attributes.distance == p.radius
        assert node.attributes.is_active == p.active
        assert np.array_equal(node.attributes.position, p.position)
        assert np.array_equal(node.attributes.color, segment_colors(np.array([ROOM_OF[p.id]]))[0])
        if not p.boundary.shape[0]:
            continue
        a = outlines_layer.get_node(sd.NodeSymbol("Q", p.id)).attributes
        assert isinstance(a, sd.Place2dNodeAttributes) and a.is_active == p.active
        b = np.array(a.boundary)
        assert np.array_equal(b[:, :2], p.boundary) and np.all(b[:, 2] == p.position[2])
        # Hydra's ellipse of the minimum-area rectangle passes through the rectangle's corners,
        # which for the axis-aligned outlines are the outline's own corners.
        if p.id <= 2:
            assert np.allclose(a.ellipse_centroid[:2], p.boundary.mean(0))
            d = p.boundary - a.ellipse_centroid[:2]
            assert np.allclose(np.einsum("ni,ij,nj->n", d, a.ellipse_matrix_compress, d), 1.0)
            sides = sorted(np.linalg.norm(a.ellipse_matrix_expand, axis=0) * np.sqrt(2))
            assert np.allclose(sides, sorted(p.boundary.max(0) - p.boundary.min(0)))


def test_rooms_carry_name_label_box_and_colour(saved):
    snap, g = saved
    key = g.get_layer_key(L.ROOMS)
    space = g.get_labelspace(key.layer, key.partition)
    r0 = g.get_node(sd.NodeSymbol("R", 0)).attributes
    assert r0.name == "kitchen" and space.get_category(r0.semantic_label) == "kitchen"
    # The room's feature is a one-row semantic_feature, its name score in the metadata.
    np.testing.assert_allclose(np.asarray(r0.semantic_feature), ROOM_FEATURE[None], atol=1e-7)
    assert r0.metadata.get()["trackgraph"]["name_score"] == pytest.approx(0.61)
    assert np.allclose(r0.bounding_box.min, snap.rooms[0].bbox_min, atol=1e-6)
    assert np.allclose(r0.bounding_box.max, snap.rooms[0].bbox_max, atol=1e-6)
    assert np.array_equal(r0.color, segment_colors(np.array([0]))[0])
    # Room 1 has no box: it comes from its places' outlines (xy) and heights +- radius (z).
    r1 = g.get_node(sd.NodeSymbol("R", 1)).attributes
    assert space.get_category(r1.semantic_label) == UNKNOWN_ROOM
    members = [p for p in snap.places if ROOM_OF[p.id] == 1]
    xy = np.concatenate([p.boundary for p in members])
    z_lo = min(p.position[2] - p.radius for p in members)
    z_hi = max(p.position[2] + p.radius for p in members)
    assert r1.bounding_box.is_valid()
    assert np.allclose(r1.bounding_box.min, [*xy.min(0), z_lo], atol=1e-6)
    assert np.allclose(r1.bounding_box.max, [*xy.max(0), z_hi], atol=1e-6)
    b = g.get_node(sd.NodeSymbol("B", 0)).attributes
    key = g.get_layer_key(L.BUILDINGS)
    assert g.get_labelspace(key.layer, key.partition).get_category(b.semantic_label) == "building"


def test_agent_layer_is_the_trajectory(saved):
    snap, g = saved
    key = g.get_layer_key(L.AGENTS)
    agents = g.get_layer(key.layer, "a")
    m = snap.trajectory.shape[0]
    assert agents.num_nodes() == m
    linked = _expected_agent_places(snap)
    # The geometry makes both rules matter: a pose in p1's outline but nearer p2, one outside all.
    assert linked[2] == 1 and linked[6] == 4
    for k in range(m):
        node = g.get_node(sd.NodeSymbol("a", k))
        a = node.attributes
        assert isinstance(a, sd.AgentNodeAttributes)
        assert (node.layer.layer, node.layer.partition) == (key.layer, ord("a"))
        assert np.array_equal(a.position, snap.trajectory[k, :3])
        q = a.world_R_body
        assert [q.x, q.y, q.z, q.w] == snap.trajectory[k, 3:].tolist()
        assert a.timestamp == datetime.timedelta(microseconds=int(snap.trajectory_frames[k]))
        assert a.external_key == sd.NodeSymbol("a", k).value
        if k:
            assert g.has_edge(sd.NodeSymbol("a", k - 1), sd.NodeSymbol("a", k))
        assert node.get_parent() == sd.NodeSymbol("p", linked[k]).value
        assert len(node.parents()) == 1
    assert agents.num_edges() == m - 1


def test_mesh_vertices_carry_segment_colours(saved):
    snap, g = saved
    v = np.asarray(g.mesh.get_vertices())
    rgb = np.round(v[3:6].T * 255).astype(np.uint8)
    ids = snap.mesh.segment_ids
    assert np.array_equal(rgb[ids < 0], snap.mesh.colors[ids < 0])
    per_segment = {}
    for sid in np.unique(ids[ids >= 0]):
        colours = np.unique(rgb[ids == sid], axis=0)
        assert colours.shape[0] == 1
        per_segment[int(sid)] = tuple(colours[0])
        assert np.array_equal(g.get_node(sd.NodeSymbol("O", int(sid))).attributes.color, colours[0])
    assert len(set(per_segment.values())) == len(per_segment)  # distinct per segment


@pytest.mark.parametrize("mesh_colors", ["segments", "rgb"])
def test_round_trip_keeps_the_new_fields(tmp_path, mesh_colors):
    snap = _snapshot()
    back = dsg.load_dsg(dsg.save_dsg(snap, tmp_path / "m.sparkdsg", mesh_colors=mesh_colors))
    assert _bytes(back) == _bytes(snap)
    assert np.array_equal(back.places[3].boundary, snap.places[3].boundary) and back.places[4].boundary.shape == (0, 2)
    assert [p.active for p in back.places] == [p.active for p in snap.places]
    assert back.rooms[1].bbox_min is None and np.array_equal(back.rooms[0].bbox_max, snap.rooms[0].bbox_max)
    assert np.array_equal(back.trajectory, snap.trajectory) and np.array_equal(back.trajectory_frames, snap.trajectory_frames)
    assert back.segments[0].gallery_weights == [0.5] and back.mesh.colors.tobytes() == snap.mesh.colors.tobytes()


def test_round_trip_without_trajectory_or_mesh(tmp_path):
    snap = _snapshot(with_mesh=False, trajectory=False)
    g = sd.DynamicSceneGraph.load(str(dsg.save_dsg(snap, tmp_path / "m.sparkdsg")))
    assert g.get_layer_key(L.AGENTS) is not None and not g.has_mesh()
    assert _bytes(dsg.from_dsg(g)) == _bytes(snap)


def test_bad_input_is_refused():
    snap = _snapshot(with_mesh=False)
    short = snap.model_copy(update={"trajectory_frames": snap.trajectory_frames[:-1]})
    with pytest.raises(ValueError, match="trajectory has 7 rows but trajectory_frames has 6"):
        dsg.to_dsg(short)
    with pytest.raises(ValueError, match="mesh_colors"):
        dsg.to_dsg(snap, mesh_colors="labels")
    g = dsg.to_dsg(_snapshot())
    info = dict(g.metadata.get())
    info["trackgraph"] = {k: v for k, v in info["trackgraph"].items() if k != "mesh_rgb"}
    g.metadata.set(info)
    with pytest.raises(ValueError, match="mesh_rgb"):
        dsg.from_dsg(g)


def test_room_area_round_trips(tmp_path):
    snap = _snapshot(with_mesh=False, trajectory=False)
    back = dsg.load_dsg(dsg.save_dsg(snap, tmp_path / "m.sparkdsg"))
    assert back.rooms[0].area_m2 == 12.0 and back.rooms[1].area_m2 == 7.5


def test_outline_without_area_still_round_trips(tmp_path):
    # A sliver (collinear points) has no Hydra ellipse, but its outline is kept.
    base = _snapshot(with_mesh=False)
    sliver = np.array([[6.0, 1.0], [7.0, 1.0], [8.0, 1.0]])
    places = [p.model_copy(update={"boundary": sliver}) if p.id == 3 else p for p in base.places]
    snap = base.model_copy(update={"places": places})
    path = dsg.save_dsg(snap, tmp_path / "m.sparkdsg")
    a = sd.DynamicSceneGraph.load(str(path)).get_node(sd.NodeSymbol("Q", 3)).attributes
    assert np.array_equal(np.array(a.boundary)[:, :2], sliver) and not np.any(a.ellipse_matrix_compress)
    assert _bytes(dsg.load_dsg(path)) == _bytes(snap)


# ------------------------------------------------------------------ format 1

# A graph that the format-1 writer (before places had outlines) saved from _v1_snapshot(),
# zlib-compressed and base64-encoded.
V1_FILE = (
    "eNrVlt9P01AUx1s2/Jn4oKgxMWa5Tz5UMsoPk0WZAyZBJiwbvkhI0213W3VtZ9chC1niv4F/zvZi8MoIvNqEP4FH3/Dc2/ay"
    "dUXQGINbOL33nHPP7vdzT1uc64Ig5LOp3LKykF90ojDTVc0gInwjbOqMgDmkhn72BO6KDLuiw67RARf9NecWmBWzhFO2bWmF"
    "po0bzj26C6yrhq0VA6ExCK0W3uGiHQjchkDONPWA+w64szW1iAP+u75fLoWsSFWwEfyB++BfrlqmYTbcDfTFHkJszVI3sdVQ"
    "C1pNs1uBxaKvNF2q9PspD+cK/cXF9MpaPowuhTT3ZimzsLSymA+jeJUimXuVng9fT6tnM6n5dD7soGip3Orq63zYke2D2Ua2"
    "pRbfVyy1XkWJbVQ2LV21UWJCQmVL1bGiGSW8BXNZQixJaeAPKPFUQlW1oei4Aatsq4klVFNbwIfWKDS1WkkzKigxLaE6PQVw"
    "T0rIgvOD0ZSEGriiwxHARG7TmdsLShmrdtPCKIHmM0vZWEWt1bDVipnlmF3FMW+RFDMNHLPMj7E6tngOU4HabYG1MWfU8war"
    "TDEZcaLisGa1aGub2NdRKJhbiq6C5vWJ8WlpYjwuxcenN/yAZkAAHOCkgTgEirAry9RKbAXLhj+ZLgEKppf+xA3J05LMFtGQ"
    "UrJbdSq3XDNVe1JGwNjVo5Q0nTHj8zMzmRYguT4DVY2mrkCbAkzKXHaZo0RcQjxtSprZaLe/ulyOk97gyB/sJ3seO6HbYd3p"
    "cY/JRGDfE4b4gPb8riB8SvpGCIxmnZv9DckHPEsYMOG+vRP4sDY+FIcKfSPkOZjM7O7nnZ1Z1uJ88z0/vcO2G9TLPX0Dt3X8"
    "6n6luts6UedByO3i4f0Fz+NTnp2Ow0oNYBzSPGT+Hkb2DPB3cxjQv590nwohpts5j9pF8HZOQQRIi39AWnjx35I++ueko4Ge"
    "zrmkI2yf2z7SH+c0L61ShafOZcPqnN68owGhc65Q8feEXoOL/xK7bGJFwYn0P534zUMET2SHaxrIzHEmZ2b6L0te/LyadV78"
    "zEzxAplit9vpuv11UUQDI2/KCpAbZIw8IifkMZHJM7i+JFnyFq5fyAH5DufIM/dGuKG8Xej8f9kBnadvE5+RMKBO6EWC8Z/U"
    "qby1"
)


def _v1_snapshot():
    seg = SegmentNode(
        id=2, centroid=np.array([1.0, 0.5, 0.25]), bbox_min=np.array([0.5, 0.0, 0.0]), bbox_max=np.array([1.5, 1.0, 0.5]),
        tracks=[4, 6], dino=np.array([0.5, -1.0, 0.25, 2.0], np.float32), gallery=np.array([[0.1, 0.2, 0.3]], np.float32),
        gallery_tracks=[6], active=True, room=0, num_vertices=2,
    )  # fmt: skip
    places = [PlaceNode(id=i, position=np.array([1.0 + i, 0.5, 1.0]), radius=0.25 * (i + 1), room=0) for i in range(2)]
    mesh = MeshChunk(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32),
        colors=np.array([[10, 20, 30], [40, 50, 60], [70, 80, 90], [200, 210, 220]], np.uint8),
        faces=np.array([[0, 1, 2], [1, 3, 2]], np.int32), segment_ids=np.array([2, 2, -1, -1], np.int32),
    )  # fmt: skip
    edges = [
        Edge(kind="segment_place", source=2, target=0), Edge(kind="place_place", source=0, target=1),
        Edge(kind="place_room", source=0, target=0), Edge(kind="place_room", source=1, target=0),
        Edge(kind="room_building", source=0, target=0),
    ]  # fmt: skip
    rooms = [RoomNode(id=0, centroid=np.array([1.5, 0.5, 1.0]), name="hall")]
    return GraphSnapshot(graph_seq=7, frame_index=12, segments=[seg], places=places, rooms=rooms, edges=edges, mesh=mesh)


def test_format_1_files_still_load(tmp_path):
    path = tmp_path / "v1.sparkdsg"
    path.write_bytes(zlib.decompress(base64.b64decode(V1_FILE)))
    back = dsg.load_dsg(path)
    want = _v1_snapshot()
    assert _bytes(back) == _bytes(want)
    # What format 1 had no room for reads as unknown.
    assert back.trajectory.shape == (0, 7) and back.places[0].boundary.shape == (0, 2) and not back.places[0].active


def test_a_chunk_of_poses_outside_every_outline_goes_to_the_nearest_place():
    # Chunks of 2 poses: the first chunk lies within no outline's box (the path the live map
    # of a corrupt-frames test took), the second within p1's.
    base = _snapshot(with_mesh=False)
    far = np.array([[50.0, 50.0, 1.0, 0, 0, 0, 1], [51.0, 50.0, 1.0, 0, 0, 0, 1]])
    traj = np.concatenate([far, base.trajectory[:2]])
    snap = base.model_copy(update={"trajectory": traj, "trajectory_frames": np.arange(len(traj), dtype=np.int64)})
    got = agent_places(snap, chunk=2)
    centres = np.array([p.position for p in snap.places])
    ids = np.array([p.id for p in snap.places])
    nearest = ids[np.argmin(np.linalg.norm(centres[None] - far[:, None, :3], axis=2), axis=1)]
    assert got[:2].tolist() == nearest.tolist()
    assert got[2:].tolist() == agent_places(base.model_copy(update={"trajectory": base.trajectory[:2], "trajectory_frames": np.arange(2, dtype=np.int64)}), chunk=2).tolist()
