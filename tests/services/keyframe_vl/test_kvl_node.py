"""keyframe_vl over Zenoh on loopback: masks then features, bad requests, embeddings."""

from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest

from services.keyframe_vl.node import KeyframeVLNode
from shared.config import TrackGraphConfig, TransportConfig
from shared.geometry import Intrinsics
from shared.messages import EmbedReply, EmbedRequest, KeyframeMasks, KeyframeRequest, MaskFeatures
from shared.topics import Topics
from shared.transport import TransportError, TypedPublisher, TypedSubscriber, open_session, request

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


H, W = 48, 64


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rgb = np.full((H, W, 3), 200, np.uint8)
    inst = np.full((H, W), -1, np.int32)
    rgb[8:30, 6:28] = (200, 30, 30)
    inst[8:30, 6:28] = 0
    rgb[12:40, 38:58] = (30, 30, 200)
    inst[12:40, 38:58] = 1
    depth = np.full((H, W), 3000, np.uint16)
    depth[8:30, 6:28] = 1500
    depth[12:40, 38:58] = 2000
    return rgb, inst, depth


def _sequence(root):
    """A two-frame synthetic sequence: the simulated encoder reads its ground truth here, by
    the keyframe's index (no request carries it)."""
    from PIL import Image

    seq = root / "seq"
    for sub in ("gt", "results", "instances"):
        (seq / sub).mkdir(parents=True)
    samples = [
        {"object_id": 0, "name": "red armchair", "labels": {"image_attributes": {"synonyms": ["armchair"], "depictions": [], "vis_sim": [], "clutter": []}}},
        {"object_id": 1, "name": "lamp", "labels": {"image_attributes": {"synonyms": ["lamp"], "depictions": [], "vis_sim": [], "clutter": []}}},
    ]
    (seq / "gt" / "gt_categories.json").write_text(json.dumps({"name": "t", "dataset": {"samples": samples}}))
    rgb, inst, depth = _scene()
    for i in range(2):
        Image.fromarray(rgb).save(seq / "results" / f"frame{i:06d}.png")
        Image.fromarray(depth).save(seq / "results" / f"depth{i:06d}.png")
        Image.fromarray((inst + 1).astype(np.uint16)).save(seq / "instances" / f"instance{i:06d}.png")
    (seq / "traj.txt").write_text("\n".join(" ".join(str(v) for v in np.eye(4).ravel()) for _ in range(2)) + "\n")
    (seq / "intrinsics.json").write_text(json.dumps({"fx": 60, "fy": 60, "cx": 31.5, "cy": 23.5, "width": W, "height": H, "depth_scale": 1000.0}))
    return seq


def _request(frame_index: int) -> KeyframeRequest:
    rgb, _, depth = _scene()
    return KeyframeRequest(
        frame_index=frame_index, rgb=rgb, depth=depth, depth_scale=1000.0,
        intrinsics=Intrinsics(fx=60, fy=60, cx=31.5, cy=23.5, width=W, height=H),
    )  # fmt: skip


