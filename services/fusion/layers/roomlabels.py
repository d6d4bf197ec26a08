"""The room labels' text embeddings, asked of keyframe_vl's ``vl/embed`` (the map's own VL
encoder) over the session's bus, tried again with a doubling wait until they come; the core
names rooms once it has them."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Annotated

import numpy as np

if TYPE_CHECKING:
    from services.fusion.protocol import FusionCoreLike
    from shared.runtime.bus import Bus
    from shared.runtime.session import FairLock

log = logging.getLogger(__name__)

ROOM_LABELS_TIMEOUT_S = 2.0
"""Time-out of each ``vl/embed`` request for a room label."""
ROOM_LABELS_RETRY_S = (2.0, 60.0)
"""First wait after a failed fetch of the room labels, and the cap it doubles up to."""


def embed_labels(bus: Bus, key: str, labels: list[str], timeout: float) -> Annotated[np.ndarray, "(L, D) float32"]:
    """One ``vl/embed`` request per label on ``key``; raises when one is refused or the
    dimensions differ."""
    from shared.messages.rpc import EmbedReply, EmbedRequest

    rows = []
    for text in labels:
        reply = bus.request(key, EmbedRequest(text=text), EmbedReply, timeout=timeout)
        if reply.error is not None or reply.embedding is None:
            raise ValueError(f"vl/embed refused {text!r}: {reply.error or 'no embedding'}")
        rows.append(np.asarray(reply.embedding, np.float32))
    if len({r.shape for r in rows}) != 1:
        raise ValueError(f"vl/embed gave the room labels embeddings of {sorted({r.shape[0] for r in rows})} dimensions")
    return np.stack(rows)


class RoomLabelFetch:
    """``labels`` (``fusion.graph.room_labels``) fetched on ``key`` for ``core``, under
    ``lock`` when handed over; :meth:`maybe_fetch` waits twice as long after each failure."""

    def __init__(self, labels: list[str], bus: Bus, key: str, core: FusionCoreLike, lock: FairLock) -> None:
        self.labels = list(labels)
        self.bus, self.key, self.core, self.lock = bus, key, core, lock
        self.tries = 0
        """Fetches tried (:meth:`fetch`)."""
        self._at = 0.0
        self._wait = ROOM_LABELS_RETRY_S[0]

    @property
    def ready(self) -> bool:
        """Whether the core has the labels' embeddings."""
        return self.core.room_vocabulary is not None

    def fetch(self, timeout: float = ROOM_LABELS_TIMEOUT_S) -> bool:
        """Embed the labels and hand them to the core. True when the core has them (or there
        are none to fetch); False, logged, when keyframe_vl did not answer them all."""
        if not self.labels or self.ready:
            return True
        self.tries += 1
        try:
            embeddings = embed_labels(self.bus, self.key, self.labels, timeout)
        except Exception as exc:  # noqa: BLE001 - keyframe_vl may not be up yet: rooms stay unnamed until it is
            level = logging.INFO if self.tries == 1 else logging.DEBUG
            log.log(level, "fusion: room labels not embedded yet (%s); rooms are named once vl/embed answers", exc)
            return False
        with self.lock:
            self.core.set_room_vocabulary(self.labels, embeddings)
        log.info("fusion: %d room labels embedded (%d-d); rooms are named from the next update", len(self.labels), embeddings.shape[1])
        return True

    def maybe_fetch(self, now: float) -> None:
        """A fetch when one is due: until the labels are in, after each failure's wait."""
        try:
            if self.ready or not self.labels or now < self._at:
                return
            if not self.fetch():
                self._at = now + self._wait
                self._wait = min(2 * self._wait, ROOM_LABELS_RETRY_S[1])
        except Exception:  # noqa: BLE001 - the next tick tries again
            log.exception("fusion: fetching the room labels failed")
