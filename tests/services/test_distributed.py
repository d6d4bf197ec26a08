"""The services as separate Zenoh participants on loopback: source -> tracker <-> keyframe_vl,
tracker -> fusion. Lossless replay must give the in-process map (same segments, same tracks)."""

from __future__ import annotations

import socket
import threading
import time

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

    stop = threading.Event()
    router_cfg = cfg.transport.model_copy(update={"mode": "router", "connect": [], "listen": [endpoint]})
    router = threading.Thread(target=run_router, args=(router_cfg, stop), daemon=True)
    router.start()
    time.sleep(0.5)
    nodes = []
    try:
        nodes.append(KeyframeVLNode(cfg))
        fusion = FusionNode(cfg, tmp_path / "distributed")
        nodes.append(fusion)
        nodes.append(TrackerNode(cfg))
        time.sleep(1.0)
        stats = run_source(cfg, small, wait_subscribers_s=20, progress=False)
        assert stats.published == 48 and stats.dropped == 0
        assert fusion.finished.wait(120), f"fusion did not finish: {fusion.stats()}"
        got = fusion.core.snapshot()
    finally:
        for n in reversed(nodes):
            n.close()
        stop.set()
        router.join(timeout=10)

    from shared.graph.store import MapStore

    want = MapStore(tmp_path / "in_process" / "graph").load().snapshot
    assert reference["segments"] == len(got.segments)
    assert [(s.id, s.tracks) for s in got.segments] == [(s.id, s.tracks) for s in want.segments]
    assert [s.gallery_tracks for s in got.segments] == [s.gallery_tracks for s in want.segments]
