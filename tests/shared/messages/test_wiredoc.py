"""The published wire contract (docs/wire.md, docs/schema/) is what the code generates, covers
every key and message, and describes what the codec really sends."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import typing

import msgpack
import numpy as np
import pytest
from pydantic import BaseModel

from shared.arrays import ArraySpec
from shared.codec import encode
from shared.config import CodecConfig
from shared.geometry import Intrinsics
from shared.messages import (
    REGISTRY,
    Frame,
    KeyframeMasks,
    KeyframeRequest,
    QueryRequest,
    TrackedFrame,
)
from shared.messages.contract import CONTRACT
from shared.messages.wiredoc import ROOT, SCHEMA_DIR, WIRE_MD, differences, generated
from shared.messages.wiredoc.models import ENCODINGS, nested_models
from shared.messages.wiredoc.schema import schemas
from shared.topics import Topics


def test_committed_docs_are_what_the_models_generate():
    diff = differences(ROOT)
    assert not diff, "run `make wire-docs` (python -m shared.messages.wiredoc): " + "; ".join(diff)


def test_generation_is_deterministic_across_processes(tmp_path):
    """Another hash seed, another process, another folder: the same bytes."""
    env = {**os.environ, "PYTHONHASHSEED": "12345", "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-m", "shared.messages.wiredoc", "--root", str(tmp_path)], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    for rel, text in generated().items():
        assert (tmp_path / rel).read_text(encoding="utf-8") == text, rel
    check = subprocess.run([sys.executable, "-m", "shared.messages.wiredoc", "--check", "--root", str(tmp_path)], env=env, capture_output=True, text=True, timeout=120)
    assert check.returncode == 0, check.stderr
    (tmp_path / WIRE_MD).write_text("edited by hand\n")
    (tmp_path / SCHEMA_DIR / "Gone.json").write_text("{}")
    check = subprocess.run([sys.executable, "-m", "shared.messages.wiredoc", "--check", "--root", str(tmp_path)], env=env, capture_output=True, text=True, timeout=120)
    assert check.returncode == 1 and "docs/wire.md: differs" in check.stderr and "Gone.json: no such message" in check.stderr


def test_every_key_and_message_is_documented():
    topics = Topics("R")
    by_name = {c.name: c for c in CONTRACT}
    for name, key in topics.all_keys().items():
        assert name in by_name, f"Topics.{name} has no wire contract"
        assert by_name[name].key.replace("<robot_id>", "R") == key
    assert by_name["status"].key.replace("<robot_id>", "R").replace("<service>", "query") == topics.status("query")
    assert by_name["alive"].key.replace("<robot_id>", "R").replace("<service>", "query") == topics.alive("query")
    wire = (ROOT / WIRE_MD).read_text()
    on_keys = {t for c in CONTRACT for t in (c.message, c.reply) if t is not None}
    assert on_keys == set(REGISTRY.values()), "a registered message travels on no key, or a key carries an unregistered one"
    for name in REGISTRY:
        assert f"### {name}\n" in wire and f"{name}.json" in schemas()
    for model in nested_models(list(REGISTRY.values())):
        assert f"### {model.__name__}\n" in wire
    for c in CONTRACT:
        assert f"`{c.key}`" in wire


def _models() -> list[type[BaseModel]]:
    return [*REGISTRY.values(), *nested_models(list(REGISTRY.values()))]


def test_no_message_carries_ground_truth():
    for model in _models():
        assert "instances" not in model.model_fields, f"{model.__name__}.instances: ground truth must not ride on the wire"


def test_every_field_has_a_docstring():
    wire = (ROOT / WIRE_MD).read_text()
    for model in _models():
        for row in wire.split(f"### {model.__name__}\n", 1)[1].split("\n### ", 1)[0].splitlines():
            if row.startswith("| `"):
                assert not row.rstrip().endswith("|  |"), f"{model.__name__}: a field without a docstring: {row}"


def _specs() -> dict[str, list[ArraySpec]]:
    out: dict[str, list[ArraySpec]] = {}
    for model in _models():
        for f in model.model_fields.values():
            meta = [*f.metadata, *(m for a in typing.get_args(f.annotation) for m in getattr(a, "__metadata__", ()))]
            for m in meta:
                if isinstance(m, ArraySpec):
                    out.setdefault(m.kind, []).append(m)
    return out


def test_documented_encodings_are_what_the_codec_sends():
    """Every array kind, under every link setting, goes out in one of the documented encodings,
    and every documented one is used by some setting."""
    msgs = {
        "rgb": lambda cfg: encode(QueryRequest(image=np.arange(48, dtype=np.uint8).reshape(4, 4, 3)), robot_id="r", seq=0, stamp=0.0, cfg=cfg),
        "depth": lambda cfg: encode(KeyframeRequest(frame_index=0, rgb=np.zeros((4, 4, 3), np.uint8), depth=np.ones((4, 4), np.uint16), depth_scale=1.0), robot_id="r", seq=0, stamp=0.0, cfg=cfg),
        "mask": lambda cfg: encode(KeyframeMasks(frame_index=0, masks=np.eye(4, dtype=bool)[None], boxes=np.zeros((1, 4), np.float32), scores=np.ones(1, np.float32)), robot_id="r", seq=0, stamp=0.0, cfg=cfg),
        "label": lambda cfg: encode(_tracked(), robot_id="r", seq=0, stamp=0.0, cfg=cfg),
        "plain": lambda cfg: encode(_tracked(), robot_id="r", seq=0, stamp=0.0, cfg=cfg),
    }
    assert set(_specs()) <= set(ENCODINGS) == set(msgs)
    for kind, make in msgs.items():
        seen: set[str] = set()
        for rgb, depth, masks, labels in itertools.product(("raw", "jpeg"), ("raw", "png", "zstd"), ("bits", "rle"), ("raw", "zlib")):
            cfg = CodecConfig(rgb=rgb, depth=depth, masks=masks, labels=labels)
            seen |= {e for k, e in _encodings(msgpack.unpackb(make(cfg))["body"]) if k == kind}
        assert seen == set(ENCODINGS[kind]), kind


def _tracked() -> TrackedFrame:
    frame = Frame(frame_index=0, rgb=np.zeros((4, 4, 3), np.uint8), depth=np.zeros((4, 4), np.uint16), depth_scale=1.0,
                  intrinsics=Intrinsics(fx=1, fy=1, cx=2, cy=2, width=4, height=4), T_world_cam=np.eye(4))  # fmt: skip
    return TrackedFrame(frame=frame, track_ids=np.zeros((4, 4), np.int32), tracks=[], confidence=np.zeros((4, 4), np.uint8))


def _encodings(body, path: str = "") -> list[tuple[str, str]]:
    """(array kind by field, encoding) of every array in a raw msgpack body."""
    kinds = {"rgb": "rgb", "image": "rgb", "depth": "depth", "masks": "mask", "track_ids": "label", "confidence": "label"}
    out = []
    if isinstance(body, dict):
        if "__nd__" in body:
            return [(kinds.get(path, "plain"), body["__nd__"])]
        for k, v in body.items():
            out += _encodings(v, k)
    elif isinstance(body, list):
        for v in body:
            out += _encodings(v, path)
    return out


def test_schemas_accept_what_the_codec_sends():
    """Each message's JSON Schema validates its real wire form (msgpack bytes as opaque data)."""
    jsonschema = pytest.importorskip("jsonschema")
    samples = {
        "TrackedFrame": _tracked(),
        "KeyframeMasks": KeyframeMasks(frame_index=3, masks=np.zeros((2, 4, 4), bool), boxes=np.zeros((2, 4), np.float32), scores=np.ones(2, np.float32)),
        "QueryRequest": QueryRequest(text="chair", top_k=3, center=np.zeros(3), radius=1.0),
    }  # fmt: skip
    for name, msg in samples.items():
        env = msgpack.unpackb(encode(msg, robot_id="robot0", seq=1, stamp=2.0, cfg=CodecConfig(masks="rle")))
        jsonschema.validate(env, json.loads(schemas()["Envelope.json"]))
        body = json.loads(schemas()[f"{name}.json"])
        jsonschema.validate(env["body"], body, format_checker=None)
        env["body"]["instances"] = {"__nd__": "raw", "dtype": "int32", "shape": [4, 4], "data": b"\0" * 64}
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(env["body"], body)


def test_docs_name_no_file_outside_the_repository():
    for path in [ROOT / WIRE_MD, *sorted((ROOT / SCHEMA_DIR).glob("*.json"))]:
        assert "../shared" not in path.read_text(), path
