"""keyframe_vl node: ``keyframe/request`` in; ``keyframe/masks`` as soon as segmentation is
done, ``keyframe/features`` when CLIP is done; the ``vl/embed`` queryable; a liveliness token.

CLIP runs on its own thread behind a bounded queue, so the next keyframe's masks never wait
for the previous keyframe's features.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import numpy as np

from services.keyframe_vl.core import KeyframeVLCore
from shared.config.root import TrackGraphConfig
from shared.messages.base import Envelope
from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures
from shared.messages.rpc import EmbedReply, EmbedRequest
from shared.topics import Topics
from shared.transport import (
    TypedPublisher,
    TypedQueryable,
    TypedSubscriber,
    declare_alive,
    open_session,
)

log = logging.getLogger(__name__)


class KeyframeVLNode:
    """Wires a :class:`KeyframeVLCore` to Zenoh; ``close()`` undeclares everything."""

    def __init__(self, cfg: TrackGraphConfig, core: KeyframeVLCore | None = None, session=None) -> None:
        self.cfg = cfg
        self.core = core or KeyframeVLCore(cfg.keyframe_vl)
        self.topics = Topics(cfg.robot_id)
        self._own_session = session is None
        self.session = session or open_session(cfg.transport)
        codec = cfg.transport.codec
        self.masks_pub = TypedPublisher(self.session, self.topics.keyframe_masks, KeyframeMasks, robot_id=cfg.robot_id, codec=codec)
        self.features_pub = TypedPublisher(self.session, self.topics.keyframe_features, MaskFeatures, robot_id=cfg.robot_id, codec=codec)
        self._clip_jobs: queue.Queue = queue.Queue(maxsize=8)
        self._stop = threading.Event()
        self._clip_thread = threading.Thread(target=self._clip_loop, name="keyframe_vl:clip", daemon=True)
        self._clip_thread.start()
        self.processed = 0
        self.failed = 0
        self.embed = TypedQueryable(
            self.session, self.topics.vl_embed, EmbedRequest, EmbedReply, self._on_embed,
            robot_id=cfg.robot_id, codec=codec, workers=2,
        )  # fmt: skip
        self.requests = TypedSubscriber(
            self.session, self.topics.keyframe_request, KeyframeRequest,
            codec=codec, policy="fifo", capacity=4, callback=self._on_request, name="keyframe_vl:requests",
        )  # fmt: skip
        self.token = declare_alive(self.session, self.topics.alive("keyframe_vl"))

    def _on_request(self, env: Envelope[KeyframeRequest]) -> None:
        req = env.body
        t0 = time.perf_counter()
        try:
            image, masks, msg = self.core.segment(req)
        except Exception as exc:  # noqa: BLE001 - answer the tracker, keep serving
            self.failed += 1
            log.exception("keyframe %d: segmentation failed", req.frame_index)
            h, w = req.rgb.shape[:2]
            empty = KeyframeMasks(
                frame_index=req.frame_index, masks=np.zeros((0, h, w), bool), boxes=np.zeros((0, 4), np.float32),
                scores=np.zeros(0, np.float32), error=f"{type(exc).__name__}: {exc}",
            )  # fmt: skip
            self.masks_pub.put(empty)
            return
        self.masks_pub.put(msg)
        self.processed += 1
        log.debug("keyframe %d: %d masks in %.0f ms", req.frame_index, len(masks), 1000 * (time.perf_counter() - t0))
        self._clip_jobs.put((image, masks))

    def _clip_loop(self) -> None:
        while not self._stop.is_set():
            try:
                image, masks = self._clip_jobs.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                msg = self.core.features(image, masks)
            except Exception as exc:  # noqa: BLE001
                log.exception("keyframe %d: CLIP failed", image.frame_index)
                msg = MaskFeatures(frame_index=image.frame_index, features=np.zeros((0, 1), np.float32), model=self.core.encoder.name, error=f"{type(exc).__name__}: {exc}")
            self.features_pub.put(msg)

    def _on_embed(self, env: Envelope[EmbedRequest]) -> EmbedReply:
        return self.core.embed(env.body)

    def stats(self) -> dict:
        return {
            "processed": self.processed,
            "failed": self.failed,
            "requests": self.requests.stats.as_dict(),
            "embed": self.embed.stats.as_dict(),
        }

    def close(self) -> None:
        self._stop.set()
        self.requests.close()
        self.embed.close()
        self._clip_thread.join(timeout=10)
        self.token.undeclare()
        self.masks_pub.close()
        self.features_pub.close()
        if self._own_session:
            self.session.close()
