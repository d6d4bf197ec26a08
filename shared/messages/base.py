"""Message base class, the envelope, and the registry of message types."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

from pydantic import BaseModel, ConfigDict

from shared import SCHEMA_VERSION


class Message(BaseModel):
    """Base of every wire message: strict keys, numpy arrays allowed."""

    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True, frozen=False)


@dataclass(frozen=True)
class Units:
    """The physical units of a field, as metadata: ``Annotated[float, Units("m")]``.
    ``docs/wire.md`` and the JSON Schemas (``x-units``) show them; validation ignores them."""

    units: str


METRES = Units("m")
SECONDS = Units("s")
PIXELS = Units("px")


M = TypeVar("M", bound=BaseModel)


@dataclass(frozen=True)
class Envelope(Generic[M]):
    """A message as it travels: the body plus who sent it, its sequence number and stamp."""

    body: M
    robot_id: str
    seq: int
    stamp: float
    schema_version: int = SCHEMA_VERSION
    received: float | None = None
    """``time.monotonic()`` when a queryable of this process took the request in, before it
    waited for a worker (never on the wire; None where nothing recorded it). A request's
    deadline is counted from here, so the sender's clock does not matter."""


REGISTRY: dict[str, type[BaseModel]] = {}


def register(cls: type[M]) -> type[M]:
    """Class decorator: make a message type known to the codec by its class name."""
    name = cls.__name__
    if name in REGISTRY and REGISTRY[name] is not cls:
        raise TypeError(f"message type {name} registered twice")
    REGISTRY[name] = cls
    return cls


def type_name(cls: type[BaseModel]) -> str:
    return cls.__name__
