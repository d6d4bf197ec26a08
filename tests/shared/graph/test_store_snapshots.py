"""Atomic, checksummed map snapshots with fallback to the previous one."""

from __future__ import annotations

import errno
import json

import numpy as np
import pytest

from shared.codec import encode
from shared.graph import store as store_mod
from shared.graph.scene import PlaceGraph, SceneGraph
from shared.graph.store import DiskFull, MapStore, SnapshotCorrupt, StoreError
from shared.messages.graph import MeshChunk, PlaceNode, RoomNode, SegmentNode


def _graph(n_segments=3, seed=0):
    rng = np.random.default_rng(seed)
    segs = []
    for i in range(n_segments):
        c = rng.uniform(0, 5, 3)
        segs.append(SegmentNode(
            id=i, centroid=c, bbox_min=c - 0.2, bbox_max=c + 0.2, tracks=[i, 100 + i],
            dino=rng.standard_normal(16).astype(np.float32),
            gallery=rng.standard_normal((2, 8)).astype(np.float32), gallery_tracks=[i, 100 + i], active=True,
        ))  # fmt: skip
    places = [PlaceNode(id=k, position=np.array([k, 1.0, 1.0]), radius=0.5, room=0) for k in range(3)]
    n = 64
    m = MeshChunk(
        vertices=rng.random((n, 3)).astype(np.float32), colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        faces=rng.integers(0, n, (30, 3)).astype(np.int32), segment_ids=rng.integers(-1, n_segments, n).astype(np.int32),
    )  # fmt: skip
    g = SceneGraph()
    g.apply_update(segs, [], PlaceGraph(places, [(0, 1), (1, 2)]), [RoomNode(id=0, centroid=np.array([1.0, 1, 1]))], m, frame_index=9)
    return g


def _extra(seed=0):
    rng = np.random.default_rng(seed)
    return {
        "tsdf": {"block_keys": rng.integers(0, 100, (20, 3)).astype(np.int32), "tsdf": rng.random((20, 8, 8, 8)).astype(np.float32)},
        "tracks": {"ids": np.arange(5), "empty": {}},
        "counter": np.int64(17),
    }


def _bytes(snap):
    return encode(snap, robot_id="r", seq=0, stamp=0.0)


@pytest.fixture(params=[True, False], ids=["with_dsg", "no_dsg"])
def store(request, tmp_path):
    if request.param:
        pytest.importorskip("spark_dsg")
    return MapStore(tmp_path / "map", keep=2, write_dsg=request.param)


def test_round_trip(store):
    g = _graph()
    snap = g.snapshot(with_mesh=True)
    path = store.save(snap, _extra(), metadata={"dataset": "replica/room0"})
    assert path.name == "000001" and store.latest_name() == "000001"
    files = {p.name for p in path.iterdir()}
    assert {"graph.msgpack", "extra.npz", "metadata.json", "MANIFEST.json"} <= files
    assert ("graph.sparkdsg" in files) == store.write_dsg

    state = store.load()
    assert _bytes(state.snapshot) == _bytes(snap)
    assert state.metadata["user"] == {"dataset": "replica/room0"}
    assert state.metadata["counts"]["segments"] == 3 and state.metadata["graph_seq"] == 1
    ex = _extra()
    assert np.array_equal(state.extra["tsdf"]["tsdf"], ex["tsdf"]["tsdf"])
    assert state.extra["tsdf"]["block_keys"].dtype == np.int32
    assert state.extra["tracks"]["empty"] == {}
    assert int(state.extra["counter"]) == 17 and not state.fell_back_from
    resumed = SceneGraph.from_snapshot(state.snapshot)
    assert _bytes(resumed.snapshot(True)) == _bytes(snap)


def test_keeps_the_previous_snapshots_only(store):
    for k in range(4):
        store.save(_graph(seed=k).snapshot())
    assert store.names() == ["000003", "000004"] and store.latest_name() == "000004"


@pytest.mark.parametrize("victim", ["graph.msgpack", "extra.npz", "metadata.json"])
def test_corrupt_newest_falls_back_to_previous(store, victim, caplog):
    old = _graph(seed=1).snapshot(with_mesh=True)
    store.save(old, _extra(1))
    newest = store.save(_graph(seed=2).snapshot(with_mesh=True), _extra(2))
    f = newest / victim
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte, same size
    f.write_bytes(bytes(data))

    with pytest.raises(SnapshotCorrupt, match="checksum mismatch") as info:
        store.load_name("000002")
    assert info.value.path == f
    state = store.load()
    assert state.path.name == "000001"
    assert _bytes(state.snapshot) == _bytes(old)
    assert "000002" in state.fell_back_from[0] and victim in state.fell_back_from[0]
    assert any("unusable" in r.message for r in caplog.records)
    with pytest.raises(SnapshotCorrupt, match=victim):
        store.load(fallback=False)


