"""The fusion session over the in-process bus with a fake core and a fake clock: duplicates,
acks, the end of the sequence once everything announced is in (or after the grace), the
snapshot queryable, periodic snapshots and resume, a failing frame."""

from __future__ import annotations

import numpy as np

from services.fusion.core import CorrectionCounters, CorrectionOutcome
from services.fusion.protocol import FusionCoreLike
from services.fusion.session import FusionSession
from shared.config import TrackGraphConfig
from shared.graph.store import MapStore
from shared.messages.frames import EndOfSequence, FrameAck, TrackedFrame
from shared.messages.graph import GraphDelta, GraphSnapshot, MeshChunk, SnapshotRequest
from shared.messages.keyframes import TrackFeature, TrackFeatures
from shared.runtime.bus import InProcessBus
from shared.topics import Topics


class FakeGraph:
    graph_seq = 0


class FakeSegments:
    segments: dict = {}


class FakeFusion:
    """The fusion core's protocol (:class:`FusionCoreLike`): a delta every ``every`` frames;
    its state is the frame count; corrections move nothing; it takes the room labels'
    embeddings, as FusionCore does."""

    def __init__(self, every: int = 2, bad: tuple[int, ...] = ()) -> None:
        self.every, self.bad = every, set(bad)
        self.frames = 0
        self.last_frame_index = -1
        self.features: list[int] = []
        self.graph = FakeGraph()
        self.segments = FakeSegments()
        self.corrections = CorrectionCounters()
        self.observations = None
        self.room_vocabulary = None
        self.finished = 0

    def add_frame(self, tf: TrackedFrame) -> GraphDelta | None:
        if tf.frame.frame_index in self.bad:
            raise ValueError(f"frame {tf.frame.frame_index} is bad")
        self.frames += 1
        self.last_frame_index = tf.frame.frame_index
        return self._delta() if self.frames % self.every == 0 else None

    def _delta(self) -> GraphDelta:
        self.graph.graph_seq += 1
        return GraphDelta(graph_seq=self.graph.graph_seq, frame_index=self.last_frame_index)

    def add_track_features(self, msg: TrackFeatures) -> None:
        self.features.append(msg.frame_index)

    def apply_correction(self, c) -> CorrectionOutcome:
        self.corrections.unchanged += 1
        return CorrectionOutcome(c.correction_id, "unchanged", None, 0, 0.0, 0.0, 0.0)

    def set_room_vocabulary(self, labels, embeddings) -> None:
        self.room_vocabulary = (list(labels), np.asarray(embeddings))

    def finish(self) -> GraphDelta:
        self.finished += 1
        return self._delta()

    def snapshot(self, with_mesh: bool = False, whole_map: bool = False) -> GraphSnapshot:
        self.asked = (with_mesh, whole_map)
        # the whole map is the active window's 2 vertices and 8 archived ones
        v = 10 if whole_map else 2 if with_mesh else 0
        mesh = MeshChunk(vertices=np.zeros((v, 3), np.float32), colors=np.zeros((v, 3), np.uint8), faces=np.zeros((0, 3), np.int32),
                         segment_ids=np.full(v, -1, np.int32)) if v else None  # fmt: skip
        return GraphSnapshot(graph_seq=self.graph.graph_seq, frame_index=self.last_frame_index, mesh=mesh)

    def state_dict(self) -> dict:
        return {"frames": np.array(self.frames), "last": np.array(self.last_frame_index)}

    def load_state_dict(self, state: dict, snapshot: GraphSnapshot) -> None:
        self.frames, self.last_frame_index = int(state["frames"]), int(state["last"])
        self.graph.graph_seq = snapshot.graph_seq


class Rig:
    def __init__(self, clock, core: FakeFusion | None = None, config: dict | None = None, **kw) -> None:
        self.clock = clock
        self.bus = InProcessBus("robot0", clock=clock)
        self.core = core or FakeFusion()
        cfg = TrackGraphConfig.model_validate({"fusion": {"snapshot_interval_s": 10.0}, **(config or {})})
        self.session = FusionSession(self.bus, cfg, self.core, clock=clock, **kw)
        t = self.topics = Topics("robot0")
        self.deltas: list[GraphDelta] = []
        self.acks: list[int] = []
        self.bus.subscribe(t.graph_delta, GraphDelta, lambda env: self.deltas.append(env.body))
        self.bus.subscribe(t.frame_ack, FrameAck, lambda env: self.acks.append(env.body.frame_index))
        self.frames = self.bus.publisher(t.tracks_frame, TrackedFrame)
        self.features = self.bus.publisher(t.tracks_features, TrackFeatures)
        self.end = self.bus.publisher(t.tracks_end, EndOfSequence)

    def frame(self, make_frame, i: int) -> None:
        fr = make_frame(i)
        self.frames.put(TrackedFrame(frame=fr, track_ids=np.zeros(fr.depth.shape, np.int32), tracks=[]))
        self.bus.drain()

    def feature(self, i: int) -> None:
        self.features.put(TrackFeatures(frame_index=i, tracks=[TrackFeature(track_id=0, dino=np.ones(4, np.float32))]))
        self.bus.drain()

    def send_end(self, last: int, features: int | None, published: int | None = None) -> None:
        n = last + 1 if published is None else published
        self.end.put(EndOfSequence(frames_published=n, frames_dropped=0, last_frame_index=last, track_features_published=features))
        self.bus.drain()

    def tick(self, dt: float) -> None:
        self.session.tick(self.clock.advance(dt))
        self.bus.drain()

    def inputs(self) -> dict:
        return {c.name: c for c in self.session.book.report().inputs}