@pytest.fixture
def system(tmp_path):
    port = _free_port()
    node_cfg = TrackGraphConfig.model_validate({
        "transport": {"mode": "peer", "connect": [], "listen": [f"tcp/127.0.0.1:{port}"], "shared_memory": False},
        "keyframe_vl": {"device": "cpu", "segmenter": {"backend": "classical", "min_area_px": 20},
                        "vl": {"backend": "simulated", "ground_truth": str(_sequence(tmp_path)), "noise_std": 0.0}},
    })  # fmt: skip
    node = KeyframeVLNode(node_cfg)
    client = open_session(TransportConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
    try:
        yield node, client
    finally:
        client.close()
        node.close()


def _collect(sub, n, timeout=30.0):
    out, deadline = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        env = sub.recv(timeout=0.5)
        if env is not None:
            out.append((time.monotonic(), env.body))
    return out


def test_request_gets_masks_then_features_and_bad_input_is_survived(system):
    node, client = system
    topics = Topics("robot0")
    masks_sub = TypedSubscriber(client, topics.keyframe_masks, KeyframeMasks)
    feats_sub = TypedSubscriber(client, topics.keyframe_features, MaskFeatures)
    pub = TypedPublisher(client, topics.keyframe_request, KeyframeRequest, robot_id="robot0")
    raw = client.declare_publisher(topics.keyframe_request)
    try:
        assert pub.wait_for_subscribers(10)
        time.sleep(0.3)
        pub.put(_request(0))
        (t_mask, masks), = _collect(masks_sub, 1)
        (t_feat, feats), = _collect(feats_sub, 1)
        assert masks.frame_index == 0 and masks.error is None and len(masks.masks) >= 2
        assert feats.frame_index == 0 and feats.features.shape == (len(masks.masks), 384)
        assert t_mask <= t_feat
        np.testing.assert_allclose(np.linalg.norm(feats.features, axis=1), 1.0, atol=1e-4)
        assert feats.view is not None and feats.view.shape == (384,)  # the keyframe's view, over the wire
        assert abs(float(np.linalg.norm(feats.view)) - 1.0) < 1e-3

        # A malformed payload is counted and the node keeps serving.
        raw.put(b"\x93not a keyframe")
        pub.put(_request(1))
        (_, masks2), = _collect(masks_sub, 1)
        assert masks2.frame_index == 1
        deadline = time.monotonic() + 5
        while node.requests.stats.rejected < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert node.requests.stats.rejected == 1

        # CLIP that cannot run (the simulated encoder has no ground truth for frame 48 of a
        # two-frame sequence) answers with an error naming the keyframe.
        pub.put(_request(48))
        got = [f for _, f in _collect(feats_sub, 2) if f.frame_index == 48]
        assert got and got[0].error and "keyframe 48" in got[0].error and got[0].features.shape[0] == 0
    finally:
        raw.undeclare()
        pub.close()
        masks_sub.close()
        feats_sub.close()


def test_embed_answers_within_timeout(system):
    _, client = system
    key = Topics("robot0").vl_embed
    deadline = time.monotonic() + 10
    while True:
        try:
            rep = request(client, key, EmbedRequest(text="armchair"), EmbedReply, robot_id="robot0", timeout=5.0)
            break
        except TransportError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    assert rep.body.error is None and rep.body.embedding.shape == (384,)
    t0 = time.monotonic()
    again = request(client, key, EmbedRequest(text="armchair"), EmbedReply, robot_id="robot0", timeout=2.0)
    assert time.monotonic() - t0 < 2.0
    np.testing.assert_array_equal(again.body.embedding, rep.body.embedding)


class _WarmingCore:
    """A stand-in core that counts its warm-up and embeds every text the same."""

    class encoder:  # noqa: N801 - stands in for an encoder object
        name = "fake"
        dim = 4

    def __init__(self) -> None:
        self.warmed = 0

    def warm_up(self) -> None:
        self.warmed += 1

    def embed(self, req: EmbedRequest) -> EmbedReply:
        return EmbedReply(embedding=np.ones(4, np.float32) / 2, model="fake")


def test_alive_and_serving_vl_embed_only_once_the_models_are_warm():
    from shared.transport import LivelinessWatcher

    port = _free_port()
    cfg = TrackGraphConfig.model_validate({"transport": {"mode": "peer", "connect": [], "listen": [f"tcp/127.0.0.1:{port}"], "shared_memory": False}})
    core = _WarmingCore()
    node = KeyframeVLNode(cfg, core=core, start=False)
    client = open_session(TransportConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], shared_memory=False))
    watcher = LivelinessWatcher(client, "trackgraph/robot0/alive/**")
    key = Topics("robot0").vl_embed
    try:
        time.sleep(0.5)
        assert node.book.report().state == "starting" and core.warmed == 0 and not watcher.alive()
        with pytest.raises(TransportError):  # no vl/embed yet: nothing answers
            request(client, key, EmbedRequest(text="chair"), EmbedReply, robot_id="robot0", timeout=0.5)
        node.start()
        assert core.warmed == 1 and node.book.report().state == "running"
        assert watcher.wait_for("trackgraph/robot0/alive/keyframe_vl", timeout=5)
        reply = request(client, key, EmbedRequest(text="chair"), EmbedReply, robot_id="robot0", timeout=5).body
        assert reply.embedding is not None and "startup_s" in node.book.report().figures
    finally:
        watcher.close()
        client.close()
        node.close()
