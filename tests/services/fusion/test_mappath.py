"""fusion's map path (``fusion.map_path``): with ``async`` graph updates are built on a map
thread while frames go on being fused and acknowledged; deltas go out in order, each
naming the frame it reflects; corrections, snapshots and the end wait for the running
update; a failing update is counted and the next one runs; the async map ends with the
synchronous map's segments."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from services.fusion.mappath import MapPath, resolve_map_path
from services.fusion.session import FusionSession
from shared.config import TrackGraphConfig
from shared.messages.graph import GraphDelta, SnapshotRequest
from shared.messages.poses import PoseCorrection
from shared.runtime.bus import InProcessBus
from tests.services.fusion.test_fusion_session import FakeFusion, Rig

ASYNC = {"fusion": {"map_path": "async", "mesh_every_n_frames": 2}}


class GatedCore(FakeFusion):
    """FakeFusion with the capture/build split; each build waits for ``gate``."""

    def __init__(self, fail_at: tuple[int, ...] = ()) -> None:
        super().__init__(every=2)
        self.sync_updates = True
        self.gate = threading.Event()
        self.building = threading.Event()
        self.fail_at = set(fail_at)
        self.captured: list[int] = []

    def add_frame(self, tf):
        if self.sync_updates:
            return super().add_frame(tf)
        self.frames += 1
        self.last_frame_index = tf.frame.frame_index
        return None

    def capture_update(self) -> SimpleNamespace:
        self.captured.append(self.last_frame_index)
        return SimpleNamespace(frame_index=self.last_frame_index)

    def build_update(self, inp: SimpleNamespace) -> GraphDelta:
        frame_index = inp.frame_index
        self.building.set()
        assert self.gate.wait(10.0), "the test never opened the gate"
        if frame_index in self.fail_at:
            raise RuntimeError(f"update at frame {frame_index} failed")
        self.graph.graph_seq += 1
        return GraphDelta(graph_seq=self.graph.graph_seq, frame_index=frame_index)


def _wait_idle(session: FusionSession) -> None:
    session.map_path.join()


def test_auto_is_async_for_a_live_source_and_sync_for_a_replay():
    assert resolve_map_path(TrackGraphConfig()) == "sync"
    assert resolve_map_path(TrackGraphConfig.model_validate({"source": {"mode": "live"}})) == "async"
    assert resolve_map_path(TrackGraphConfig.model_validate({"source": {"mode": "live"}, "fusion": {"map_path": "sync"}})) == "sync"
    assert resolve_map_path(TrackGraphConfig.model_validate({"fusion": {"map_path": "async"}})) == "async"
    with pytest.raises(ValueError, match="map_path"):
        MapPath(FakeFusion(), "later", 10)  # type: ignore[arg-type]


def test_frames_are_fused_and_acked_while_an_update_is_built(clock, make_frame):
    core = GatedCore()
    rig = Rig(clock, core=core, config=ASYNC)
    s = rig.session
    assert not core.sync_updates  # the session's map path took the updates over
    for i in range(2):
        rig.frame(make_frame, i)
    assert core.building.wait(5.0) and core.captured == [1]
    # the update at frame 1 is held on the map thread: frames 2..9 are fused and acked anyway
    for i in range(2, 10):
        rig.frame(make_frame, i)
    assert rig.acks == list(range(10)) and core.frames == 10
    assert rig.deltas == [] and s.map_path.busy and core.captured == [1]  # one update at a time
    core.gate.set()
    _wait_idle(s)
    rig.frame(make_frame, 10)  # the frame path publishes what the map thread finished
    assert [d.frame_index for d in rig.deltas][:1] == [1]
    _wait_idle(s)
    rig.tick(0.2)
    assert [d.frame_index for d in rig.deltas] == [1, 10]  # the next capture came at frame 10
    assert [d.graph_seq for d in rig.deltas] == [1, 2]
    fig = s.book.report().figures["map_path"]
    assert fig["mode"] == "async" and fig["updates"] == 2 and fig["failed"] == 0
    s.close(save=False)


def test_a_failed_update_is_counted_and_the_next_one_runs(clock, make_frame):
    core = GatedCore(fail_at=(1,))
    core.gate.set()
    rig = Rig(clock, core=core, config=ASYNC)
    s = rig.session
    for i in range(2):
        rig.frame(make_frame, i)
    _wait_idle(s)
    for i in range(2, 5):
        rig.frame(make_frame, i)
    _wait_idle(s)
    rig.tick(0.2)
    assert [d.frame_index for d in rig.deltas] == [3]
    assert s.map_path.failed == 1 and s.book.report().errors == 1
    s.close(save=False)


def test_a_failed_capture_leaves_the_frame_fused_and_is_counted(clock, make_frame):
    core = GatedCore()
    core.gate.set()
    calls = []

    def capture():
        calls.append(core.last_frame_index)
        if len(calls) == 1:
            raise MemoryError("no room for the copy")
        return SimpleNamespace(frame_index=core.last_frame_index)

    core.capture_update = capture
    rig = Rig(clock, core=core, config=ASYNC)
    s = rig.session
    for i in range(4):
        rig.frame(make_frame, i)
    _wait_idle(s)
    rig.tick(0.2)
    assert rig.acks == [0, 1, 2, 3] and s.book.report().inputs  # every frame fused and acked
    assert rig.inputs()["tracks_frame"].rejected == 0
    assert calls == [1, 3] and [d.frame_index for d in rig.deltas] == [3]
    assert s.map_path.failed == 1 and s.book.report().errors == 1
    s.close(save=False)


def test_snapshots_corrections_and_the_end_wait_for_the_running_update(clock, make_frame):
    core = GatedCore()
    rig = Rig(clock, core=core, config=ASYNC)
    s = rig.session
    for i in range(2):
        rig.frame(make_frame, i)
    assert core.building.wait(5.0)
    answered: list = []
    asker = threading.Thread(target=lambda: answered.append(s._on_snapshot(SnapshotRequest())))
    asker.start()
    asker.join(0.3)
    assert asker.is_alive() and not answered  # the snapshot waits for the update being built
    core.gate.set()
    asker.join(5.0)
    assert answered and answered[0].graph_seq == 1
    # a correction due now publishes the finished update first, then its own
    core.gate.clear()
    for i in range(2, 4):
        rig.frame(make_frame, i)
    assert s.map_path.busy
    opener = threading.Timer(0.2, core.gate.set)
    opener.start()
    rig.bus.publisher(rig.topics.poses_correction, PoseCorrection).put(
        PoseCorrection(correction_id=1, frame_index=1, frames=[0], poses=np.eye(4)[None]))
    rig.bus.drain()
    opener.join()
    assert not s.map_path.busy and [d.frame_index for d in rig.deltas] == [1, 3]
    rig.send_end(3, 0)
    assert s.finished.is_set() and [d.graph_seq for d in rig.deltas] == [1, 2, 3]
    s.close(save=False)


@pytest.mark.slow
def test_an_async_map_ends_with_the_synchronous_maps_segments(drifting):
    from tests.services.fusion.test_corrections import Mapper

    n = 60
    sync = Mapper(drifting)
    sync.run(n)
    sync.core.finish()
    m = Mapper(drifting)
    cfg = m.cfg.model_copy(update={"fusion": m.cfg.fusion.model_copy(update={"map_path": "async"})})
    bus = InProcessBus(cfg.robot_id)
    deltas: list[GraphDelta] = []
    session = FusionSession(bus, cfg, m.core)
    bus.subscribe(session.topics.graph_delta, GraphDelta, lambda env: deltas.append(env.body))
    try:
        m.feed(session, range(n))
        session.finish()
        bus.drain()
    finally:
        session.close(save=False)
        bus.close()
    assert session.map_path.updates >= 1 and session.map_path.failed == 0
    seqs = [d.graph_seq for d in deltas]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    frames = [d.frame_index for d in deltas]
    assert frames == sorted(frames) and frames[-1] == n - 1
    tracks = sorted(sorted(s.tracks) for s in m.core.segments.segments.values())
    assert tracks == sorted(sorted(s.tracks) for s in sync.core.segments.segments.values())
