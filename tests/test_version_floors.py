"""The version floors of pyproject.toml hold for what is installed, and are no lower than the
versions that first have the APIs the code calls. Installs nothing."""

from __future__ import annotations

import sys
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 (the Jetson's)
    tomllib = pytest.importorskip("tomli")

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"

API_FLOORS = {
    # Each checked by reading the wheel of that version (pip download --no-deps), 2026-12-04.
    "transformers": ("4.56", "DINOv3ViTModel (shared/perception/features/dinov3.py)"),
    "timm": ("1.0.20", "vit_small_plus_patch16_dinov3[_qkvb] and eva.checkpoint_filter_fn"),
    "open-clip-torch": ("3.0", "model.visual.preprocess_cfg, get_tokenizer(context_length=)"),
    # 8.3.0 names FastSAM's half precision `half`, later ones `quantize`: predict gets neither
    # (autocast), and the ONNX export passes the one the installed version has.
    "ultralytics": ("8.3", "FastSAM, predict(retina_masks=, max_det=), export(format='onnx', dynamic=)"),
    "rosbags": ("0.11", "Stores.ROS2_JAZZY and ROS2_KILTED, Typestore.hash_rihs01 (shared/ros2/types.py)"),
    "torch": ("2.2", "torch.autocast on CPU with bfloat16; fp16 on CPU is refused below 2.5"),
}
"""The lowest version with every API the code calls, and which APIs set it."""


def requirements() -> list[Requirement]:
    project = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in project["optional-dependencies"].values():
        reqs += [Requirement(r) for r in extra if not r.startswith("trackgraph[")]
    return reqs


def floor(req: Requirement) -> Version | None:
    lows = [Version(s.version) for s in req.specifier if s.operator in (">=", "==", "~=")]
    return max(lows) if lows else None


def test_installed_versions_satisfy_the_floors():
    checked, wrong = 0, []
    for req in requirements():
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        try:
            installed = metadata.version(req.name)
        except metadata.PackageNotFoundError:
            continue  # an extra this environment does not install (gpu beside fusion, say)
        checked += 1
        if not req.specifier.contains(installed, prereleases=True):
            wrong.append(f"{req.name} {installed} (pyproject.toml asks {req.specifier})")
    assert not wrong, "installed versions outside pyproject.toml's ranges: " + "; ".join(wrong)
    assert checked >= 10  # the core and the dev tools at least


@pytest.mark.parametrize("name", sorted(API_FLOORS))
def test_no_floor_is_below_the_apis_the_code_calls(name):
    asked = [floor(r) for r in requirements() if r.name == name]
    assert asked, f"{name} is not a requirement of pyproject.toml"
    need, apis = API_FLOORS[name]
    for low in asked:
        assert low is not None and low >= Version(need), f"{name}>={low} allows versions without {apis} (needs {need})"
