"""10^4 hostile payloads into every subscribed key and queryable of a running system (router,
keyframe_vl, tracker, fusion, query and viewer over loopback Zenoh) while the ``small``
preset streams through it. Nothing crashes or hangs, every rejection is counted exactly,
memory stays bounded, and the map equals the in-process one (the valid traffic is untouched).
The 10^5 run is ``benchmarks/fuzz.py``."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh
from hostile import KINDS, QUERYABLE, SUBSCRIBED, key_expr, payloads, rss_mb

from services.fusion.node import FusionNode
from services.keyframe_vl.node import KeyframeVLNode
from services.mapping import prepare_config, run_map
from services.query.client import QueryClient
from services.query.node import QueryNode
from services.router import run_router
from services.source.node import run_source
from services.tracker.node import TrackerNode
from shared.config import TrackGraphConfig
from shared.topics import Topics
from shared.transport import open_session

pytestmark = pytest.mark.faults

N_PAYLOADS = 10_000



class Fuzzer:
    """Sends payloads from its own session: puts to subscribed keys, gets to queryables."""

    def __init__(self, cfg: TrackGraphConfig, seed: int) -> None:
        self.session = open_session(cfg.transport)
        self.topics = Topics(cfg.robot_id)
        self.seed = seed
        self.sent: dict[str, int] = {}
        self.answers: dict[str, int] = {}
        """Queryable -> error replies received (a hostile request must get one)."""
        self.bad_answers: list[str] = []

    def run(self, n: int, seed: int, per_s: float | None = None) -> None:
        keys = {**SUBSCRIBED, **QUERYABLE}
        t0 = time.monotonic()
        for i, p in enumerate(payloads(n, seed, keys)):
            key = key_expr(self.topics, p.key)
            self.sent[p.key] = self.sent.get(p.key, 0) + 1
            if p.key in QUERYABLE:
                replies = list(self.session.get(key, payload=p.data, timeout=10.0))
                if len(replies) == 1 and replies[0].err is not None:
                    self.answers[p.key] = self.answers.get(p.key, 0) + 1
                else:
                    self.bad_answers.append(f"{p.key} {p.kind}: {len(replies)} replies, ok={replies[0].ok is not None if replies else None}")
            else:
                # BLOCK: Zenoh's default (DROP) may discard a put under load, and the counts must be exact
                self.session.put(key, p.data, congestion_control=zenoh.CongestionControl.BLOCK)
            if per_s is not None:
                ahead = t0 + (i + 1) / per_s - time.monotonic()
                if ahead > 0:
                    time.sleep(ahead)

    def close(self) -> None:
        self.session.close()


def rejected(stats) -> int:
    return stats.rejected + stats.dropped


@pytest.mark.zenoh
@pytest.mark.slow
def test_hostile_traffic_is_counted_and_harms_nothing(small, tmp_path, free_port):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    base = TrackGraphConfig.model_validate({
        "transport": {"mode": "client", "connect": [endpoint], "shared_memory": False},
        "keyframe_vl": {"segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}},
        "tracker": {"features": {"backend": "classical", "short_side": 240}, "wait_for_masks": True, "device": "cpu"},
        "source": {"max_frames": 48},
    })  # fmt: skip
    cfg = prepare_config(base, small)
    run_map(small, cfg, tmp_path / "in_process", progress=False)

    stop = threading.Event()
    router_cfg = cfg.transport.model_copy(update={"mode": "router", "connect": [], "listen": [endpoint]})
    router = threading.Thread(target=run_router, args=(router_cfg, stop), daemon=True)
    router.start()
    time.sleep(0.5)
    nodes: list = []
    fuzzer = None
    try:
        keyframe_vl = KeyframeVLNode(cfg)
        fusion = FusionNode(cfg, tmp_path / "distributed")
        tracker = TrackerNode(cfg)
        query = QueryNode(cfg)
        nodes += [keyframe_vl, fusion, tracker, query]
        viewer = None
        try:
            from services.viewer.node import ViewerNode

            viewer = ViewerNode(cfg, tmp_path / "map.rrd")
            nodes.append(viewer)
        except ImportError:
            pass
        fuzzer = Fuzzer(cfg, seed=0)
        time.sleep(1.0)

        # hostile traffic alone: memory must not grow with it
        before = rss_mb()
        fuzzer.run(N_PAYLOADS // 2, seed=1)
        time.sleep(1.0)
        growth_idle = rss_mb() - before

        # the rest interleaved with the valid stream
        worker = threading.Thread(target=fuzzer.run, args=(N_PAYLOADS - N_PAYLOADS // 2, 2), kwargs={"per_s": 400.0})
        worker.start()
        stats = run_source(cfg, small, wait_subscribers_s=20, progress=False)
        worker.join(timeout=120)
        assert not worker.is_alive(), "the fuzzer hung"
        assert stats.published == 48 and stats.dropped == 0
        assert fusion.finished.wait(120), f"fusion did not finish: {fusion.stats()}"
        got = fusion.core.snapshot()

        client = QueryClient(cfg.transport, session=fuzzer.session)
        deadline = time.monotonic() + 20
        while query.index.graph_seq < fusion.core.graph.graph_seq and time.monotonic() < deadline:
            time.sleep(0.1)
        hits = client.query("chair", top_k=3)
        assert hits and query.index.graph_seq == fusion.core.graph.graph_seq
    finally:
        for n in reversed(nodes):
            n.close()
        if fuzzer is not None:
            fuzzer.close()
        stop.set()
        router.join(timeout=10)

    assert sum(fuzzer.sent.values()) == N_PAYLOADS
    assert fuzzer.bad_answers == []
    # every hostile payload was counted as rejected (or dropped) by each subscriber of its key
    counted = {
        "frames": [tracker.subs[0].stats],
        "keyframe_masks": [tracker.subs[1].stats],
        "keyframe_features": [tracker.subs[2].stats],
        "end_of_sequence": [tracker.subs[3].stats],
        "keyframe_request": [keyframe_vl.requests.stats],
        "tracks_frame": [fusion.subs[0].stats],
        "tracks_features": [fusion.subs[1].stats],
        "tracks_end": [fusion.subs[2].stats],
        "graph_delta": [query.deltas.stats],
        "graph_snapshot": [fusion.snapshots.stats],
        "vl_embed": [keyframe_vl.embed.stats],
        "query": [query.queryable.stats],
    }
    if viewer is not None:
        counted["graph_delta"].append(viewer.subs[0].stats)
        # the viewer keeps only the newest frame: valid frames it drops are counted with the rest
        frames = viewer.subs[1].stats
        assert frames.rejected <= fuzzer.sent["tracks_frame"] <= frames.rejected + frames.dropped
    for key, links in counted.items():
        for link in links:
            assert rejected(link) == fuzzer.sent.get(key, 0), f"{key}: sent {fuzzer.sent.get(key, 0)}, counted {link.as_dict()}"
    for key in QUERYABLE:
        assert fuzzer.answers.get(key, 0) == fuzzer.sent.get(key, 0)
    assert fusion.errors == 0 and tracker.errors == 0
    assert growth_idle < 150, f"RSS grew {growth_idle:.0f} MB under hostile traffic alone"

    # the valid stream is untouched: the map is the in-process one
    from shared.graph.store import MapStore

    want = MapStore(tmp_path / "in_process" / "graph").load().snapshot
    assert [(s.id, s.tracks) for s in got.segments] == [(s.id, s.tracks) for s in want.segments]
    assert [s.gallery_tracks for s in got.segments] == [s.gallery_tracks for s in want.segments]


def test_every_generated_payload_is_refused_by_the_codec():
    """The generator's promise, which the exact counts above rely on."""
    from shared.codec import CodecError, decode

    keys = {**SUBSCRIBED, **QUERYABLE}
    kinds = set()
    for p in payloads(3000, seed=5, keys=keys):
        kinds.add(p.kind)
        with pytest.raises(CodecError):
            decode(p.data, keys[p.key])
    assert kinds == set(KINDS)
