"""``trackgraph map`` and ``trackgraph launch`` run the same session classes: the tracker
and keyframe_vl sessions over the in-process bus, and the same classes in their Zenoh nodes
(three loopback peers: tracker, keyframe_vl, a driver standing in for the source and fusion),
give the same tracked frames and track features on the ``small`` preset with simulated
perception."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from services.keyframe_vl.build import build_keyframe_vl
from services.keyframe_vl.node import KeyframeVLNode
from services.keyframe_vl.session import KeyframeVLSession
from services.mapping import prepare_config
from services.tracker.build import build_tracker
from services.tracker.node import TrackerNode
from services.tracker.session import TrackerSession
from shared.config import TrackGraphConfig, TransportConfig
from shared.datasets import open_sequence
from shared.messages.frames import EndOfSequence, Frame, FrameAck, TrackedFrame
from shared.messages.keyframes import TrackFeatures
from shared.runtime.bus import InProcessBus
from shared.topics import Topics
from shared.transport import ZenohBus, open_session

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

FRAMES = 30
"""Two keyframes (0 and 24) and the frames propagated from each."""


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from shared.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "small"
    run_synth("small", 0, out)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Outputs:
    """What the tracker sends, collected from any bus."""

    def __init__(self, bus) -> None:
        t = Topics(bus.robot_id)
        self.tracked: list[TrackedFrame] = []
        self.features: list[TrackFeatures] = []
        self.ends: list[EndOfSequence] = []
        self.acked: list[int] = []
        bus.subscribe(t.tracks_frame, TrackedFrame, lambda env: self.tracked.append(env.body), capacity=256)
        bus.subscribe(t.tracks_features, TrackFeatures, lambda env: self.features.append(env.body), capacity=256)
        bus.subscribe(t.tracks_end, EndOfSequence, lambda env: self.ends.append(env.body))
        bus.subscribe(t.frame_ack, FrameAck, lambda env: self.acked.append(env.body.frame_index), capacity=256)

    def folded(self) -> dict[int, tuple]:
        """Each track's last features, as fusion keeps them (the number and grouping of
        feature messages depends on when CLIP answers; what they add up to does not)."""
        state: dict[int, tuple] = {}
        for msg in self.features:
            for f in msg.tracks:
                state[f.track_id] = (f.dino, f.clip, f.clip_count)
            for r in msg.retired:
                state[r] = ("retired",)
        return state


def _end(frames: list[Frame]) -> EndOfSequence:
    return EndOfSequence(frames_published=len(frames), frames_dropped=0, last_frame_index=frames[-1].frame_index)


def run_in_process(cfg: TrackGraphConfig, frames: list[Frame]) -> Outputs:
    bus = InProcessBus(cfg.robot_id)
    KeyframeVLSession(bus, build_keyframe_vl(cfg))
    TrackerSession(bus, cfg, build_tracker(cfg))
    out = Outputs(bus)
    t = Topics(cfg.robot_id)
    pub, end = bus.publisher(t.frames, Frame), bus.publisher(t.end_of_sequence, EndOfSequence)
    for f in frames:
        pub.put(f)
        bus.drain()
    end.put(_end(frames))
    bus.drain()
    bus.close()
    return out


def _wait(cond, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def run_over_zenoh(cfg: TrackGraphConfig, frames: list[Frame]) -> Outputs:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    listen = TransportConfig(mode="peer", connect=[], listen=[endpoint], shared_memory=False)
    join = TransportConfig(mode="peer", connect=[endpoint], shared_memory=False)
    zenohs = [open_session(listen), open_session(join), open_session(join)]
    nodes = []
    try:
        tracker = TrackerNode(cfg, session=zenohs[0])
        nodes.append(tracker)
        kvl = KeyframeVLNode(cfg, session=zenohs[1])
        nodes.append(kvl)
        driver = ZenohBus(zenohs[2], cfg.robot_id)
        out = Outputs(driver)
        t = Topics(cfg.robot_id)
        pub, end = driver.publisher(t.frames, Frame), driver.publisher(t.end_of_sequence, EndOfSequence)
        links = [pub, tracker.session.requests, kvl.session.masks_out, kvl.session.features_out, tracker.session.tracked,
                 tracker.session.features, tracker.session.ends, tracker.session.acks]  # fmt: skip
        _wait(lambda: all(p.has_subscribers() for p in links), "the peers to meet")
        time.sleep(0.3)
        for f in frames:
            pub.put(f)
            # one frame in flight, as a lossless source with a window of one
            _wait(lambda k=f.frame_index: k in out.acked, f"the ack of frame {f.frame_index}")
        end.put(_end(frames))
        _wait(lambda: out.ends, "tracks/end")
        _wait(lambda: len(out.tracked) == len(frames), "every tracked frame")
        report = tracker.book.report()
        assert {c.name: c.processed for c in report.inputs}["frames"] == len(frames)
        assert report.figures["keyframes"]["answered"] == 2 and report.state == "finished"
        driver.close()
        return out
    finally:
        for n in reversed(nodes):
            n.close()
        for z in zenohs:
            z.close()


def test_the_tracker_session_gives_the_same_outputs_over_both_buses(small):
    base = TrackGraphConfig.model_validate({
        "keyframe_vl": {"device": "cpu", "segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}},
        "tracker": {"features": {"backend": "classical", "short_side": 240}, "wait_for_masks": True, "device": "cpu"},
    })  # fmt: skip
    cfg = prepare_config(base, small)
    reader = open_sequence(small)
    frames = [reader.frame(i) for i in range(FRAMES)]

    want = run_in_process(cfg, frames)
    got = run_over_zenoh(cfg, frames)

    assert [tf.frame.frame_index for tf in got.tracked] == [tf.frame.frame_index for tf in want.tracked] == list(range(FRAMES))
    for a, b in zip(got.tracked, want.tracked, strict=True):
        np.testing.assert_array_equal(a.track_ids, b.track_ids)
        assert a.keyframe == b.keyframe and a.tracks == b.tracks
    assert len(np.unique(want.tracked[-1].track_ids)) > 3  # something was tracked
    a, b = got.folded(), want.folded()
    assert sorted(a) == sorted(b) and any(v[1] is not None for v in b.values())
    for tid in b:
        for x, y in zip(a[tid], b[tid], strict=True):
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y)
            else:
                assert x == y
    assert got.ends[0].last_frame_index == want.ends[0].last_frame_index == FRAMES - 1
    assert got.acked == want.acked == list(range(FRAMES))
