"""Generate the published wire contract: ``docs/wire.md`` and ``docs/schema/<Type>.json``.

    python -m shared.messages.wiredoc           # write both (``make wire-docs``)
    python -m shared.messages.wiredoc --check   # exit 1 if the committed files differ

Everything comes from code: the keys and their QoS from :mod:`shared.messages.contract`, the
fields from the message models (type annotations, :class:`~shared.arrays.ArraySpec`,
:class:`~shared.messages.base.Units`, pydantic constraints and the docstring under each
field), the envelope and array encodings from :mod:`shared.codec`, the decoder's limits from
:class:`~shared.config.transport.CodecConfig`. The output is deterministic: the same code
gives the same bytes.
"""

from __future__ import annotations

import argparse
import ast
import inspect
import json
import sys
import textwrap
import types
import typing
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import annotated_types as at
import numpy as np
from pydantic import BaseModel
from pydantic.json_schema import GenerateJsonSchema

from shared import SCHEMA_VERSION
from shared.arrays import ALLOWED_DTYPES, ArraySpec
from shared.config.root import ROBOT_ID
from shared.config.transport import CodecConfig
from shared.messages import REGISTRY
from shared.messages.base import Units
from shared.messages.contract import CONTRACT
from shared.topics import service_names

ROOT = Path(__file__).resolve().parents[2]
WIRE_MD = Path("docs") / "wire.md"
SCHEMA_DIR = Path("docs") / "schema"

ENCODINGS: dict[str, tuple[str, ...]] = {
    "rgb": ("raw", "jpeg"),
    "depth": ("raw", "zstd2d", "png"),
    "mask": ("bits", "rle"),
    "label": ("raw", "zlib"),
    "plain": ("raw",),
}
"""What a sender may use for an array of each :class:`~shared.arrays.ArraySpec` kind (the link's
``transport.codec`` picks); a receiver decodes any encoding valid for the dtype and shape."""

ERROR_PREFIXES: tuple[tuple[str, str], ...] = (
    ("empty request: ", "the query carried no payload"),
    ("bad request: ", "not msgpack, not an envelope, another schema version, another message type, a body that does not "
     "validate (the text names `Type.field`), or an envelope whose `robot` is not the key's"),
    ("overloaded: ", "the queryable's queue is full; try again later"),
    ("internal error: ", "the service's handler raised (`internal error: ExceptionType: message`)"),
)  # fmt: skip
"""The text every Zenoh error reply of a TrackGraph queryable starts with (shared/transport.py)."""

UNITS_ELSEWHERE: dict[str, dict[str, str]] = {
    "Intrinsics": {"fx": "px", "fy": "px", "cx": "px", "cy": "px", "width": "px", "height": "px"},
    "ServiceStatus": {"uptime_s": "s", "rate_hz": "Hz", "latency_p50_ms": "ms", "latency_p99_ms": "ms"},
    "InputCounters": {"rate_hz": "Hz"},
}
"""Units of models defined outside the messages this module's package owns (shared/geometry.py
and shared/messages/status.py declare theirs in their docstrings)."""


# ---------------------------------------------------------------- reading the models


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


def _flat(text: str) -> str:
    return " ".join(text.split())


def _cell(text: str) -> str:
    return _flat(text).replace("|", "\\|")


def _anchor(name: str) -> str:
    return name.lower()


def _meta_of(annotation: Any, metadata: Iterable[Any]) -> list[Any]:
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
        return f"[{t.__name__}](#{_anchor(t.__name__)})"
    if isinstance(t, type):
        return t.__name__
    return str(t)


def _limits(meta: list[Any], spec: ArraySpec | None) -> str:
    parts = []
    for m in meta:
        if isinstance(m, at.Gt):
            parts.append(f"> {m.gt}")
        elif isinstance(m, at.Ge):
            parts.append(f">= {m.ge}")
        elif isinstance(m, at.Lt):
            parts.append(f"< {m.lt}")
        elif isinstance(m, at.Le):
            parts.append(f"<= {m.le}")
        elif isinstance(m, at.MinLen):
            parts.append(f"length >= {m.min_length}")
        elif isinstance(m, at.MaxLen):
            parts.append(f"length <= {m.max_length}")
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


