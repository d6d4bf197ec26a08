"""Export to spark_dsg (.sparkdsg) and back."""

from __future__ import annotations

import numpy as np
import pytest

from shared.codec import encode
from shared.graph.scene import PlaceGraph, SceneGraph
from shared.messages.graph import MeshChunk, PlaceNode, RoomNode, SegmentNode

sd = pytest.importorskip("spark_dsg")
dsg = pytest.importorskip("shared.graph.dsg")
from shared.graph.dsg.layout import NO_LABEL  # noqa: E402 - after the importorskip guards


def _graph(gallery_dtype=np.float32, with_mesh=True):
    rng = np.random.default_rng(1)
    segs = []
    for i, c in enumerate([[1.0, 1.0, 0.4], [6.0, 1.2, 0.9], [3.0, 2.0, 1.3]]):
        rows = i  # 0, 1 and 2 gallery rows: an empty gallery must survive too
        tracks = [100 + 10 * i + k for k in range(3)]
        c = np.array(c)
        segs.append(SegmentNode(
            id=3 * i + 1, centroid=c, bbox_min=c - [0.1, 0.2, 0.3], bbox_max=c + 0.25, tracks=tracks,
            dino=rng.standard_normal(8).astype(np.float32),
            gallery=rng.standard_normal((rows, 5)).astype(gallery_dtype), gallery_tracks=tracks[:rows],
            active=i != 1, num_vertices=40 + i,
        ))  # fmt: skip
    places = [PlaceNode(id=k, position=np.array([1.0 + 2 * k, 1.5, 1.0]), radius=0.3 + 0.1 * k, room=int(k >= 2)) for k in range(4)]
    rooms = [RoomNode(id=0, centroid=np.array([2.0, 1.5, 1.0]), name="kitchen"), RoomNode(id=1, centroid=np.array([6.0, 1.5, 1.0]))]
    n = 50
    m = MeshChunk(
        vertices=rng.random((n, 3)).astype(np.float32), colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        faces=rng.integers(0, n, (20, 3)).astype(np.int32),
        segment_ids=rng.choice([-1, 1, 4, 7], n).astype(np.int32),
    )  # fmt: skip
    g = SceneGraph()
    g.apply_update(segs, [], PlaceGraph(places, [(0, 1), (1, 2), (2, 3)]), rooms, m if with_mesh else None, frame_index=42)
    return g


def _bytes(snap):
    return encode(snap, robot_id="r", seq=0, stamp=0.0)


@pytest.mark.parametrize("with_mesh", [True, False])
def test_save_and_load_round_trip_exactly(tmp_path, with_mesh):
    snap = _graph(with_mesh=with_mesh).snapshot(with_mesh=True)
    path = dsg.save_dsg(snap, tmp_path / "map.sparkdsg")
    assert path.is_file() and not list(tmp_path.glob(".*"))  # the temporary file is gone
    back = dsg.load_dsg(path)
    assert _bytes(back) == _bytes(snap)


def test_float16_galleries_come_back_as_float16(tmp_path):
    snap = _graph(gallery_dtype=np.float16).snapshot(with_mesh=False)
    back = dsg.load_dsg(dsg.save_dsg(snap, tmp_path / "m.sparkdsg"))
    assert back.segments[2].gallery.dtype == np.float16
    assert _bytes(back) == _bytes(snap)


def test_the_file_is_a_hydra_graph(tmp_path):
    snap = _graph().snapshot(with_mesh=True)
    g = sd.DynamicSceneGraph.load(str(dsg.save_dsg(snap, tmp_path / "m.sparkdsg")))
    objects = g.get_layer(sd.DsgLayers.OBJECTS)
    assert objects.num_nodes() == 3 and g.get_layer(sd.DsgLayers.PLACES).num_nodes() == 4
    assert g.get_layer(sd.DsgLayers.ROOMS).num_nodes() == 2 and g.get_layer(sd.DsgLayers.BUILDINGS).num_nodes() == 1
    node = g.get_node(sd.NodeSymbol("O", 7))
    feat = np.asarray(node.attributes.semantic_feature)
    assert feat.shape == (2, 5)  # the whole CLIP gallery, not an average
    assert np.allclose(feat, snap.segments[2].gallery)
    assert node.attributes.is_active
    assert sorted(node.attributes.mesh_connections) == np.flatnonzero(snap.mesh.segment_ids == 7).tolist()
    assert node.attributes.bounding_box.is_valid()
    assert np.allclose(node.attributes.bounding_box.min, snap.segments[2].bbox_min, atol=1e-6)
    assert g.get_node(sd.NodeSymbol("p", 2)).attributes.distance == pytest.approx(0.5)
    assert g.get_node(sd.NodeSymbol("R", 0)).attributes.name == "kitchen"
    assert g.has_edge(sd.NodeSymbol("O", 1), sd.NodeSymbol("p", 0))
    assert g.has_edge(sd.NodeSymbol("R", 1), sd.NodeSymbol("B", 0))
    assert g.has_mesh() and g.mesh.num_vertices() == 50
    labels = np.asarray(g.mesh.get_labels())
    assert np.array_equal(labels == NO_LABEL, snap.mesh.segment_ids < 0)


def test_foreign_graph_is_refused(tmp_path):
    g = sd.DynamicSceneGraph()
    path = tmp_path / "other.sparkdsg"
    g.save(str(path))
    with pytest.raises(ValueError, match="not a trackgraph scene graph"):
        dsg.load_dsg(path)
    with pytest.raises(FileNotFoundError):
        dsg.load_dsg(tmp_path / "missing.sparkdsg")
