"""Reading the message models for the wire docs: each field's type, dtype, shape, units,
limits, default and docstring, and which models the messages nest."""

from __future__ import annotations

import ast
import inspect
import json
import textwrap
import types
import typing
from collections.abc import Iterable
from typing import Any, Literal, get_args, get_origin

import annotated_types as at
import numpy as np
from pydantic import BaseModel

from shared.arrays import ArraySpec
from shared.messages import REGISTRY
from shared.messages.base import Units
from shared.messages.contract import CONTRACT

ENCODINGS: dict[str, tuple[str, ...]] = {
    "rgb": ("raw", "jpeg"),
    "depth": ("raw", "zstd2d", "png"),
    "mask": ("bits", "rle"),
    "label": ("raw", "zlib"),
    "plain": ("raw",),
}
"""What a sender may use for an array of each :class:`~shared.arrays.ArraySpec` kind (the link's
``transport.codec`` picks); a receiver decodes any encoding valid for the dtype and shape."""

UNITS_ELSEWHERE: dict[str, dict[str, str]] = {
    "Intrinsics": {"fx": "px", "fy": "px", "cx": "px", "cy": "px", "width": "px", "height": "px"},
    "ServiceStatus": {"uptime_s": "s", "rate_hz": "Hz", "latency_p50_ms": "ms", "latency_p99_ms": "ms"},
    "InputCounters": {"rate_hz": "Hz"},
}
"""Units of models defined outside the messages this module's package owns (shared/geometry.py
and shared/messages/status.py declare theirs in their docstrings)."""


def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each annotated attribute of ``cls`` (and of its bases)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass in (object, BaseModel) or not isinstance(klass, type):
            continue
        try:
            source = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = ast.parse(source).body[0]
        if not isinstance(body, ast.ClassDef):
            continue
        items = body.body
        for node, nxt in zip(items, [*items[1:], None], strict=True):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(nxt, ast.Expr):
                if isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str):
                    docs[node.target.id] = inspect.cleandoc(nxt.value.value)
    return docs


def flat(text: str) -> str:
    return " ".join(text.split())


def cell(text: str) -> str:
    return flat(text).replace("|", "\\|")


def anchor(name: str) -> str:
    return name.lower()


def meta_of(annotation: Any, metadata: Iterable[Any]) -> list[Any]:
    """The field's metadata plus that of Annotated types inside its union."""
    out = list(metadata)
    for a in get_args(annotation):
        if get_origin(a) is typing.Annotated:
            out.extend(a.__metadata__)
    if get_origin(annotation) is typing.Annotated:
        out.extend(annotation.__metadata__)
    return out


def _type_name(t: Any, models: dict[str, type[BaseModel]]) -> str:
    origin = get_origin(t)
    if origin is typing.Annotated:
        return _type_name(get_args(t)[0], models)
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_name(a, models) for a in get_args(t))
    if origin is Literal:
        return " \\| ".join(json.dumps(v) for v in get_args(t))
    if origin is list:
        return f"list[{_type_name(get_args(t)[0], models)}]"
    if origin is dict:
        k, v = get_args(t)
        return f"map[{_type_name(k, models)}, {_type_name(v, models)}]"
    if t is type(None):
        return "nil"
    if t is np.ndarray:
        return "array"
    if t is dict:
        return "map"
    if t is list:
        return "list"
    if isinstance(t, type) and issubclass(t, BaseModel):
        models.setdefault(t.__name__, t)
        return f"[{t.__name__}](#{anchor(t.__name__)})"
    if isinstance(t, type):
        return t.__name__
    return str(t)


_BOUNDS = (
    (at.Gt, ">", "gt"),
    (at.Ge, ">=", "ge"),
    (at.Lt, "<", "lt"),
    (at.Le, "<=", "le"),
    (at.MinLen, "length >=", "min_length"),
    (at.MaxLen, "length <=", "max_length"),
)
"""The pydantic constraints the docs name: the annotated-types class, its words, its attribute."""


def _limits(meta: list[Any], spec: ArraySpec | None) -> str:
    parts = []
    for m in meta:
        for kind, text, attr in _BOUNDS:
            if isinstance(m, kind):
                parts.append(f"{text} {getattr(m, attr)}")
                break
    if spec is not None:
        if spec.finite:
            parts.append("finite")
        parts.append("sent as " + " or ".join(f"`{e}`" for e in ENCODINGS[spec.kind]))
    return "; ".join(parts)


def _shape(spec: ArraySpec | None) -> str:
    if spec is None or spec.shape is None:
        return ""
    return "(" + ", ".join("*" if s is None else str(s) for s in spec.shape) + ("," if len(spec.shape) == 1 else "") + ")"


def _default(field) -> str:
    if field.is_required():
        return "required"
    if field.default_factory is not None:
        value = field.default_factory()
    else:
        value = field.default
    if value is None:
        return "nil"
    if isinstance(value, np.ndarray):
        # An empty array default: its shape says what it is.
        return "empty " + "x".join(str(n) for n in value.shape) + f" {value.dtype.name}"
    return json.dumps(value)


def field_units(cls: type[BaseModel], name: str, meta: list[Any]) -> str:
    for m in meta:
        if isinstance(m, Units):
            return m.units
    return UNITS_ELSEWHERE.get(cls.__name__, {}).get(name, "")


def validator_docs(cls: type[BaseModel]) -> list[str]:
    """Docstrings of the model's cross-field validators."""
    out = []
    decorators = cls.__pydantic_decorators__
    for group in (decorators.field_validators, decorators.model_validators):
        for name in sorted(group):
            doc = inspect.getdoc(group[name].func)
            if doc:
                out.append(flat(doc))
    return out


def field_rows(cls: type[BaseModel], models: dict[str, type[BaseModel]]) -> list[dict[str, str]]:
    """One row per field: name, type, dtype, shape, units, limits, default, description."""
    docs = field_docs(cls)
    rows = []
    for name, field in cls.model_fields.items():
        meta = meta_of(field.annotation, field.metadata)
        spec = next((m for m in meta if isinstance(m, ArraySpec)), None)
        rows.append({
            "field": f"`{name}`",
            "type": _type_name(field.annotation, models),
            "dtype": "/".join(spec.dtypes) if spec is not None else "",
            "shape": _shape(spec),
            "units": field_units(cls, name, meta),
            "limits": _limits(meta, spec),
            "default": _default(field),
            "description": cell(docs.get(name, "")),
        })  # fmt: skip
    return rows


def ordered_messages() -> list[type[BaseModel]]:
    """Registered messages in the order the keys table first names them, then the rest by name."""
    order: list[type[BaseModel]] = []
    for c in CONTRACT:
        for t in (c.message, c.reply):
            if t is not None and t not in order:
                order.append(t)
    order += [REGISTRY[n] for n in sorted(REGISTRY) if REGISTRY[n] not in order]
    return order


def nested_models(messages: list[type[BaseModel]]) -> list[type[BaseModel]]:
    """Models used inside messages that are not messages themselves, in first-use order."""
    found: dict[str, type[BaseModel]] = {}
    queue = list(messages)
    seen: set[type] = set()
    while queue:
        cls = queue.pop(0)
        if cls in seen:
            continue
        seen.add(cls)
        before = set(found)
        field_rows(cls, found)
        queue += [found[n] for n in found if n not in before]
    return [m for m in found.values() if m not in messages]
