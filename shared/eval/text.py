"""Text encoders as the evaluation sees them, and cosine scoring against them.

Any object with a ``dim`` and ``encode(texts) -> (N, dim) float32`` rows will do; the default
is the offline MiniLM encoder the simulated VL backend embeds its labels with
(:class:`shared.text.minilm.MiniLMTextEncoder`), so a map built with that backend is scored in
its own embedding space.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Protocol, runtime_checkable

import numpy as np

from shared.eval.errors import EvalInputError

log = logging.getLogger(__name__)


@runtime_checkable
class TextEncoder(Protocol):
    """Embeds texts to unit rows of a fixed dimension."""

    dim: int

    def encode(self, texts: Sequence[str]) -> Annotated[np.ndarray, "(N, dim) float32, unit rows"]: ...


def default_encoder() -> TextEncoder:
    """The MiniLM text encoder of the simulated VL backend (embeddings cached on disk)."""
    from shared.text.minilm import MiniLMTextEncoder

    return MiniLMTextEncoder()


def encoder_name(encoder: TextEncoder) -> str:
    return str(getattr(encoder, "name", type(encoder).__name__))


def encode_texts(encoder: TextEncoder, texts: Sequence[str]) -> Annotated[np.ndarray, "(N, dim) float32"]:
    """``encoder.encode(texts)`` checked for shape and finiteness, rows re-normalised."""
    texts = list(texts)
    dim = int(encoder.dim)
    if not texts:
        return np.zeros((0, dim), np.float32)
    out = np.asarray(encoder.encode(texts), dtype=np.float32)
    if out.shape != (len(texts), dim):
        raise ValueError(
            f"text encoder {encoder_name(encoder)} returned shape {out.shape} for {len(texts)} texts "
            f"(expected ({len(texts)}, {dim}))"
        )
    if not np.isfinite(out).all():
        raise ValueError(f"text encoder {encoder_name(encoder)} returned non-finite values")
    return unit_rows(out)


def unit_rows(x: Annotated[np.ndarray, "(N, D) float"]) -> Annotated[np.ndarray, "(N, D) float32"]:
    """Rows scaled to unit length; all-zero rows stay zero (their cosine with anything is 0)."""
    x = np.asarray(x, dtype=np.float32)
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return np.divide(x, norm, out=np.zeros_like(x), where=norm > 0)


def check_dimension(embeddings_dim: int, encoder: TextEncoder, embeddings_path: Path) -> None:
    """A prediction's feature dimension must be the encoder's, or cosines mean nothing."""
    if embeddings_dim != int(encoder.dim):
        raise EvalInputError(
            embeddings_path,
            f"features have dimension {embeddings_dim} but the text encoder "
            f"{encoder_name(encoder)} embeds to dimension {int(encoder.dim)}; evaluate with the "
            "encoder whose space the map was built in",
        )


def cosine(
    a: Annotated[np.ndarray, "(N, D) float"], b: Annotated[np.ndarray, "(M, D) float"]
) -> Annotated[np.ndarray, "(N, M) float32"]:
    """Cosine similarity of every row of ``a`` with every row of ``b`` (zero rows give 0)."""
    return unit_rows(a) @ unit_rows(b).T