def test_frames_fused_duplicates_skipped_and_every_frame_acked(clock, make_frame):
    rig = Rig(clock)
    for i in (0, 1, 1, 0, 2, 3):
        rig.frame(make_frame, i)
    s = rig.session
    assert rig.core.frames == 4 and s.duplicates == 2 and rig.acks == [0, 1, 1, 0, 2, 3]
    assert [d.graph_seq for d in rig.deltas] == [1, 2]
    report = s.book.report()
    calm = {"held": 0, "held_most": 0, "skipped": 0, "dropped": 0, "tracker_restarts": 0}
    corrections = {**CorrectionCounters().as_dict(), "pending": 0, "last_error": None}
    assert report.figures == {"frames": 4, "frames_in_map": 4, "duplicates": 2, "reorder": calm, "graph_seq": 2, "finished": False,
                              "room_labels": False, "corrections": corrections,
                              "map_path": {"mode": "sync", "busy": False, "updates": 0, "failed": 0, "capture_ms": 0.0, "build_ms": 0.0}}  # fmt: skip
    assert report.frames_done == 4 and report.published == {"frame_ack": 6, "graph_delta": 2}
    assert rig.inputs()["tracks_frame"].processed == 6


def test_the_map_finishes_only_once_everything_announced_is_in(clock, make_frame):
    rig = Rig(clock)
    rig.frame(make_frame, 0)
    rig.feature(0)
    rig.send_end(last=2, features=2)  # the tracker's end overtook frames 1, 2 and a feature message
    assert not rig.session.finished.is_set()
    assert rig.session.book.report().frames_expected == 3
    rig.frame(make_frame, 1)
    rig.frame(make_frame, 2)
    assert not rig.session.finished.is_set()
    rig.feature(2)
    assert rig.session.finished.is_set() and rig.core.finished == 1
    assert rig.deltas[-1].graph_seq == rig.core.graph.graph_seq
    assert rig.session.book.state == "finished" and rig.session.book.report().figures["finished"] is True
    rig.tick(1.0)
    assert rig.core.finished == 1  # once


def test_missing_messages_finish_the_map_after_the_grace(clock, make_frame):
    rig = Rig(clock, config={"fusion": {"snapshot_interval_s": 10.0, "end_grace_s": 4.0}})
    rig.frame(make_frame, 0)
    rig.send_end(last=5, features=3, published=6)
    rig.tick(4.0 - 1)
    assert not rig.session.finished.is_set()
    rig.tick(2)
    assert rig.session.finished.is_set()
    d = rig.session.delivery()
    assert {k: d[k] for k in ("frames_in_map", "frames_announced", "frames_lost", "frames_duplicate", "resumed_from")} == {
        "frames_in_map": 1, "frames_announced": 6, "frames_lost": 5, "frames_duplicate": 0, "resumed_from": None,
    }  # fmt: skip
    assert d["features_in_map"] == 0 and d["journal"] is None  # no store: no journal


def test_a_failing_frame_is_counted_acked_and_not_fatal(clock, make_frame):
    rig = Rig(clock, FakeFusion(bad=(1,)))
    for i in range(3):
        rig.frame(make_frame, i)
    assert rig.acks == [0, 1, 2] and rig.core.frames == 2
    c = rig.inputs()["tracks_frame"]
    assert c.rejected == 1 and c.processed == 2 and rig.session.book.errors == 1


def test_snapshot_queryable(clock, make_frame):
    rig = Rig(clock)
    for i in range(2):
        rig.frame(make_frame, i)
    snap = rig.bus.request(rig.topics.graph_snapshot, SnapshotRequest(), GraphSnapshot, timeout=1.0)
    assert snap.graph_seq == 1 and snap.frame_index == 1
    assert rig.inputs()["graph_snapshot"].processed == 1


