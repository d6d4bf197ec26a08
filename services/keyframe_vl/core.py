"""The keyframe_vl core: masks, then CLIP features, for a keyframe; embeddings for queries.

No Zenoh here. Segmentation and CLIP are separate calls so the node can publish the masks
as soon as they exist and the features when CLIP is done (the tracker never waits for CLIP).
"""

from __future__ import annotations

import logging
from typing import Annotated

import numpy as np

from services.keyframe_vl.embedder import Embedder, warm_up_encoder
from shared.config.keyframe_vl import KeyframeVLConfig
from shared.devices import resolve_device
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures
from shared.messages.rpc import EmbedReply, EmbedRequest
from shared.perception import KeyframeImage, Masks, Segmenter, VLEncoder
from shared.perception.encoders import make_vl_encoder
from shared.perception.segmenters import make_segmenter

log = logging.getLogger(__name__)


def keyframe_image(req: KeyframeRequest) -> KeyframeImage:
    depth = None if req.depth is None else req.depth.astype(np.float32) / np.float32(req.depth_scale)
    return KeyframeImage(frame_index=req.frame_index, rgb=req.rgb, depth_m=depth, intrinsics=req.intrinsics)


class KeyframeVLCore:
    """Segmenter and VL encoder built from config (or given, for tests)."""

    def __init__(self, cfg: KeyframeVLConfig, segmenter: Segmenter | None = None, encoder: VLEncoder | None = None) -> None:
        self.cfg = cfg
        device = resolve_device(cfg.device, "keyframe_vl.device")
        self.segmenter = segmenter or make_segmenter(cfg.segmenter, device=device, fp16=cfg.fp16)
        self.encoder = encoder or make_vl_encoder(cfg.vl, device=device, fp16=cfg.fp16)
        self.embedder = Embedder(self.encoder, cfg.embed_cache_size)

    def warm_up(self) -> None:
        """Make the VL encoder's text path ready (:func:`warm_up_encoder`): a model loaded
        lazily is loaded now, so the first novel query text costs milliseconds."""
        warm_up_encoder(self.encoder)

    def segment(self, req: KeyframeRequest) -> tuple[KeyframeImage, Masks, KeyframeMasks]:
        image = keyframe_image(req)
        masks = self.segmenter.segment(image)
        msg = KeyframeMasks(frame_index=req.frame_index, masks=masks.masks, boxes=masks.boxes, scores=masks.scores)
        return image, masks, msg

    def features(self, image: KeyframeImage, masks: Masks) -> MaskFeatures:
        """The masks' CLIP features and, from an encoder that makes one, the keyframe's view."""
        feats = self.encoder.encode_crops(image, masks) if len(masks) else np.zeros((0, self.encoder.dim), np.float32)
        return MaskFeatures(
            frame_index=image.frame_index, features=np.asarray(feats, np.float32), model=self.encoder.name,
            view=self.view(image),
        )  # fmt: skip

    def view(self, image: KeyframeImage) -> Annotated[np.ndarray, "(D,) float32"] | None:
        """The encoder's whole-keyframe embedding (room naming); None from an encoder without
        ``encode_view`` or when it fails: the crops' features go out all the same, and fusion
        names rooms from their segments alone."""
        encode_view = getattr(self.encoder, "encode_view", None)
        if encode_view is None:
            return None
        try:
            view = np.asarray(encode_view(image), np.float32)
            if view.shape != (self.encoder.dim,) or not np.isfinite(view).all():
                raise ValueError(f"expected a finite ({self.encoder.dim},) vector, got shape {view.shape}")
        except Exception as exc:  # noqa: BLE001 - a view is an extra; the crops' features must not be lost
            log.warning("keyframe %d: no view from %s (%s: %s)", image.frame_index, self.encoder.name, type(exc).__name__, exc)
            return None
        return view

    def embed_text(self, text: str) -> Annotated[np.ndarray, "(D,) float32"]:
        return self.embedder.embed_text(text)

    def embed(self, req: EmbedRequest) -> EmbedReply:
        """Text or image to the encoder's space; failures come back as an error reply."""
        return self.embedder.embed(req)
