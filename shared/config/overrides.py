"""``--set KEY=VALUE``: the one way to override a config, on the command line and in launch
files (``set: [KEY=VALUE, ...]``).

``KEY`` is a dotted path of the config (``fusion.tsdf.voxel_size``); ``VALUE`` is read as YAML
(``0.05``, ``true``, ``null``, ``[a, b]``, ``{x: 1}``), so it has the type the field wants. A
field that takes text gets the text as written wherever YAML would give it something else:
YAML 1.1 reads ``on``/``off``/``yes``/``no`` as booleans and ``null`` as nothing, so
``fusion.refuse=off`` is the word ``off``, and ``null`` is None only for a field that accepts
None. The field's annotation decides, found by walking the config model along the key.
Every key is checked against the config model before anything is set: a misspelt key is an
error naming it, with the nearest real key. Setting a section's ``backend`` to another backend
starts that section afresh from the new backend's defaults (the old backend's fields mean
nothing to it); later ``--set``s then fill it in.
"""

from __future__ import annotations

import copy
import difflib
import types
from collections.abc import Iterable, Mapping
from pathlib import PurePath
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import yaml
from pydantic import BaseModel

from shared.config.base import ConfigError, _model_at


def parse_set(item: str) -> tuple[list[str], str]:
    """``"a.b.c=VALUE"`` -> (["a", "b", "c"], the text of VALUE); :func:`read_value` reads it."""
    key, sep, text = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. fusion.tsdf.voxel_size=0.05")
    parts = key.split(".")
    if any(not p for p in parts):
        raise ConfigError(f"--set {item!r}: {key!r} is not a dotted key")
    return parts, text


def read_value(key: str, text: str, annotation: Any = Any) -> Any:
    """``text`` read as YAML, unless the field (of type ``annotation``) takes text and would not
    take what YAML reads: then the text as written (``off`` for a ``Literal["on", "off"]``)."""
    if not text.strip():
        return ""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        if _takes_text(annotation):
            return text.strip()
        raise ConfigError(f"--set {key}: {text!r} is not a YAML value ({exc.problem or exc})") from None
    if _takes_text(annotation) and not _accepts(annotation, value):
        return text.strip()
    return value


def _members(annotation: Any) -> list[Any]:
    """The types a field accepts: the members of a union, ``Annotated`` unwrapped."""
    origin = get_origin(annotation)
    if origin is Annotated:
        return _members(get_args(annotation)[0])
    if origin in (Union, types.UnionType):
        return [m for a in get_args(annotation) for m in _members(a)]
    return [annotation]


def _takes_text(annotation: Any) -> bool:
    for t in _members(annotation):
        if t is str or (isinstance(t, type) and issubclass(t, PurePath)):
            return True
        if get_origin(t) is Literal and any(isinstance(v, str) for v in get_args(t)):
            return True
    return False


def _accepts(annotation: Any, value: Any) -> bool:
    """Whether ``value`` as YAML read it is of a type the field accepts; unknown types: yes."""
    for t in _members(annotation):
        origin = get_origin(t)
        if origin is Literal:
            # ``True == 1``: a Literal takes a value of its own type only.
            ok = any(value == v and type(value) is type(v) for v in get_args(t))
        elif t is type(None):
            ok = value is None
        elif t is bool:
            ok = isinstance(value, bool)
        elif t is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif t is float:
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        elif t is str or (isinstance(t, type) and issubclass(t, PurePath)):
            ok = isinstance(value, str)
        elif t in (list, tuple, set, frozenset) or origin in (list, tuple, set, frozenset):
            ok = isinstance(value, list)
        elif t is dict or origin is dict or (isinstance(t, type) and issubclass(t, BaseModel)):
            ok = isinstance(value, dict)
        else:
            ok = True
        if ok:
            return True
    return False


def apply_sets(data: Mapping[str, Any], items: Iterable[str], model: type[BaseModel]) -> dict[str, Any]:
    """``data`` (a config as loaded from YAML) with every ``KEY=VALUE`` of ``items`` set, in
    order; ``data`` is left as it was. Unknown keys raise :class:`ConfigError`."""
    out = copy.deepcopy(dict(data))
    for item in items:
        parts, text = parse_set(item)
        node = out
        for depth, part in enumerate(parts):
            at = _model_at(model, tuple(parts[:depth]), out)
            if at is not None and part not in at.model_fields:
                close = difflib.get_close_matches(part, list(at.model_fields), n=1)
                where = ".".join(parts[: depth + 1])
                backend = f" for backend {at.model_fields['backend'].default!r}" if "backend" in at.model_fields else ""
                hint = f" (did you mean {'.'.join([*parts[:depth], close[0]])!r}?)" if close else ""
                raise ConfigError(f"--set {where}: unknown key{backend}{hint}")
            if depth == len(parts) - 1:
                # Inside a free-form mapping (no model here) YAML alone decides.
                value = read_value(".".join(parts), text, at.model_fields[part].annotation if at is not None else Any)
                if part == "backend" and node.get("backend", _default_backend(at)) != value:
                    node.clear()  # another backend: its own defaults, not the old one's fields
                node[part] = value
            else:
                child = node.get(part)
                if not isinstance(child, dict):
                    if child is not None and at is not None and _nested(at, part) is None:
                        raise ConfigError(f"--set {'.'.join(parts)}: {'.'.join(parts[: depth + 1])} is a value, not a section")
                    child = node[part] = {}
                node = child
    return out


def _default_backend(model: type[BaseModel] | None) -> Any:
    return getattr(model, "__default_backend__", None) if model is not None else None


def _nested(model: type[BaseModel], name: str) -> type[BaseModel] | None:
    ann = model.model_fields[name].annotation
    return ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None


def as_sets(tree: Mapping[str, Any], prefix: str = "") -> list[str]:
    """A nested mapping as ``KEY=VALUE`` items (what a launch file's ``set`` holds), leaves
    written as YAML flow values. A ``backend`` key goes first in its section, so that setting it
    does not wipe the section's other keys set before it."""
    items: list[str] = []
    keys = sorted(tree, key=lambda k: k != "backend")
    for key in keys:
        value = tree[key]
        path = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            items.extend(as_sets(value, path + "."))
        else:
            text = yaml.safe_dump(value, default_flow_style=True, width=1 << 20).strip()
            if text.endswith("..."):  # a plain scalar's document-end marker
                text = text[:-3].strip()
            items.append(f"{path}={text}")
    return items
