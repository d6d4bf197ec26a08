"""Every VL encoder backend implements the whole VLEncoder protocol, the keyframe view included."""

from __future__ import annotations

import importlib
import inspect

import pytest

from shared.perception import VLEncoder

BACKENDS = [
    pytest.param("shared.perception.encoders.simulated", "SimulatedVLEncoder", (), id="simulated"),
    # importing torch alone takes seconds
    pytest.param("shared.perception.encoders.openclip", "OpenClipEncoder", ("torch",), id="openclip", marks=pytest.mark.slow),
    pytest.param("shared.perception.encoders.clip_onnx", "ClipOnnxEncoder", (), id="clip_onnx"),
]


def _methods(cls: type) -> dict[str, inspect.Signature]:
    return {n: inspect.signature(f) for n, f in vars(cls).items() if inspect.isfunction(f) and not n.startswith("_")}


def test_the_protocol_asks_for_a_keyframe_view():
    assert list(inspect.signature(VLEncoder.encode_view).parameters) == ["self", "image"]


@pytest.mark.parametrize(("module", "name", "needs"), BACKENDS)
def test_backend_has_every_protocol_method_with_its_parameters(module, name, needs):
    for dep in needs:
        pytest.importorskip(dep)
    cls = getattr(importlib.import_module(module), name)
    ours = {n: inspect.signature(getattr(cls, n)) for n in _methods(VLEncoder) if callable(getattr(cls, n, None))}
    assert set(ours) == set(_methods(VLEncoder)), f"{name} lacks {sorted(set(_methods(VLEncoder)) - set(ours))}"
    for n, sig in _methods(VLEncoder).items():
        assert list(ours[n].parameters) == list(sig.parameters), f"{name}.{n}{ours[n]} differs from the protocol's {sig}"
