"""Text and image queries into the VL encoder's space, with a bounded cache of text
embeddings: the ``vl/embed`` queryable of keyframe_vl and the query service's local encoder
both answer through it."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Annotated

import numpy as np

from services.keyframe_vl.types import VLEncoder
from shared.messages.rpc import EmbedReply, EmbedRequest


class Embedder:
    """One encoder and its text cache (clients repeat the same prompts)."""

    def __init__(self, encoder: VLEncoder, cache_size: int = 256) -> None:
        self.encoder = encoder
        self.cache_size = cache_size
        self._text_cache: OrderedDict[str, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        """Queryables answer on several threads; the cache is shared by them."""

    @property
    def name(self) -> str:
        return self.encoder.name

    def embed_text(self, text: str) -> Annotated[np.ndarray, "(D,) float32"]:
        with self._lock:
            hit = self._text_cache.get(text)
            if hit is not None:
                self._text_cache.move_to_end(text)
                return hit
        vec = np.asarray(self.encoder.encode_text([text])[0], np.float32)
        if self.cache_size:
            with self._lock:
                self._text_cache[text] = vec
                while len(self._text_cache) > self.cache_size:
                    self._text_cache.popitem(last=False)
        return vec

    def embed(self, req: EmbedRequest) -> EmbedReply:
        """Text or image to the encoder's space; failures come back as an error reply."""
        try:
            if req.text is not None:
                vec = self.embed_text(req.text)
            else:
                vec = np.asarray(self.encoder.encode_image(req.image, req.instances), np.float32)
        except (ValueError, RuntimeError) as exc:
            return EmbedReply(model=self.encoder.name, error=str(exc))
        return EmbedReply(embedding=vec, model=self.encoder.name)