def _units(cls: type[BaseModel], name: str, meta: list[Any]) -> str:
    for m in meta:
        if isinstance(m, Units):
            return m.units
    return UNITS_ELSEWHERE.get(cls.__name__, {}).get(name, "")


def _checks(cls: type[BaseModel]) -> list[str]:
    """Docstrings of the model's cross-field validators."""
    out = []
    decorators = cls.__pydantic_decorators__
    for group in (decorators.field_validators, decorators.model_validators):
        for name in sorted(group):
            doc = inspect.getdoc(group[name].func)
            if doc:
                out.append(_flat(doc))
    return out


def field_rows(cls: type[BaseModel], models: dict[str, type[BaseModel]]) -> list[dict[str, str]]:
    """One row per field: name, type, dtype, shape, units, limits, default, description."""
    docs = field_docs(cls)
    rows = []
    for name, field in cls.model_fields.items():
        meta = _meta_of(field.annotation, field.metadata)
        spec = next((m for m in meta if isinstance(m, ArraySpec)), None)
        rows.append({
            "field": f"`{name}`",
            "type": _type_name(field.annotation, models),
            "dtype": "/".join(spec.dtypes) if spec is not None else "",
            "shape": _shape(spec),
            "units": _units(cls, name, meta),
            "limits": _limits(meta, spec),
            "default": _default(field),
            "description": _cell(docs.get(name, "")),
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


# ---------------------------------------------------------------- JSON Schema


class WireSchema(GenerateJsonSchema):
    """Pydantic's JSON Schema generator, with numpy arrays as the codec's ``__nd__`` maps."""

    def function_plain_schema(self, schema) -> dict[str, Any]:
        spec = getattr(schema["function"]["function"], "__self__", None)
        if isinstance(spec, ArraySpec):
            return array_schema(spec)
        return super().function_plain_schema(schema)


def accepted_encodings(spec: ArraySpec) -> list[str]:
    """Every encoding a TrackGraph decoder takes for an array of ``spec`` (a sender uses one of
    :data:`ENCODINGS` for its kind)."""
    out = ["raw", "zlib"]
    if "bool" in spec.dtypes:
        out += ["bits", "rle"]
    if "uint8" in spec.dtypes and spec.shape is not None and len(spec.shape) == 3 and spec.shape[2] in (3, None):
        out.append("jpeg")
    if "uint16" in spec.dtypes and spec.shape is not None and len(spec.shape) == 2:
        out += ["png", "zstd2d"]
    return out


def array_schema(spec: ArraySpec) -> dict[str, Any]:
    """The msgpack map one array of ``spec`` travels as."""
    if spec.shape is None:
        shape: dict[str, Any] = {"type": "array", "items": {"type": "integer", "minimum": 0}}
    else:
        items = [{"type": "integer", "minimum": 0} if s is None else {"const": s} for s in spec.shape]
        shape = {"type": "array", "prefixItems": items, "minItems": len(items), "maxItems": len(items)}
    out: dict[str, Any] = {
        "type": "object",
        "description": "A numpy array as the codec's map (see docs/wire.md, Arrays).",
        "properties": {
            "__nd__": {"enum": accepted_encodings(spec)},
            "dtype": {"enum": list(spec.dtypes)},
            "shape": shape,
            "data": {"description": "msgpack bin: the encoded bytes", "x-msgpack": "bin"},
        },
        "required": ["__nd__", "dtype", "shape", "data"],
        "additionalProperties": False,
        "x-array-kind": spec.kind,
    }
    if spec.finite:
        out["x-finite"] = True
    return out


def message_schema(cls: type[BaseModel]) -> dict[str, Any]:
    """The JSON Schema of one message body, with each field's docstring and units."""
    schema = cls.model_json_schema(schema_generator=WireSchema)
    models: dict[str, type[BaseModel]] = {cls.__name__: cls}
    field_rows(cls, models)
    for m in nested_models([cls]):
        models[m.__name__] = m

    def annotate(node: dict[str, Any], model: type[BaseModel]) -> None:
        docs = field_docs(model)
        for name, prop in node.get("properties", {}).items():
            field = model.model_fields.get(name)
            if field is None:
                continue
            if docs.get(name):
                prop["description"] = _flat(docs[name])
            units = _units(model, name, _meta_of(field.annotation, field.metadata))
            if units:
                prop["x-units"] = units

    annotate(schema, cls)
    for name, sub in schema.get("$defs", {}).items():
        if name in models:
            annotate(sub, models[name])
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = f"{cls.__name__}.json"
    schema["x-schema-version"] = SCHEMA_VERSION
    return schema


def envelope_schema() -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "Envelope.json",
        "title": "Envelope",
        "description": "Every payload on every key: a msgpack map around one message body (docs/wire.md, Envelope).",
        "type": "object",
        "properties": {
            "v": {"const": SCHEMA_VERSION, "description": "Schema version."},
            "type": {"enum": sorted(REGISTRY), "description": "The body's message type."},
            "robot": {"type": "string", "pattern": ROBOT_ID.pattern, "description": "The sender's robot id; must be the key's."},
            "seq": {"type": "integer", "minimum": 0, "description": "Per-publisher counter, from 0."},
            "stamp": {"type": "number", "description": "Sender's wall clock when sent (s since the Unix epoch).", "x-units": "s"},
            "body": {"type": "object", "description": "The message: docs/schema/<type>.json."},
        },
        "required": ["v", "type", "robot", "seq", "stamp", "body"],
        "additionalProperties": True,
        "x-schema-version": SCHEMA_VERSION,
    }


def schemas() -> dict[str, str]:
    """File name -> contents of every JSON Schema."""
    out = {"Envelope.json": envelope_schema()}
    for cls in sorted(REGISTRY.values(), key=lambda c: c.__name__):
        out[f"{cls.__name__}.json"] = message_schema(cls)
    return {name: json.dumps(s, indent=2, sort_keys=True) + "\n" for name, s in sorted(out.items())}


# ---------------------------------------------------------------- docs/wire.md


def _table(headers: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _link(t: type[BaseModel] | None) -> str:
    return "-" if t is None else f"[{t.__name__}](#{_anchor(t.__name__)})"


def _keys_section() -> list[str]:
    rows = []
    for c in CONTRACT:
        qos = {
            "pub/sub": f"reliable, congestion control {c.congestion}",
            "query/reply": "request/reply; one reply per request",
            "liveliness": "liveliness token",
        }[c.delivery]
        listeners = "; ".join(f"{ls.service} ({ls.policy}{': ' + ls.note if ls.note else ''})" for ls in c.listeners)
        msg = _link(c.message) + (f" → {_link(c.reply)}" if c.reply is not None else "")
        rows.append([f"`{c.key}`", msg, c.delivery, qos, ", ".join(c.declared_by), _cell(listeners), _cell(c.summary)])
    return [
        "## Keys",
        "",
        f"Every key lies under `trackgraph/<robot_id>/`; a robot id is 1 to 64 letters, digits, `_` or `-` "
        f"(`{ROBOT_ID.pattern}`). `<service>` is one of {', '.join(f'`{s}`' for s in service_names())}.",
        "",
        *_table(["key", "message", "delivery", "QoS", "declared by", "listeners (subscriber policy)", "what"], rows),
        "",
        "- **pub/sub**: the services under *declared by* declare publishers (Zenoh reliable; congestion",
        "  control `BLOCK`: a publisher waits rather than lose a large fragmented message); listeners declare",
        "  subscribers. No listener ever blocks in its Zenoh callback: it hands the payload to a bounded",
        "  queue, `fifo` (in order; when full the *new* message is dropped and counted) or `latest` (keeps",
        "  the newest; older ones are dropped and counted). Drops show as `dropped` in the listener's",
        "  [ServiceStatus](#servicestatus).",
        "- **query/reply**: the service named declares a Zenoh queryable; a caller sends a `get` whose",
        "  payload is the request envelope and takes the first reply. Its answer is an envelope of the reply",
        "  type, or an error reply (see [Errors](#errors)).",
        "- **liveliness**: a Zenoh liveliness token, no payload; it vanishes when the process dies or loses",
        "  its router.",
        "",
    ]


def _envelope_section() -> list[str]:
    return [
        "## Envelope",
        "",
        "Every payload, on every key, in both directions, is one [msgpack](https://msgpack.org) map",
        "(string keys, `bin` for bytes, no extension types):",
        "",
        "```",
        f'{{"v": {SCHEMA_VERSION}, "type": "Frame", "robot": "robot0", "seq": 12, "stamp": 1.7e9, "body": {{...}}}}',
        "```",
        "",
        *_table(["key", "type", "meaning"], [
            ["`v`", "int", f"schema version; this contract is version {SCHEMA_VERSION}, any other is refused"],
            ["`type`", "str", "the body's message type name (a section under [Messages](#messages))"],
            ["`robot`", "str", "the sender's robot id; see [The robot-key rule](#the-robot-key-rule)"],
            ["`seq`", "int >= 0", "per-publisher (or per-client) counter starting at 0"],
            ["`stamp`", "float", "sender's wall clock when sent, seconds since the Unix epoch"],
            ["`body`", "map", "the message: one entry per field below; an optional field may be left out (it takes its default), an unknown field is refused"],
        ]),  # fmt: skip
        "",
        "`nil` is msgpack nil (Python None). Floats may be sent as float32 or float64, integers in any",
        "width. JSON Schemas of the envelope and of every body are in [docs/schema/](schema/)",
        "(`Envelope.json`, `<type>.json`; draft 2020-12, arrays as below, `x-units` for units).",
        "",
    ]


def _arrays_section() -> list[str]:
    rows = [
        ["`raw`", "any", "`data` is the array's bytes in C order, little-endian: exactly prod(shape) × itemsize bytes"],
        ["`zlib`", "any (label maps)", "`data` is a zlib stream (RFC 1950) of the `raw` bytes"],
        ["`jpeg`", "uint8 (H, W, 3)", "`data` is a baseline JPEG; decode to RGB. Lossy: a link sends it only with `transport.codec.rgb: jpeg`"],
        ["`png`", "uint16 (H, W)", "`data` is a 16-bit greyscale PNG (lossless)"],
        ["`zstd2d`", "uint16 (H, W)", "lossless depth. Let x be the depth and r = x - left - up + up-left (mod 2^16; x outside the image counts as 0), so that x is the prefix sum of r over rows and then columns. Each r is zigzag-mapped as int16 to z = (r << 1) ^ (r >> 15). `data` is one zstd frame of all the low bytes of z, row-major, then all the high bytes"],
        ["`bits`", "bool", "`data` is the C-order flattened array packed 8 to a byte, first element in the most significant bit (numpy `packbits`), the last byte zero-padded: ceil(n / 8) bytes"],
        ["`rle`", "bool", "`data` is little-endian uint32 run lengths of the C-order flattened array, alternating False, True, False, ... and starting with False (a first run of 0 when it starts True); they sum to prod(shape)"],
    ]  # fmt: skip
    return [
        "## Arrays",
        "",
        "A numpy array inside a body is a map with the reserved key `__nd__`:",
        "",
        "```",
        '{"__nd__": "raw", "dtype": "float32", "shape": [3], "data": <bin>}',
        "```",
        "",
        f"`dtype` is one of {', '.join(f'`{d}`' for d in sorted(ALLOWED_DTYPES))}; `shape` a list of",
        "non-negative sizes. Each field below gives the dtypes and shape it accepts (`*`: any size) and the",
        "encodings a sender may use for it; a receiver must decode every encoding that fits the dtype:",
        "",
        *_table(["`__nd__`", "dtype, shape", "how to decode `data`"], rows),
        "",
    ]


def _robot_section() -> list[str]:
    return [
        "## The robot-key rule",
        "",
        "A message arriving on `trackgraph/<robot_id>/...` whose envelope `robot` is not that `<robot_id>`",
        "is refused: a subscriber drops it and counts it as `rejected`; a queryable answers",
        "`bad request: ... claims robot ...` (an error reply). One robot's data never reaches another's",
        "map because a client mislabelled it. Replies carry the answering service's robot id.",
        "",
    ]


def _errors_section() -> list[str]:
    rows = [[f"`{p.strip()}`", _cell(why)] for p, why in ERROR_PREFIXES]
    return [
        "## Errors",
        "",
        "**One rule.** A request the service could not take in, or failed on, comes back as a **Zenoh error",
        "reply** whose payload is UTF-8 text starting with one of these prefixes; a request the service",
        "understood but declines comes back as a **normal reply** of the reply type with its `error` field",
        "set (a sentence that names the message field concerned) and its results empty.",
        "",
        *_table(["error reply starts with", "when"], rows),
        "",
        "Normal replies with `error` set: [QueryReply](#queryreply) (no graph yet or resynchronising: try",
        "again shortly; an unknown room; `top_k`, text or image over the service's limits; a query that",
        "cannot be embedded, with the embedding service's reason), [EmbedReply](#embedreply) (the encoder",
        "cannot embed the text or image: `EmbedRequest.image: ...`), [GraphSnapshot](#graphsnapshot) (a",
        "[SnapshotRequest](#snapshotrequest) with `whole_map` whose mesh would be over the codec's array",
        "limits: the graph comes back without the mesh, `error` starting `SnapshotRequest.whole_map: `).",
        "",
        "Pub/sub has nobody to answer: an undecodable, invalid or wrong-robot message is dropped and",
        "counted as `rejected` in the receiver's [ServiceStatus](#servicestatus). A keyframe that could not",
        "be segmented or embedded is still answered on `keyframe/masks` and `keyframe/features`, with",
        "N = 0 and `error` set.",
        "",
    ]


def _limits_section() -> list[str]:
    docs = field_docs(CodecConfig)
    rows = []
    for name, field in CodecConfig.model_fields.items():
        rows.append([f"`{name}`", json.dumps(field.default), _cell(docs.get(name, ""))])
    return [
        "## Limits",
        "",
        "What a TrackGraph decoder accepts, and how its links encode (`transport.codec`, defaults shown).",
        "A payload or array over a limit is refused before anything is allocated.",
        "",
        *_table(["setting", "default", "meaning"], rows),
        "",
    ]


def _model_section(cls: type[BaseModel], models: dict[str, type[BaseModel]], level: str) -> list[str]:
    rows = field_rows(cls, models)
    head = ["field", "type", "dtype", "shape", "units", "limits", "default", "description"]
    out = [f"{level} {cls.__name__}", "", _flat(inspect.getdoc(cls) or ""), ""]
    used = [c.key for c in CONTRACT if cls in (c.message, c.reply)]
    if used:
        out += ["On " + ", ".join(f"`{k}`" for k in used) + f". Schema: [schema/{cls.__name__}.json](schema/{cls.__name__}.json).", ""]
    out += _table(head, [[r[h] for h in head] for r in rows]) if rows else ["No fields: an empty map."]
    checks = _checks(cls)
    if checks:
        out += ["", "Also checked:", ""] + [f"- {c}" for c in checks]
    return out + [""]


def wire_md() -> str:
    messages = ordered_messages()
    models: dict[str, type[BaseModel]] = {}
    nested = nested_models(messages)
    lines = [
        "# The TrackGraph wire contract",
        "",
        "<!-- Generated by `python -m shared.messages.wiredoc` (`make wire-docs`) from shared/messages,",
        "shared/codec.py and shared/config/transport.py. Do not edit: tests/shared/messages/test_wiredoc.py",
        "fails when this file or docs/schema/ differ from what the code generates. -->",
        "",
        "Everything a program needs to talk to a TrackGraph system over Zenoh, with nothing but a Zenoh",
        "client, a msgpack library and numpy: the keys, what travels on each and how, the envelope, the",
        "array encodings, the errors, and every field of every message. `examples/raw_client.py` (a query,",
        "a snapshot and the deltas) and `examples/external_keyframe_vl.py` (a stand-in keyframe_vl service)",
        "use only this page.",
        "",
        f"Schema version **{SCHEMA_VERSION}**.",
        "",
        "- [Keys](#keys)",
        "- [Envelope](#envelope)",
        "- [Arrays](#arrays)",
        "- [The robot-key rule](#the-robot-key-rule)",
        "- [Errors](#errors)",
        "- [Limits](#limits)",
        "- [Messages](#messages): " + ", ".join(f"[{m.__name__}](#{_anchor(m.__name__)})" for m in messages),
        "- [Nested types](#nested-types): " + ", ".join(f"[{m.__name__}](#{_anchor(m.__name__)})" for m in nested),
        "",
        *_keys_section(),
        *_envelope_section(),
        *_arrays_section(),
        *_robot_section(),
        *_errors_section(),
        *_limits_section(),
        "## Messages",
        "",
        "Each is the `body` of an envelope whose `type` is its name.",
        "",
    ]
    for cls in messages:
        lines += _model_section(cls, models, "###")
    lines += ["## Nested types", "", "Maps inside message bodies (no envelope of their own).", ""]
    for cls in nested:
        lines += _model_section(cls, models, "###")
    return "\n".join(lines).rstrip("\n") + "\n"


# ---------------------------------------------------------------- files


def generated() -> dict[Path, str]:
    """Repository path -> contents of every generated file."""
    out = {WIRE_MD: wire_md()}
    out.update({SCHEMA_DIR / name: text for name, text in schemas().items()})
    return out


def differences(root: Path = ROOT) -> list[str]:
    """What differs between the files under ``root`` and what the code generates."""
    want = generated()
    out = []
    for rel, text in want.items():
        path = root / rel
        if not path.is_file():
            out.append(f"{rel}: missing")
        elif path.read_text(encoding="utf-8") != text:
            out.append(f"{rel}: differs")
    schema_dir = root / SCHEMA_DIR
    if schema_dir.is_dir():
        for path in sorted(schema_dir.glob("*.json")):
            if SCHEMA_DIR / path.name not in want:
                out.append(f"{SCHEMA_DIR / path.name}: no such message (stale)")
    return out


def write(root: Path = ROOT) -> list[Path]:
    """Write every generated file under ``root`` and remove stale schemas; returns the paths written."""
    want = generated()
    (root / SCHEMA_DIR).mkdir(parents=True, exist_ok=True)
    for path in sorted((root / SCHEMA_DIR).glob("*.json")):
        if SCHEMA_DIR / path.name not in want:
            path.unlink()
    written = []
    for rel, text in want.items():
        path = root / rel
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
            written.append(rel)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m shared.messages.wiredoc", description="generate docs/wire.md and docs/schema/*.json")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if the committed files differ")
    ap.add_argument("--root", type=Path, default=ROOT, help="repository root (default: this checkout)")
    args = ap.parse_args(argv)
    if args.check:
        diff = differences(args.root)
        for d in diff:
            print(d, file=sys.stderr)
        if diff:
            print("the wire docs are out of date: run `make wire-docs`", file=sys.stderr)
        return 1 if diff else 0
    for rel in write(args.root):
        print(f"wrote {rel}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
