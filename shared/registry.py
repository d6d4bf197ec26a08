"""One registry per kind of extension point: services, segmenters, VL encoders, dense-feature
backends, dataset readers and presets.

An entry is registered once, beside what it describes (a backend's config class, a service's
package, a reader's module), and everything that lists names (command-line choices, ``config
check`` suggestions, the launcher, ``trackgraph serve``) reads them from here. Registering
imports nothing heavy: an entry names the module that does the work, and that module is imported
only when the entry is built.

Registries fill themselves on first use by importing their ``modules`` (the built-in entries)
and then every installed entry point of the group ``trackgraph.<kind>``, so a separately
installed package can add a backend without touching this project.
"""

from __future__ import annotations

import difflib
import importlib
import logging
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Generic, Literal, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")


class UnknownName(ValueError):
    """A name no entry of the registry has; the message lists the known ones."""


class Registry(Generic[T]):
    """Name -> entry for one ``kind``, filled by ``register`` calls in ``modules``."""

    def __init__(self, kind: str, *, modules: tuple[str, ...] = (), entry_points: bool = True) -> None:
        self.kind = kind
        """What the entries are, in messages: ``"segmenter backend"``, ``"service"``."""
        self.modules = list(modules)
        """Modules whose import registers the built-in entries, in the order names are listed."""
        self._group = f"trackgraph.{kind.replace(' ', '_')}s" if entry_points else None
        self._entries: dict[str, T] = {}
        self._origin: dict[str, str] = {}  # name -> the module that registered it
        self._loaded = False
        self._lock = threading.RLock()

    def register(self, name: str, entry: T | None = None) -> Callable[[T], T] | T:
        """Add ``entry`` under ``name``; without ``entry``, a decorator that adds what it
        decorates. A name registered twice with another entry is an error: two modules would
        otherwise fight over it depending on import order."""

        origin = sys._getframe(1).f_globals.get("__name__", "")

        def add(obj: T) -> T:
            with self._lock:
                old = self._entries.get(name)
                if old is not None and old is not obj and _qualname(old) != _qualname(obj):
                    raise ValueError(f"{self.kind} {name!r} is registered twice ({_qualname(old)} and {_qualname(obj)})")
                self._entries[name] = obj
                self._origin[name] = origin
            return obj

        return add if entry is None else add(entry)

    def unregister(self, name: str) -> None:
        """Remove ``name`` (tests that register a toy entry clean up with this)."""
        with self._lock:
            self._entries.pop(name, None)
            self._origin.pop(name, None)

    def _load(self) -> None:
        if self._loaded:
            return
        with self._lock:
            if self._loaded:
                return
            self._loaded = True  # before importing: the modules call register() on this registry
            for mod in self.modules:
                importlib.import_module(mod)
            if self._group:
                from importlib.metadata import entry_points

                for ep in entry_points(group=self._group):
                    try:
                        ep.load()
                    except Exception as exc:  # noqa: BLE001 - a broken plugin must not take the built-ins down
                        log.warning("%s plugin %s (%s) failed to load: %s", self.kind, ep.name, ep.value, exc)

    def names(self) -> tuple[str, ...]:
        """Every registered name: the built-ins in ``modules`` order (whichever was imported
        first), then the others as they came."""
        self._load()
        rank = {m: i for i, m in enumerate(self.modules)}
        order = {n: i for i, n in enumerate(self._entries)}
        return tuple(sorted(self._entries, key=lambda n: (rank.get(self._origin.get(n, ""), len(rank)), order[n])))

    def get(self, name: str) -> T:
        """The entry of ``name``; :class:`UnknownName` lists the choices and the nearest one."""
        self._load()
        try:
            return self._entries[name]
        except KeyError:
            raise UnknownName(self.unknown(name)) from None

    def unknown(self, name: object) -> str:
        """The message for a name that is not registered."""
        names = self.names()
        close = difflib.get_close_matches(str(name), names, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"unknown {self.kind} {name!r}{hint}; choose one of: {', '.join(names)}"

    def __contains__(self, name: object) -> bool:
        self._load()
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def items(self) -> list[tuple[str, T]]:
        return [(n, self._entries[n]) for n in self.names()]


def _qualname(obj: object) -> str:
    return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', type(obj).__qualname__)}"


def load_object(path: str):
    """``"package.module:attr"`` -> the attribute, importing the module now."""
    module, _, attr = path.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@dataclass(frozen=True)
class ServiceEntry:
    """A service: what ``trackgraph serve NAME`` builds and what the launcher starts."""

    summary: str
    """One line for help texts."""
    node: str | None = None
    """``"module:function"`` building the node: ``function(cfg, *, out, resume)``; ``None`` for a
    service with a command of its own (``source`` runs as ``trackgraph source``)."""
    out: Literal["dir", "file"] | None = None
    """What ``--out`` names for this service, when it needs one."""
    out_help: str = ""
    """The message when ``out`` is needed and missing."""

    @property
    def servable(self) -> bool:
        return self.node is not None


SERVICES: Registry[ServiceEntry] = Registry(
    "service",
    modules=(
        "services.source",
        "services.tracker",
        "services.keyframe_vl",
        "services.fusion",
        "services.query",
        "services.viewer",
        "services.ros2",
    ),
)
"""Every TrackGraph service. Each registers itself in its package's ``__init__``."""


def servable_services() -> tuple[str, ...]:
    """Services ``trackgraph serve`` runs (every one with a node)."""
    return tuple(n for n, e in SERVICES.items() if e.servable)