def test_whole_map_snapshot_or_the_reason_it_cannot_travel(clock, make_frame):
    rig = Rig(clock)
    rig.frame(make_frame, 0)
    ask = lambda **kw: rig.bus.request(rig.topics.graph_snapshot, SnapshotRequest(**kw), GraphSnapshot, timeout=1.0)  # noqa: E731
    assert ask(with_mesh=True).mesh.vertices.shape == (2, 3) and rig.core.asked == (True, False)
    snap = ask(whole_map=True)  # whole_map implies the mesh
    assert snap.mesh.vertices.shape == (10, 3) and snap.error is None and rig.core.asked == (True, True)
    # 10 vertices are 120 bytes: over a 100-byte array limit the graph comes without the mesh, and why
    small = Rig(clock, config={"transport": {"codec": {"max_array_bytes": 100}}})
    small.frame(make_frame, 0)
    snap = small.bus.request(small.topics.graph_snapshot, SnapshotRequest(whole_map=True), GraphSnapshot, timeout=1.0)
    assert snap.mesh is None and snap.frame_index == 0
    assert snap.error.startswith("SnapshotRequest.whole_map: ") and "vertices are 120 bytes, over transport.codec.max_array_bytes 100" in snap.error
    # the active window's mesh is what it always was
    assert small.bus.request(small.topics.graph_snapshot, SnapshotRequest(with_mesh=True), GraphSnapshot, timeout=1.0).error is None


def test_periodic_snapshots_and_resume(clock, make_frame, tmp_path):
    store = MapStore(tmp_path / "graph", write_dsg=False)
    rig = Rig(clock, store=store, out=tmp_path)
    rig.frame(make_frame, 0)
    assert store.latest_name() is None
    rig.tick(11.0)  # the snapshot interval passed with a frame not yet saved
    assert store.latest_name() == "000001"
    rig.tick(11.0)  # nothing new: no new snapshot
    assert store.latest_name() == "000001"
    rig.frame(make_frame, 1)  # more than the interval since the last snapshot: one now
    assert store.latest_name() == "000002"
    rig.frame(make_frame, 2)
    assert store.latest_name() == "000002"
    rig.session.close(save=True)  # what came after the last snapshot is kept at close
    assert store.latest_name() == "000003"

    again = Rig(clock, FakeFusion(), store=store, out=tmp_path, resume=True)
    assert again.session.resumed_from is not None and again.core.last_frame_index == 2
    assert again.session.deltas.seq == again.core.graph.graph_seq == 1  # deltas go on from the snapshot
    for i in (2, 3):
        again.frame(make_frame, i)
    assert again.session.duplicates == 1 and again.core.frames == 4


def test_room_labels_are_fetched_through_vl_embed_with_backoff(clock):
    """No keyframe_vl at first: the fetch fails and is tried again after 2 s, then 4 s; once
    vl/embed is served the next due tick fetches every label, and none is asked again."""
    from shared.messages.rpc import EmbedReply, EmbedRequest

    core = FakeFusion()
    rig = Rig(clock, core=core, config={"fusion": {"snapshot_interval_s": 10.0, "graph": {"room_labels": ["kitchen", "bedroom"]}}})
    asked: list[str] = []
    rig.tick(0.0)
    assert rig.session.room_labels.tries == 1 and core.room_vocabulary is None
    rig.tick(1.0)  # within the 2 s wait: not tried
    assert rig.session.room_labels.tries == 1

    def embed(env):
        asked.append(env.body.text)
        return EmbedReply(embedding=np.full(3, 1 / np.sqrt(3), np.float32), model="fake")

    rig.tick(1.5)  # 2.5 s after the first try: the second fails too, next wait 4 s
    assert rig.session.room_labels.tries == 2
    rig.bus.serve(rig.topics.vl_embed, EmbedRequest, EmbedReply, embed)
    rig.tick(3.0)  # 5.5 s: 3 s after the second try, under the 4 s wait
    assert rig.session.room_labels.tries == 2 and asked == []
    rig.tick(1.5)  # 7 s: due
    assert asked == ["kitchen", "bedroom"] and core.room_vocabulary[0] == ["kitchen", "bedroom"]
    assert rig.session.book.report().figures["room_labels"] is True
    rig.tick(100.0)
    assert asked == ["kitchen", "bedroom"] and rig.session.room_labels.tries == 3


def test_a_refused_room_label_leaves_the_rooms_unnamed(clock):
    from shared.messages.rpc import EmbedReply, EmbedRequest

    core = FakeFusion()
    rig = Rig(clock, core=core, config={"fusion": {"snapshot_interval_s": 10.0, "graph": {"room_labels": ["kitchen"]}}})
    rig.bus.serve(rig.topics.vl_embed, EmbedRequest, EmbedReply, lambda env: EmbedReply(error="model not loaded"))
    assert rig.session.fetch_room_labels() is False and core.room_vocabulary is None


def test_the_fusion_cores_have_what_the_session_drives():
    """FusionCore and the tests' doubles all satisfy the protocol the session is typed with."""
    from services.fusion.core import FusionCore
    from tests.services.fusion.test_fusion_reorder import OrderLog

    cfg = TrackGraphConfig()
    for core in (FusionCore(cfg.fusion, device="cpu"), FakeFusion(), OrderLog()):
        assert isinstance(core, FusionCoreLike), type(core).__name__
