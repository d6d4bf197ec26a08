"""keyframe_vl's coordination, without Zenoh: ``keyframe/request`` in; ``keyframe/masks`` as
soon as segmentation is done, ``keyframe/features`` when CLIP is done; the ``vl/embed``
queryable.

CLIP is a separate step so that the next keyframe's masks never wait for the previous
keyframe's features: given ``defer_clip``, a request hands its CLIP job to it (the node's own
thread runs :meth:`KeyframeVLSession.run_clip`); without, CLIP runs at once after the masks
are out (``trackgraph map``, where the masks are delivered first all the same). A failure in
either step is answered with an error message, so the tracker never waits for its time-out.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures
from shared.messages.rpc import EmbedReply, EmbedRequest
from shared.perception import KeyframeImage, Masks, VLEncoder
from shared.runtime.bus import Bus
from shared.runtime.session import Session
from shared.runtime.status import StatusBook

log = logging.getLogger(__name__)


@dataclass
class ClipJob:
    """A keyframe whose masks are out and whose CLIP features are still to compute."""

    image: KeyframeImage
    masks: Masks
    received_at: float
    """When its request arrived (the keyframe's latency is measured from there)."""


class KeyframeVLModels(Protocol):
    """What the session drives: :class:`~services.keyframe_vl.core.KeyframeVLCore`, or a
    stand-in with the same calls."""

    encoder: VLEncoder
    """Names the model in an error answer."""

    def segment(self, req: KeyframeRequest) -> tuple[KeyframeImage, Masks, KeyframeMasks]:
        """The keyframe's image, its masks, and the message that carries them."""

    def features(self, image: KeyframeImage, masks: Masks) -> MaskFeatures:
        """The CLIP features of ``masks`` (and the keyframe's view)."""

    def embed(self, req: EmbedRequest) -> EmbedReply:
        """A text's embedding, for ``vl/embed``."""


class KeyframeVLSession(Session):
    """A :class:`KeyframeVLModels` on a bus."""

    service = "keyframe_vl"
    serialized = False  # segmentation, CLIP and embeddings run on their own threads, as the core allows

    def __init__(
        self, bus: Bus, core: KeyframeVLModels, *, defer_clip: Callable[[ClipJob], None] | None = None,
        clock: Callable[[], float] = time.monotonic, book: StatusBook | None = None,
    ) -> None:  # fmt: skip
        super().__init__(bus, clock=clock, book=book)
        self.core = core
        self.defer_clip = defer_clip
        self.processed = 0
        """Keyframes whose masks went out."""
        self.failed = 0
        """Keyframes answered with an error, in segmentation or in CLIP."""
        self.masks_out = self.output("keyframe_masks", KeyframeMasks)
        self.features_out = self.output("keyframe_features", MaskFeatures)
        self.embed = self.serve("vl_embed", EmbedRequest, EmbedReply, self.core.embed, workers=2)
        self.requests = self.subscribe("keyframe_request", KeyframeRequest, self._on_request, capacity=4)
        self._refresh()

    def _on_request(self, req: KeyframeRequest) -> None:
        t0 = self.clock()
        try:
            image, masks, msg = self.core.segment(req)
        except Exception as exc:  # noqa: BLE001 - answer the tracker, keep serving
            self._count_failed()
            log.exception("keyframe %d: segmentation failed", req.frame_index)
            h, w = req.rgb.shape[:2]
            empty = KeyframeMasks(
                frame_index=req.frame_index, masks=np.zeros((0, h, w), bool), boxes=np.zeros((0, 4), np.float32),
                scores=np.zeros(0, np.float32), error=f"{type(exc).__name__}: {exc}",
            )  # fmt: skip
            self.masks_out.put(empty)
            self._refresh()
            return
        self.masks_out.put(msg)
        with self.lock:  # counters: segmentation and CLIP run on different threads
            self.processed += 1
        log.debug("keyframe %d: %d masks in %.0f ms", req.frame_index, len(masks), 1000 * (self.clock() - t0))
        job = ClipJob(image, masks, t0)
        self._refresh()
        if self.defer_clip is not None:
            self.defer_clip(job)
        else:
            self.run_clip(job)

    def run_clip(self, job: ClipJob) -> None:
        """CLIP features of one keyframe out (an error message if CLIP fails)."""
        try:
            msg = self.core.features(job.image, job.masks)
        except Exception as exc:  # noqa: BLE001 - answer the tracker, keep serving
            self._count_failed()
            log.exception("keyframe %d: CLIP failed", job.image.frame_index)
            msg = MaskFeatures(
                frame_index=job.image.frame_index, features=np.zeros((0, 1), np.float32), model=self.core.encoder.name,
                error=f"{type(exc).__name__}: {exc}",
            )  # fmt: skip
        try:
            self.features_out.put(msg)
        finally:
            self.book.work_done(max(self.clock() - job.received_at, 0.0))
            self._refresh()

    def _count_failed(self) -> None:
        with self.lock:
            self.failed += 1
        self.book.error()

    def _refresh(self) -> None:
        self.book.figure("processed", self.processed)
        self.book.figure("failed", self.failed)
