"""A live ``graph/snapshot`` with ``whole_map`` at the end of ``small`` carries the same mesh as
the saved map: fusion's session (the one its service runs, with a store and a map folder) on
the in-process bus, fed by the source and the ground-truth tracker as ``trackgraph launch``
feeds it, and the reply through the wire codec."""

from __future__ import annotations

import time

import numpy as np
import pytest

from services.fusion.core import FusionCore
from services.fusion.session import FusionSession
from services.mapping import prepare_config
from services.source.session import SourceSession
from services.tracker.build import build_tracker
from services.tracker.session import TrackerSession
from shared.codec import decode, encode
from shared.config import TrackGraphConfig
from shared.datasets import open_sequence
from shared.graph.store import MapStore
from shared.messages.graph import GraphSnapshot, SnapshotRequest
from shared.runtime.bus import InProcessBus

pytestmark = pytest.mark.slow

GT_TRACKS = {"keyframe_vl": {"vl": {"backend": "simulated"}}, "tracker": {"mode": "ground_truth"}}


def test_live_whole_map_snapshot_equals_the_saved_map(tmp_path):
    from shared.synth import run_synth

    seq = tmp_path / "small"
    run_synth("small", 0, seq, progress=False)
    cfg = prepare_config(TrackGraphConfig.model_validate(GT_TRACKS), seq)
    replay = cfg.source.model_copy(update={"mode": "lossless", "loops": 1})
    cfg = cfg.model_copy(update={"source": replay})
    out = tmp_path / "map"
    store = MapStore(out / "graph", robot_id=cfg.robot_id)
    bus = InProcessBus(cfg.robot_id)
    tracker = TrackerSession(bus, cfg, build_tracker(cfg), wait_for_masks=True)
    fusion = FusionSession(bus, cfg, FusionCore(cfg.fusion, device="cpu"), store=store, out=out)
    source = SourceSession(bus, open_sequence(seq, cfg.source.dataset, cfg.source), replay)
    try:
        while source.tick(time.monotonic()) is not None:
            bus.drain()
        deadline = time.monotonic() + 60
        while not fusion.finished.is_set() and time.monotonic() < deadline:
            now = time.monotonic()
            tracker.tick(now)
            fusion.tick(now)
            if not bus.drain():
                time.sleep(0.02)
        assert fusion.finished.is_set(), fusion.book.report()
        saved = store.load().snapshot.mesh  # the whole map, saved at the end
        live = bus.request(fusion.topics.graph_snapshot, SnapshotRequest(whole_map=True), GraphSnapshot, timeout=60.0)
        window = bus.request(fusion.topics.graph_snapshot, SnapshotRequest(with_mesh=True), GraphSnapshot, timeout=60.0)
    finally:
        for s in (source, fusion, tracker):
            s.close()
        bus.close()

    assert live.error is None and saved is not None
    # the archive holds most of the map by the end of small; the active window alone is less
    assert len(live.mesh.vertices) == len(saved.vertices) > len(window.mesh.vertices)
    assert len(live.mesh.faces) == len(saved.faces)
    np.testing.assert_array_equal(live.mesh.segment_ids, saved.segment_ids)
    # and it travels: the reply decodes under the default codec limits
    wire = decode(encode(live, robot_id=cfg.robot_id, seq=0, stamp=0.0, cfg=cfg.transport.codec), GraphSnapshot, cfg.transport.codec).body
    assert len(wire.mesh.vertices) == len(saved.vertices)
