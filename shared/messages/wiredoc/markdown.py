"""docs/wire.md: the keys, the envelope, the array encodings, the robot-key rule, the errors,
the decoder's limits, and a table of every message's and nested model's fields."""

from __future__ import annotations

import inspect
import json

from pydantic import BaseModel

from shared import SCHEMA_VERSION
from shared.arrays import ALLOWED_DTYPES
from shared.config.root import ROBOT_ID
from shared.config.transport import CodecConfig
from shared.messages.contract import CONTRACT
from shared.messages.wiredoc.models import (
    anchor,
    cell,
    field_docs,
    field_rows,
    flat,
    nested_models,
    ordered_messages,
    validator_docs,
)
from shared.topics import service_names

ERROR_PREFIXES: tuple[tuple[str, str], ...] = (
    ("empty request: ", "the query carried no payload"),
    ("bad request: ", "not msgpack, not an envelope, another schema version, another message type, a body that does not "
     "validate (the text names `Type.field`), or an envelope whose `robot` is not the key's"),
    ("overloaded: ", "the queryable's queue is full; try again later"),
    ("internal error: ", "the service's handler raised (`internal error: ExceptionType: message`)"),
)  # fmt: skip
"""The text every Zenoh error reply of a TrackGraph queryable starts with (shared/transport.py)."""


def _table(headers: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _link(t: type[BaseModel] | None) -> str:
    return "-" if t is None else f"[{t.__name__}](#{anchor(t.__name__)})"


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
        rows.append([f"`{c.key}`", msg, c.delivery, qos, ", ".join(c.declared_by), cell(listeners), cell(c.summary)])
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
        "Any other map in a body (a status's `figures`, say) is data and keeps every string key: a",
        "sender puts `__nd_esc__` in front of a key that is `__nd__` or starts with `__nd_esc__`, and a",
        "receiver takes one `__nd_esc__` off every key that starts with it, so no data map reads as an array.",
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
    rows = [[f"`{p.strip()}`", cell(why)] for p, why in ERROR_PREFIXES]
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
        rows.append([f"`{name}`", json.dumps(field.default), cell(docs.get(name, ""))])
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
    out = [f"{level} {cls.__name__}", "", flat(inspect.getdoc(cls) or ""), ""]
    used = [c.key for c in CONTRACT if cls in (c.message, c.reply)]
    if used:
        out += ["On " + ", ".join(f"`{k}`" for k in used) + f". Schema: [schema/{cls.__name__}.json](schema/{cls.__name__}.json).", ""]
    out += _table(head, [[r[h] for h in head] for r in rows]) if rows else ["No fields: an empty map."]
    checks = validator_docs(cls)
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
        "- [Messages](#messages): " + ", ".join(f"[{m.__name__}](#{anchor(m.__name__)})" for m in messages),
        "- [Nested types](#nested-types): " + ", ".join(f"[{m.__name__}](#{anchor(m.__name__)})" for m in nested),
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
