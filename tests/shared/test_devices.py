"""Devices and precisions as configs name them (shared/devices.py)."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from shared.config.keyframe_vl import KeyframeVLConfig
from shared.config.query import QueryConfig
from shared.config.tracker import TrackerConfig
from shared.devices import device_index, device_type, resolve_device, resolve_precision
from shared.perception.features.config import dense_features_config


@pytest.mark.parametrize("device", ["auto", "cpu", "cuda", "cuda:0", "cuda:1", "cuda:12"])
def test_configs_accept_every_device_form(device):
    assert KeyframeVLConfig(device=device).device == device
    assert TrackerConfig(device=device).device == device
    assert QueryConfig(device=device).device == device


@pytest.mark.parametrize("device", ["gpu", "cuda:", "cuda:x", "CUDA", "cuda:-1", "mps0"])
def test_configs_refuse_other_devices_naming_the_field(device):
    with pytest.raises(ValidationError, match="device"):
        KeyframeVLConfig(device=device)
    with pytest.raises(ValueError, match="expected auto, cpu, cuda or cuda:N"):
        resolve_device(device)


def test_precision_fields_take_the_four_values_and_nothing_else():
    for p in ("auto", "fp32", "fp16", "bf16"):
        assert dense_features_config(precision=p).precision == p
    with pytest.raises(ValidationError, match="precision"):
        dense_features_config(precision="int8")


def test_auto_precision_is_half_on_cuda_only_and_explicit_choices_stay():
    assert resolve_precision("auto", "cuda:1") == "fp16"
    assert resolve_precision("auto", "cuda", half_default=False) == "fp32"
    assert resolve_precision("auto", "cpu") == "fp32"
    assert resolve_precision("bf16", "cpu") == "bf16"
    assert resolve_precision("fp16", "cpu") == "fp16"
    assert device_type("cuda:3") == "cuda" and device_index("cuda:3") == 3 and device_index("cuda") == 0


def test_gpu_devices_are_checked_against_what_torch_sees(monkeypatch):
    torch = pytest.importorskip("torch")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu"
    with pytest.raises(ValueError, match=r"tracker.device 'cuda:1': torch .* sees no CUDA GPU"):
        resolve_device("cuda:1", "tracker.device")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == "cuda"
    assert resolve_device("cuda:1") == "cuda:1"
    with pytest.raises(ValueError, match=r"'cuda:2': torch sees 2 CUDA device\(s\), cuda:0 to cuda:1"):
        resolve_device("cuda:2")


def test_onnx_providers_pin_the_gpu_index(monkeypatch):
    ort = pytest.importorskip("onnxruntime")
    from shared.devices import onnx_providers

    assert onnx_providers("cpu") == ["CPUExecutionProvider"]
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    assert onnx_providers("cuda:1") == [("CUDAExecutionProvider", {"device_id": 1}), "CPUExecutionProvider"]
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    assert onnx_providers("cuda:1") == ["CPUExecutionProvider"]
