"""Request/reply messages: embeddings (``vl/embed``) and retrieval (``query``)."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from shared.arrays import ArraySpec
from shared.messages.base import METRES, SECONDS, Message, register
from shared.messages.frames import RGB
from shared.messages.graph import Vec3
from shared.messages.keyframes import Vector


def _one_of_text_or_image(text: str | None, image: np.ndarray | None) -> None:
    if (text is None) == (image is None):
        raise ValueError("give exactly one of text or image")
    if text is not None and not text.strip():
        raise ValueError("text is empty")
    if image is not None and (image.shape[0] == 0 or image.shape[1] == 0):
        raise ValueError(f"image has no pixels (shape {image.shape})")

@register
class EmbedRequest(Message):
    """Embed a text or an image in the VL encoder's space."""

    text: str | None = None
    """A text prompt."""
    image: RGB | None = None
    """(H, W, 3) uint8 image."""

    @model_validator(mode="after")
    def _one(self) -> EmbedRequest:
        """Exactly one of ``text`` (not blank) and ``image`` (with pixels)."""
        _one_of_text_or_image(self.text, self.image)
        return self

@register
class EmbedReply(Message):
    """The embedding, or an error."""

    embedding: Vector | None = None
    """(D,) L2-normalised feature."""
    model: str = ""
    """Encoder name."""
    error: str | None = None
    """Why no embedding was made."""

@register
class QueryRequest(Message):
    """Find segments by text or image (eq. 10)."""

    text: str | None = None
    """Text query, e.g. "red armchair"."""
    image: RGB | None = None
    """Image query."""
    top_k: int | None = Field(None, ge=1)
    """Results wanted; the service caps it."""
    room: int | None = None
    """Only segments in this room."""
    room_text: str | None = None
    """Only segments in the room that best matches this description (e.g. "kitchen"): the
    rooms are ranked by their feature (``RoomNode.feature``) against its embedding, and the
    reply's ``rooms`` says which room was taken. Not with ``room``."""
    target: Literal["segments", "rooms"] = "segments"
    """``rooms``: rank the graph's rooms instead of its segments ("which room is the kitchen");
    the answer is the reply's ``rooms``, best first, and ``hits`` is empty."""
    center: Annotated[Vec3 | None, METRES] = None
    """With radius: only segments whose centroid lies within radius of this point."""
    radius: Annotated[float | None, METRES] = Field(None, gt=0)
    """Radius around center (m)."""
    gallery: Literal["max", "mean"] | None = None
    """Override the service's gallery scoring."""
    deadline_s: Annotated[float | None, SECONDS] = Field(None, gt=0)
    """Time budget (s), counted from when the service receives the request, so the client's
    and the service's clocks need not agree. A request still waiting for a worker when it runs
    out is answered with an error starting "deadline exceeded" and not worked on; the embedding
    round trip and a wait for the replica to resynchronise are cut to what is left of it. None:
    no deadline, the service's own time-outs apply. ``QueryClient`` sets it from its timeout."""

    @model_validator(mode="after")
    def _valid(self) -> QueryRequest:
        """Exactly one of ``text`` (not blank) and ``image`` (with pixels); ``center`` and
        ``radius`` go together; ``room_text`` is not blank and not given with ``room``."""
        _one_of_text_or_image(self.text, self.image)
        if (self.center is None) != (self.radius is None):
            raise ValueError("center and radius go together")
        if self.room_text is not None and not self.room_text.strip():
            raise ValueError("room_text is empty")
        if self.room_text is not None and self.room is not None:
            raise ValueError("give at most one of room and room_text")
        return self

class QueryHit(Message):
    """One ranked segment."""

    segment: int
    """Segment id."""
    score: float
    """Eq. 10 score."""
    centroid: Annotated[Vec3, METRES]
    """Centroid (m, world)."""
    bbox_min: Annotated[Vec3, METRES]
    """Box corner."""
    bbox_max: Annotated[Vec3, METRES]
    """Box corner."""
    room: int | None = None
    """Room id."""
    best_track: int | None = None
    """Gallery track that gave the score."""

class RoomHit(Message):
    """One ranked room."""

    room: int
    """Room id."""
    score: float
    """Cosine between the query's embedding and the room's feature."""
    margin: float | None = None
    """For a text query: ``score`` minus the room feature's best cosine with any other room
    label (``fusion.graph.room_labels``), the ranking key: positive where the text describes
    the room better than every other label does. None for an image query, or without labels
    (then ``score`` ranks)."""
    name: str = ""
    """The room's name (``RoomNode.name``)."""
    centroid: Annotated[Vec3, METRES]
    """Centroid of its places (m, world)."""
    bbox_min: Annotated[Vec3, METRES] | None = None
    """Box corner (m, world); None if unknown."""
    bbox_max: Annotated[Vec3, METRES] | None = None
    """Box corner (m, world); None if unknown."""


@register
class QueryReply(Message):
    """Ranked segments (or rooms), or an error."""

    hits: list[QueryHit] = Field(default_factory=list)
    """Best first."""
    rooms: list[RoomHit] = Field(default_factory=list)
    """Ranked rooms, best first: the answer to a ``target: rooms`` request; for a
    ``room_text`` filter, the room it chose (and the runners-up)."""
    graph_seq: int = Field(-1, ge=-1)
    """Graph version the answer comes from."""
    error: str | None = None
    """Why the query was refused; it starts with "deadline exceeded: " when the request's
    ``deadline_s`` ran out before it could be answered."""

QueryEmbedding = Annotated[np.ndarray, ArraySpec(("float32",), (None,), finite=True)]
