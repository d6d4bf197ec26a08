"""The TSDF's device choice without a CUDA Open3D (``open3d-cpu``, or the ``gpu`` extra's
``open3d`` on a machine without a GPU): 'auto' falls back to the CPU, an explicit 'cuda'
refuses with a message that says what to install, and an unknown device is refused.

CUDA's presence is monkeypatched on both Open3D and torch, so these run the same on any
machine; nothing here needs or touches a GPU."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.volume.grid import resolve_device
from services.fusion.volume.tsdf import HypothesisTSDF
from shared.config.fusion import TSDFConfig
from shared.geometry import Intrinsics
from shared.o3d import import_open3d

torch = pytest.importorskip("torch")


@pytest.fixture
def o3d():
    return import_open3d()


def _cuda(monkeypatch, o3d, *, open3d: bool, torch_cuda: bool) -> None:
    monkeypatch.setattr(o3d.core.cuda, "is_available", lambda: open3d)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: torch_cuda)


def test_open3d_imports_and_reports_its_cuda(o3d):
    assert tuple(int(v) for v in o3d.__version__.split(".")[:2]) >= (0, 18)
    assert isinstance(o3d.core.cuda.is_available(), bool)
    assert o3d.core.cuda.device_count() >= 0
    assert str(o3d.core.Device("CPU:0")) == "CPU:0"


@pytest.mark.parametrize("open3d, torch_cuda", [(False, False), (False, True), (True, False)])
def test_auto_picks_the_cpu_unless_both_have_cuda(monkeypatch, o3d, open3d, torch_cuda):
    _cuda(monkeypatch, o3d, open3d=open3d, torch_cuda=torch_cuda)
    assert resolve_device("auto") == "CPU:0"
    assert resolve_device("AUTO") == "CPU:0"


def test_auto_takes_cuda_when_both_have_it(monkeypatch, o3d):
    _cuda(monkeypatch, o3d, open3d=True, torch_cuda=True)
    assert resolve_device("auto") == "CUDA:0"


def test_auto_without_torch_picks_the_cpu(monkeypatch, o3d):
    import builtins

    monkeypatch.setattr(o3d.core.cuda, "is_available", lambda: True)
    real_import = builtins.__import__

    def no_torch(name, *args, **kwargs):
        if name == "torch":
            raise ImportError("no torch here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_torch)
    assert resolve_device("auto") == "CPU:0"


@pytest.mark.parametrize("device", ["cpu", "CPU", "cpu:0"])
def test_cpu_is_cpu(monkeypatch, o3d, device):
    _cuda(monkeypatch, o3d, open3d=True, torch_cuda=True)
    assert resolve_device(device) == "CPU:0"


@pytest.mark.parametrize("device", ["cuda", "cuda:0", "cuda:1", "CUDA:1"])
def test_cuda_refused_without_a_cuda_open3d(monkeypatch, o3d, device):
    _cuda(monkeypatch, o3d, open3d=False, torch_cuda=True)
    with pytest.raises(RuntimeError, match=r"has no CUDA.*install `open3d`, not `open3d-cpu`") as err:
        resolve_device(device)
    assert repr(device) in str(err.value)


@pytest.mark.parametrize("device, name", [("cuda", "CUDA:0"), ("cuda:1", "CUDA:1")])
def test_cuda_with_a_cuda_open3d_names_the_index(monkeypatch, o3d, device, name):
    _cuda(monkeypatch, o3d, open3d=True, torch_cuda=True)
    assert resolve_device(device) == name


@pytest.mark.parametrize("device", ["gpu", "tpu", "mps", "", "vulkan"])
def test_unknown_device_refused(monkeypatch, o3d, device):
    _cuda(monkeypatch, o3d, open3d=False, torch_cuda=False)
    with pytest.raises(ValueError, match=r"unknown device .*'auto', 'cpu' or 'cuda\[:N\]'"):
        resolve_device(device)


def _small() -> TSDFConfig:
    return TSDFConfig(voxel_size=0.05, initial_blocks=64)


def test_volume_on_auto_falls_back_to_the_cpu_and_integrates(monkeypatch, o3d):
    _cuda(monkeypatch, o3d, open3d=False, torch_cuda=False)
    tsdf = HypothesisTSDF(_small(), device="auto")
    assert tsdf.device_name == "CPU:0"
    assert str(tsdf.vbg.hashmap().device) == "CPU:0"
    K = Intrinsics(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48)
    depth = np.full((48, 64), 1.5, np.float32)
    rgb = np.full((48, 64, 3), 128, np.uint8)
    ids = np.zeros((48, 64), np.int32)
    stats = tsdf.integrate(depth, rgb, K, np.eye(4), ids, {0: 1.0})
    assert stats.frame_blocks > 0 and tsdf.active_blocks > 0


@pytest.mark.parametrize("device", ["cuda", "cuda:1"])
def test_volume_on_cuda_refused_without_a_cuda_open3d(monkeypatch, o3d, device):
    _cuda(monkeypatch, o3d, open3d=False, torch_cuda=False)
    with pytest.raises(RuntimeError, match="this open3d build has no CUDA"):
        HypothesisTSDF(_small(), device=device)


def test_volume_on_cuda_refused_when_torch_has_no_cuda(monkeypatch, o3d):
    # A CUDA Open3D beside a CPU torch: the vote runs in torch on the grid's memory, so the
    # volume refuses before it allocates anything on the GPU.
    _cuda(monkeypatch, o3d, open3d=True, torch_cuda=False)
    with pytest.raises(RuntimeError, match="torch has no CUDA for the vote"):
        HypothesisTSDF(_small(), device="cuda")


def test_volume_refuses_an_unknown_device(monkeypatch, o3d):
    _cuda(monkeypatch, o3d, open3d=False, torch_cuda=False)
    with pytest.raises(ValueError, match="unknown device 'gpu'"):
        HypothesisTSDF(_small(), device="gpu")
