"""examples/: a raw Zenoh client and a stand-in keyframe_vl, written from docs/wire.md with
zenoh, msgpack and numpy only. Offline: they speak the wire exactly as the codec does. Live: the
raw client against a running system, and a map of ``small`` with the stand-in in keyframe_vl's
place (deploy/external-vl.yaml)."""

from __future__ import annotations

import ast
import importlib.util
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import yaml

from shared.codec import decode, encode
from shared.config import CodecConfig
from shared.messages import (
    EmbedReply,
    EmbedRequest,
    GraphSnapshot,
    KeyframeMasks,
    KeyframeRequest,
    MaskFeatures,
    QueryRequest,
    ServiceStatus,
    SnapshotRequest,
)

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
SYNTHETIC = ROOT / "deploy" / "configs" / "synthetic.yaml"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("name", ["raw_client", "external_keyframe_vl"])
def test_examples_import_only_zenoh_msgpack_numpy(name):
    tree = ast.parse((EXAMPLES / f"{name}.py").read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add((node.module or "").split(".")[0])
    assert imported - set(sys.stdlib_module_names) == {"zenoh", "msgpack", "numpy"}


def test_raw_client_speaks_the_codecs_wire():
    rc = _load("raw_client")
    env = decode(rc.pack("QueryRequest", {"text": "chair", "top_k": 3}, "robot0", 4), QueryRequest)
    assert env.body.text == "chair" and env.body.top_k == 3 and env.seq == 4 and env.robot_id == "robot0"
    assert decode(rc.pack("SnapshotRequest", {"with_mesh": False}, "robot0", 0), SnapshotRequest).body.with_mesh is False
    snap = GraphSnapshot(graph_seq=7, frame_index=3)
    for cfg in (CodecConfig(), CodecConfig(labels="raw", masks="rle")):
        body = rc.unpack(encode(snap, robot_id="robot0", seq=0, stamp=0.0, cfg=cfg), "GraphSnapshot", "robot0")
        assert body["graph_seq"] == 7 and body["segments"] == []
    with pytest.raises(ValueError, match="claims robot 'robot1'"):
        rc.unpack(encode(snap, robot_id="robot1", seq=0, stamp=0.0), "GraphSnapshot", "robot0")
    arr = np.arange(12, dtype=np.float32).reshape(3, 4)
    np.testing.assert_array_equal(rc._array(rc.nd(arr)), arr)

    replica = rc.Segments()
    replica.load({"graph_seq": 2, "segments": [{"id": 1, "centroid": [0, 0, 0]}]})
    assert replica.apply({"graph_seq": 2}) and replica.skipped == 1
    assert replica.apply({"graph_seq": 3, "segments": [{"id": 5, "centroid": [1, 2, 3]}], "removed_segments": [1]})
    assert set(replica.segments) == {5} and not replica.apply({"graph_seq": 5}) and replica.gaps == 1


def test_stand_in_keyframe_vl_speaks_the_codecs_wire():
    ev = _load("external_keyframe_vl")
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[:, 32:] = (200, 30, 30)
    rgb[10:30, 5:25] = (30, 30, 200)
    for cfg in (CodecConfig(), CodecConfig(depth="png", labels="raw")):
        req = KeyframeRequest(frame_index=5, rgb=rgb, depth=np.ones((48, 64), np.uint16), depth_scale=1000.0)
        body = ev.unpack(encode(req, robot_id="robot0", seq=0, stamp=0.0, cfg=cfg), "KeyframeRequest", "robot0")
        np.testing.assert_array_equal(body["rgb"], rgb)
    jpeg = ev.unpack(encode(KeyframeRequest(frame_index=5, rgb=rgb), robot_id="robot0", seq=0, stamp=0.0, cfg=CodecConfig(rgb="jpeg")), "KeyframeRequest", "robot0")
    assert isinstance(jpeg["rgb"], ev.Undecoded)
    masks, boxes, scores = ev.segment(rgb, 0.004, 40)
    assert masks.shape == (3, 48, 64) and (scores[:-1] >= scores[1:]).all()
    np.testing.assert_array_equal(boxes[2], [5, 10, 25, 30])
    feats = np.stack([ev.histogram(rgb[m]) for m in masks])
    # What it publishes is what TrackGraph's codec decodes and validates.
    got = msgpack.packb({"v": ev.SCHEMA_VERSION, "type": "KeyframeMasks", "robot": "robot0", "seq": 0, "stamp": 0.0,
                         "body": {"frame_index": 5, "masks": ev.nd(masks, "bits"), "boxes": ev.nd(boxes), "scores": ev.nd(scores), "error": None}})  # fmt: skip
    m = decode(got, KeyframeMasks).body
    np.testing.assert_array_equal(m.masks, masks)
    got = msgpack.packb({"v": ev.SCHEMA_VERSION, "type": "MaskFeatures", "robot": "robot0", "seq": 0, "stamp": 0.0,
                         "body": {"frame_index": 5, "features": ev.nd(feats), "model": ev.MODEL, "error": None}})  # fmt: skip
    f = decode(got, MaskFeatures).body
    np.testing.assert_allclose(np.linalg.norm(f.features, axis=1), 1.0, atol=1e-6)
    t = ev.text_embedding("chair")
    np.testing.assert_array_equal(t, ev.text_embedding("chair"))
    assert t.shape == (64,) and abs(float(np.linalg.norm(t)) - 1) < 1e-6 and not np.allclose(t, ev.text_embedding("lamp"))
    with pytest.raises(ev.BadRequest, match="expected a version 2 KeyframeRequest"):
        ev.unpack(encode(EmbedRequest(text="x"), robot_id="robot0", seq=0, stamp=0.0), "KeyframeRequest", "robot0")


def test_the_shipped_external_vl_launch_file_runs_the_stand_in(tmp_path):
    from services.launch import plan_launch

    seq = tmp_path / "seq"
    seq.mkdir()
    plan = plan_launch(ROOT / "deploy" / "external-vl.yaml", sequence=seq, out=tmp_path / "map", log_dir=tmp_path / "logs")
    cmd = plan.commands["keyframe_vl"]
    assert cmd[0] == sys.executable and Path(cmd[1]).resolve() == EXAMPLES / "external_keyframe_vl.py"
    assert cmd[2:] == ["--connect", "tcp/127.0.0.1:7447", "--robot", "robot0"]
    assert plan.commands["tracker"][:3] == [sys.executable, "-m", "services.cli"]


# ---------------------------------------------------------------- live


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out)
    return out