def test_truncated_file_and_manifest(store):
    store.save(_graph(seed=1).snapshot())
    newest = store.save(_graph(seed=2).snapshot())
    graph = newest / "graph.msgpack"
    graph.write_bytes(graph.read_bytes()[:100])
    with pytest.raises(SnapshotCorrupt, match=r"graph\.msgpack: truncated"):
        store.verify("000002")
    manifest = newest / "MANIFEST.json"
    manifest.write_bytes(manifest.read_bytes()[:40])
    with pytest.raises(SnapshotCorrupt, match=r"MANIFEST\.json: corrupt or truncated manifest"):
        store.verify("000002")
    assert store.load().path.name == "000001"
    manifest.unlink()
    with pytest.raises(SnapshotCorrupt, match="missing"):
        store.verify("000002")


def test_nothing_usable_is_a_clear_error(store):
    with pytest.raises(StoreError, match="no map snapshot"):
        store.load()
    p = store.save(_graph().snapshot())
    (p / "extra.npz").write_bytes(b"")
    with pytest.raises(StoreError, match=r"no usable map snapshot.*extra\.npz"):
        store.load()


def test_broken_latest_pointer_is_survivable(store):
    store.save(_graph(seed=1).snapshot())
    store.save(_graph(seed=2).snapshot())
    (store.root / "latest").write_text("garbage")
    assert store.load().path.name == "000002"
    (store.root / "latest").unlink()
    assert store.load().path.name == "000002"


@pytest.mark.parametrize("fail_on", ["graph.msgpack", "extra.npz", "MANIFEST.json", "latest"])
def test_disk_full_keeps_the_previous_snapshot(store, monkeypatch, fail_on):
    old = _graph(seed=1).snapshot(with_mesh=True)
    store.save(old, _extra())
    real = store_mod.atomic_write_bytes

    def full(path, data):
        if path.name == fail_on:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, data)

    monkeypatch.setattr(store_mod, "atomic_write_bytes", full)
    with pytest.raises(DiskFull, match=rf"disk full while writing {fail_on} of snapshot 000002.*000001 is still current"):
        store.save(_graph(seed=2).snapshot(with_mesh=True), _extra())
    monkeypatch.undo()
    assert store.names() == ["000001"] and store.latest_name() == "000001"
    assert not list((store.root / "snapshots").glob(".*"))  # no partial folder left
    assert _bytes(store.load().snapshot) == _bytes(old)
    # Once space is back, saving works and numbering continues.
    assert store.save(_graph(seed=3).snapshot()).name == "000002"


def test_other_write_errors_are_store_errors(store, monkeypatch):
    def denied(path, data):
        raise OSError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(store_mod, "atomic_write_bytes", denied)
    with pytest.raises(StoreError, match="cannot write graph.msgpack") as info:
        store.save(_graph().snapshot())
    assert not isinstance(info.value, DiskFull)


def test_interrupted_save_is_ignored(store):
    store.save(_graph(seed=1).snapshot())
    # A crash after the rename but before ``latest`` moved, with the manifest missing.
    p = store.save(_graph(seed=2).snapshot())
    (p / "MANIFEST.json").unlink()
    (store.root / "latest").write_text("000001\n")
    state = store.load()
    assert state.path.name == "000001" and not state.fell_back_from


def test_bad_extra_state_is_refused_before_writing(store):
    with pytest.raises(StoreError, match="without '/'"):
        store.save(_graph().snapshot(), {"a/b": np.zeros(2)})
    with pytest.raises(StoreError, match="Python objects"):
        store.save(_graph().snapshot(), {"a": np.array([object()])})
    with pytest.raises(StoreError, match="metadata.json"):
        store.save(_graph().snapshot(), metadata={"x": object()})
    assert store.names() == []


def test_manifest_lists_sizes_and_hashes(store):
    p = store.save(_graph().snapshot(with_mesh=True))
    manifest = json.loads((p / "MANIFEST.json").read_text())
    for name, info in manifest["files"].items():
        assert (p / name).stat().st_size == info["bytes"] and len(info["sha256"]) == 64


def test_disk_full_inside_spark_dsg(tmp_path, monkeypatch):
    dsg = pytest.importorskip("shared.graph.dsg")
    pytest.importorskip("spark_dsg")
    store = MapStore(tmp_path / "map")
    store.save(_graph(seed=1).snapshot())

    def failing(snap, path, include_mesh=True):
        raise RuntimeError("could not write file")

    monkeypatch.setattr(dsg, "save_dsg", failing)
    monkeypatch.setattr(store_mod.shutil, "disk_usage", lambda p: type("U", (), {"free": 0})())
    with pytest.raises(DiskFull, match="graph.sparkdsg"):
        store.save(_graph(seed=2).snapshot())
    monkeypatch.undo()
    assert store.names() == ["000001"] and store.load().path.name == "000001"
