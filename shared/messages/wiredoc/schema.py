"""The JSON Schemas of docs/schema/: the envelope, and every message body with its fields'
docstrings and units, numpy arrays as the codec's ``__nd__`` maps."""

from __future__ import annotations

import json
from typing import Any

from pydantic import BaseModel
from pydantic.json_schema import GenerateJsonSchema

from shared import SCHEMA_VERSION
from shared.arrays import ArraySpec
from shared.config.root import ROBOT_ID
from shared.messages import REGISTRY
from shared.messages.wiredoc.models import (
    field_docs,
    field_rows,
    field_units,
    flat,
    meta_of,
    nested_models,
)


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
                prop["description"] = flat(docs[name])
            units = field_units(model, name, meta_of(field.annotation, field.metadata))
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
