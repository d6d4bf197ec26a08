"""Text and image queries into the VL encoder's space, with a bounded cache of text
embeddings: the ``vl/embed`` queryable of keyframe_vl and the query service's local encoder
both answer through it."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Annotated

import numpy as np

from shared.messages.rpc import EmbedReply, EmbedRequest
from shared.perception import VLEncoder


class TextCache:
    """The newest ``size`` text embeddings (clients repeat the same prompts), shared by the
    threads of a queryable; ``size`` 0 remembers nothing."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[str, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, text: str, compute: Callable[[], np.ndarray]) -> Annotated[np.ndarray, "(D,) float32"]:
        """The cached embedding of ``text``, else ``compute()``'s, remembered."""
        with self._lock:
            hit = self._items.get(text)
            if hit is not None:
                self._items.move_to_end(text)
                return hit
        vec = compute()  # outside the lock: an encoder or a round trip may take a while
        if self.size:
            with self._lock:
                self._items[text] = vec
                while len(self._items) > self.size:
                    self._items.popitem(last=False)
        return vec


WARMUP_TEXT = "a photo of something"
"""What a warm-up embeds (any text: the encoder's own warm-up skips its caches)."""


def warm_up_encoder(encoder: VLEncoder) -> None:
    """Make ``encoder`` ready to embed a novel text at its normal speed: its own ``warm_up()``
    where it has one (a lazily loaded text model), else one text through its text tower."""
    warm = getattr(encoder, "warm_up", None)
    if warm is not None:
        warm()
    else:
        encoder.encode_text([WARMUP_TEXT])


class Embedder:
    """One encoder and its text cache."""

    def __init__(self, encoder: VLEncoder, cache_size: int = 256) -> None:
        self.encoder = encoder
        self._cache = TextCache(cache_size)

    @property
    def name(self) -> str:
        return self.encoder.name

    def warm_up(self) -> None:
        """The encoder's warm-up (:func:`warm_up_encoder`), past this cache."""
        warm_up_encoder(self.encoder)

    def embed_text(self, text: str) -> Annotated[np.ndarray, "(D,) float32"]:
        return self._cache.get(text, lambda: np.asarray(self.encoder.encode_text([text])[0], np.float32))

    def embed(self, req: EmbedRequest) -> EmbedReply:
        """Text or image to the encoder's space; failures come back as an error reply that
        names the request's field."""
        try:
            if req.text is not None:
                vec = self.embed_text(req.text)
            else:
                vec = np.asarray(self.encoder.encode_image(req.image), np.float32)
        except (ValueError, RuntimeError) as exc:
            field = "text" if req.text is not None else "image"
            return EmbedReply(model=self.encoder.name, error=f"{type(req).__name__}.{field}: {exc}")
        return EmbedReply(embedding=vec, model=self.encoder.name)