def _launch(tmp_path: Path, services: list[dict], frames: int, **extra) -> Path:
    port = _free_port()
    doc = {
        "config": str(SYNTHETIC),
        "set": ["tracker.wait_for_masks=true", "tracker.device=cpu", "transport.shared_memory=false", f"source.max_frames={frames}"],
        "connect": [f"tcp/127.0.0.1:{port}"],
        "listen": [f"tcp/127.0.0.1:{port}"],
        "services": services,
        **extra,
    }
    path = tmp_path / "launch.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _wait(sup, cond, what: str, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert sup.error is None, sup.error
        assert time.monotonic() < deadline, f"{what}: {sup.summary()}"
        time.sleep(0.2)


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_raw_client_against_a_live_system(small, tmp_path):
    """While ``small`` is being mapped: a text query answered, a snapshot read, deltas followed."""
    from services.launch import Supervisor, plan_launch
    from services.query.client import QueryClient

    services = [
        {"name": "router"},
        {"name": "keyframe_vl"},
        {"name": "fusion"},
        {"name": "query"},
        {"name": "tracker", "after": ["keyframe_vl"]},
        {"name": "source", "after": ["tracker", "fusion", "query"]},
    ]
    plan = plan_launch(_launch(tmp_path, services, 120, exit_when_finished=False), sequence=small, out=tmp_path / "map")
    sup = Supervisor(plan, status=False)
    runner = threading.Thread(target=sup.run, daemon=True)
    runner.start()
    try:
        _wait(sup, lambda: sup.procs["source"].state in ("alive", "finished"), "mapping started")
        # Once the map has segments (asked the project's way), the raw client must see them too.
        with QueryClient(plan.system.transport, robot_id=plan.system.robot_id, timeout_s=10) as client:
            _wait(sup, lambda: bool(client.ask(QueryRequest(text="chair")).hits), "a first segment")
        cmd = [sys.executable, str(EXAMPLES / "raw_client.py"), "--connect", plan.launch.connect[0], "--robot", plan.system.robot_id,
               "--text", "chair", "--follow", "6", "--wait", "120", "--json"]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert out.returncode == 0, out.stderr + out.stdout
        got = json.loads(out.stdout.strip().splitlines()[-1])
    finally:
        sup.stop_event.set()
        runner.join(timeout=120)
    assert "error" not in got and got["query"]["error"] is None, got
    assert got["snapshot"]["graph_seq"] >= 1 and got["snapshot"]["segments"] >= 1
    hits = got["query"]["hits"]
    assert 1 <= len(hits) <= 5 and all(a["score"] >= b["score"] for a, b in zip(hits, hits[1:], strict=False)), hits
    assert got["deltas"]["received"] >= 1 and got["deltas"]["last_seq"] >= got["snapshot"]["graph_seq"], got
    assert got["segments"] >= 0 and got["deltas"]["applied"] + got["deltas"]["skipped"] >= 1


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_small_is_mapped_with_the_stand_in_keyframe_vl(small, tmp_path):
    """deploy/external-vl.yaml's services on a free port: the stand-in answers every keyframe,
    the map has segments, and its status and embeddings come through."""
    from services.launch import Supervisor, plan_launch
    from shared.graph.store import MapStore
    from shared.topics import Topics
    from shared.transport import TypedSubscriber, open_session, request

    shipped = yaml.safe_load((ROOT / "deploy" / "external-vl.yaml").read_text())
    services = shipped["services"]
    for s in services:
        if "command" in s:
            s["command"] = [a.replace("{here}", str(ROOT / "deploy")) for a in s["command"]]
    plan = plan_launch(_launch(tmp_path, services, 48, exit_when_finished=False), sequence=small, out=tmp_path / "map")
    sup = Supervisor(plan, status=False)
    runner = threading.Thread(target=sup.run, daemon=True)
    runner.start()
    session = None
    try:
        _wait(sup, lambda: sup.procs["keyframe_vl"].state == "alive", "the stand-in is alive", 120)
        session = open_session(plan.system.transport)
        topics = Topics(plan.system.robot_id)
        status = TypedSubscriber(session, topics.status("keyframe_vl"), ServiceStatus)
        _wait(sup, lambda: (tmp_path / "map" / "run.json").exists(), "the map finished", 500)
        report = None
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and (report is None or report.body.figures.get("processed", 0) < 6):
            report = status.recv(timeout=2) or report
        assert report is not None and report.body.service == "keyframe_vl" and report.body.figures["processed"] >= 6, report
        assert report.body.figures["failed"] == 0
        reply = request(session, topics.vl_embed, EmbedRequest(text="chair"), EmbedReply, robot_id=plan.system.robot_id, timeout=5).body
        assert reply.error is None and reply.embedding.shape == (64,) and reply.model.startswith("external:")
        status.close()
    finally:
        if session is not None:
            session.close()
        sup.stop_event.set()
        runner.join(timeout=120)
    snap = MapStore(tmp_path / "map" / "graph").load().snapshot
    run = json.loads((tmp_path / "map" / "run.json").read_text())
    assert run["frames"] == 48 and run["segments"] > 0 and len(snap.segments) > 0
    # The segments carry the stand-in's 64-d histograms as their galleries.
    assert any(s.gallery.shape[1:] == (64,) for s in snap.segments if len(s.gallery_tracks))
