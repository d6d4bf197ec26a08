"""The keyframe_vl session over the in-process bus with a fake core: masks then features,
CLIP deferred to another runner, failures answered with errors, embeddings."""

from __future__ import annotations

import numpy as np
import pytest

from services.keyframe_vl.core import keyframe_image
from services.keyframe_vl.session import ClipJob, KeyframeVLSession
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures
from shared.messages.rpc import EmbedReply, EmbedRequest
from shared.perception import Masks
from shared.runtime.bus import BusError, InProcessBus
from shared.topics import Topics


class Encoder:
    name = "fake-clip"
    dim = 8


class FakeKeyframeVL:
    """One mask over the whole image; CLIP rows of ones; fails where told to."""

    def __init__(self, bad_segment: tuple[int, ...] = (), bad_clip: tuple[int, ...] = ()) -> None:
        self.bad_segment, self.bad_clip = set(bad_segment), set(bad_clip)
        self.encoder = Encoder()

    def segment(self, req: KeyframeRequest):
        if req.frame_index in self.bad_segment:
            raise RuntimeError("segmenter out of memory")
        h, w = req.rgb.shape[:2]
        masks = Masks(np.ones((1, h, w), bool), np.array([[0, 0, w, h]], np.float32), np.ones(1, np.float32))
        msg = KeyframeMasks(frame_index=req.frame_index, masks=masks.masks, boxes=masks.boxes, scores=masks.scores)
        return keyframe_image(req), masks, msg

    def features(self, image, masks) -> MaskFeatures:
        if image.frame_index in self.bad_clip:
            raise RuntimeError("CLIP out of memory")
        return MaskFeatures(frame_index=image.frame_index, features=np.ones((len(masks), 8), np.float32), model=self.encoder.name)

    def embed(self, req: EmbedRequest) -> EmbedReply:
        if req.text == "boom":
            raise ValueError("cannot embed that")
        return EmbedReply(embedding=np.ones(8, np.float32), model=self.encoder.name)


def rig(clock, core, **kw):
    bus = InProcessBus("robot0", clock=clock)
    session = KeyframeVLSession(bus, core, clock=clock, **kw)
    t = Topics("robot0")
    out: list = []
    bus.subscribe(t.keyframe_masks, KeyframeMasks, lambda env: out.append(env.body))
    bus.subscribe(t.keyframe_features, MaskFeatures, lambda env: out.append(env.body))
    return bus, session, bus.publisher(t.keyframe_request, KeyframeRequest), out


def request(k: int) -> KeyframeRequest:
    return KeyframeRequest(frame_index=k, rgb=np.zeros((4, 6, 3), np.uint8))


def test_masks_then_features_and_counts(clock):
    bus, session, pub, out = rig(clock, FakeKeyframeVL())
    pub.put(request(0))
    pub.put(request(3))
    bus.drain()
    assert [(type(m).__name__, m.frame_index) for m in out] == [
        ("KeyframeMasks", 0), ("MaskFeatures", 0), ("KeyframeMasks", 3), ("MaskFeatures", 3),
    ]  # fmt: skip
    assert out[1].features.shape == (1, 8)
    report = session.book.report()
    assert report.figures == {"processed": 2, "failed": 0}
    assert {c.name: c.processed for c in report.inputs}["keyframe_request"] == 2
    assert report.published == {"keyframe_masks": 2, "keyframe_features": 2} and report.latency_p50_ms is not None


def test_deferred_clip_leaves_the_masks_first(clock):
    jobs: list[ClipJob] = []
    bus, session, pub, out = rig(clock, FakeKeyframeVL(), defer_clip=jobs.append)
    pub.put(request(0))
    pub.put(request(3))
    bus.drain()
    assert [type(m).__name__ for m in out] == ["KeyframeMasks", "KeyframeMasks"] and len(jobs) == 2
    clock.advance(0.25)
    session.run_clip(jobs.pop(0))
    bus.drain()
    assert isinstance(out[-1], MaskFeatures) and out[-1].frame_index == 0
    assert session.book.report().latency_p50_ms == pytest.approx(250.0)


def test_failures_are_answered_with_errors_and_counted(clock):
    bus, session, pub, out = rig(clock, FakeKeyframeVL(bad_segment=(0,), bad_clip=(3,)))
    pub.put(request(0))
    pub.put(request(3))
    pub.put(request(6))
    bus.drain()
    masks = [m for m in out if isinstance(m, KeyframeMasks)]
    feats = [m for m in out if isinstance(m, MaskFeatures)]
    assert [m.frame_index for m in masks] == [0, 3, 6] and "out of memory" in masks[0].error and masks[0].masks.shape == (0, 4, 6)
    assert [f.frame_index for f in feats] == [3, 6] and feats[0].error and feats[0].features.shape[0] == 0 and feats[1].error is None
    report = session.book.report()
    assert report.figures == {"processed": 2, "failed": 2} and report.errors == 2


def test_embeddings_and_a_failing_one(clock):
    bus, session, _, _ = rig(clock, FakeKeyframeVL())
    key = Topics("robot0").vl_embed
    assert bus.request(key, EmbedRequest(text="chair"), EmbedReply, timeout=1.0).model == "fake-clip"
    with pytest.raises(BusError, match="cannot embed that"):
        bus.request(key, EmbedRequest(text="boom"), EmbedReply, timeout=1.0)
    c = {c.name: c for c in session.book.report().inputs}["vl_embed"]
    assert (c.received, c.processed, c.rejected) == (2, 1, 1)
