"""The services as separate Zenoh participants on loopback: source -> tracker <-> keyframe_vl,
tracker -> fusion. Lossless replay must give the in-process map (same segments, same tracks)."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from services.fusion.node import FusionNode
from services.keyframe_vl.node import KeyframeVLNode
from services.mapping import prepare_config, run_map
from services.router import run_router
from services.source.node import run_source
from services.tracker.node import TrackerNode
from shared.config import TrackGraphConfig

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]


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


def _run_distributed(cfg, endpoint: str, seq, out) -> FusionNode:
    """A router on ``endpoint``, keyframe_vl, fusion and the tracker as Zenoh participants, and
    the source replaying 48 frames of ``seq`` losslessly; returns fusion (closed) once it has
    finished the map."""
    stop = threading.Event()
    router_cfg = cfg.transport.model_copy(update={"mode": "router", "connect": [], "listen": [endpoint]})
    router = threading.Thread(target=run_router, args=(router_cfg, stop), daemon=True)
    router.start()
    time.sleep(0.5)
    nodes = []
    try:
        nodes.append(KeyframeVLNode(cfg))
        fusion = FusionNode(cfg, out)
        nodes.append(fusion)
        nodes.append(TrackerNode(cfg))
        time.sleep(1.0)
        stats = run_source(cfg, seq, wait_subscribers_s=20, progress=False)
        assert stats.published == 48 and stats.dropped == 0
        assert fusion.finished.wait(120), f"fusion did not finish: {fusion.stats()}"
    finally:
        for n in reversed(nodes):
            n.close()
        stop.set()
        router.join(timeout=10)
    return fusion


def test_distributed_lossless_equals_in_process(small, tmp_path):
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    base = TrackGraphConfig.model_validate({
        "transport": {"mode": "client", "connect": [endpoint], "shared_memory": False},
        "keyframe_vl": {"segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}},
        "tracker": {"features": {"backend": "classical", "short_side": 240}, "wait_for_masks": True, "device": "cpu"},
        "source": {"max_frames": 48},
    })  # fmt: skip
    cfg = prepare_config(base, small)

    reference = run_map(small, cfg, tmp_path / "in_process", progress=False)

    fusion = _run_distributed(cfg, endpoint, small, tmp_path / "distributed")
    got = fusion.core.snapshot()

    from shared.graph.store import MapStore

    want = MapStore(tmp_path / "in_process" / "graph").load().snapshot
    assert reference["segments"] == len(got.segments)
    assert [(s.id, s.tracks) for s in got.segments] == [(s.id, s.tracks) for s in want.segments]
    assert [s.gallery_tracks for s in got.segments] == [s.gallery_tracks for s in want.segments]


@pytest.fixture(scope="module")
def drifting(tmp_path_factory):
    """The small scene with drifting odometry, and a loop-closure correction at frame 30
    (true poses up to it) sent 6 frames late, as a back end would."""
    from shared.messages.poses import PoseCorrection
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "drifting"
    run_synth("small", 0, out, drift=0.05)
    true = np.loadtxt(out / "traj_gt.txt").reshape(-1, 4, 4)
    c = PoseCorrection(correction_id=1, frame_index=30, frames=np.arange(31), poses=true[:31], apply_after_frame=36)
    (out / "late.jsonl").write_text(c.to_json() + "\n")
    return out


def test_distributed_corrections_equal_in_process(drifting, tmp_path):
    """The source replays the correction on poses/correction; fusion applies it after the same
    frame as the in-process map does, and the two maps are the same."""
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    base = TrackGraphConfig.model_validate({
        "transport": {"mode": "client", "connect": [endpoint], "shared_memory": False},
        "keyframe_vl": {"segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}},
        "tracker": {"features": {"backend": "classical", "short_side": 240}, "wait_for_masks": True, "device": "cpu"},
        "source": {"max_frames": 48, "corrections": str(drifting / "late.jsonl")},
    })  # fmt: skip
    cfg = prepare_config(base, drifting)
    run_map(drifting, cfg, tmp_path / "in_process", progress=False)

    fusion = _run_distributed(cfg, endpoint, drifting, tmp_path / "distributed")
    got, corrections = fusion.core.snapshot(), fusion.core.corrections

    from shared.graph.store import MapStore

    want = MapStore(tmp_path / "in_process" / "graph").load().snapshot
    assert corrections.applied == 1 and corrections.last_id == 1
    np.testing.assert_allclose(got.trajectory, want.trajectory, atol=1e-9)
    true = np.loadtxt(drifting / "traj_gt.txt").reshape(-1, 4, 4)
    np.testing.assert_allclose(got.trajectory[:31, :3], true[:31, :3, 3], atol=1e-9)
    assert [(s.id, s.tracks) for s in got.segments] == [(s.id, s.tracks) for s in want.segments]
    for a, b in zip(got.segments, want.segments, strict=True):
        np.testing.assert_allclose(a.centroid, b.centroid, atol=1e-6)
