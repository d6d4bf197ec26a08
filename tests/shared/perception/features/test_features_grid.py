"""The input-resize rule shared by every dense-feature backend, and the light package import."""

from __future__ import annotations

import subprocess
import sys

import pytest

from shared.perception.features import grid_shape, resized_shape


@pytest.mark.parametrize(
    ("height", "width", "short", "expected"),
    [
        (680, 1200, 720, (720, 1264)),  # Replica: 1200 * 720/680 = 1270.6 -> 79.4 patches -> 79
        (680, 1200, 480, (480, 848)),  # onboard: 847.1 -> 52.9 patches -> 53
        (1200, 680, 720, (1264, 720)),  # portrait keeps the rule on the short side
        (480, 640, 480, (480, 640)),  # already a multiple: unchanged
        (240, 320, 240, (240, 320)),
        (1440, 1920, 720, (720, 960)),  # ScanNet++ iPhone
        (720, 1080, 720, (720, 1088)),  # HM3D walks: 67.5 patches rounds half up to 68
        (480, 640, 700, (704, 944)),  # a short side that is not a multiple rounds too
        (10, 10, 720, (720, 720)),
        (8, 1000, 16, (16, 2000)),
    ],
)
def test_resized_shape_hand_cases(height, width, short, expected):
    assert resized_shape(height, width, short, 16) == expected
    assert grid_shape(height, width, short, 16) == (expected[0] // 16, expected[1] // 16)


def test_resize_keeps_aspect_within_half_a_patch():
    for height, width in [(680, 1200), (480, 640), (1440, 1920), (123, 457), (1000, 333)]:
        rh, rw = resized_shape(height, width, 720, 16)
        assert rh % 16 == 0 and rw % 16 == 0 and min(rh, rw) == 720
        scale = 720 / min(height, width)
        assert abs(max(rh, rw) - max(height, width) * scale) <= 8


def test_other_patch_sizes():
    assert resized_shape(680, 1200, 720, 14) == (714, 1260)
    assert grid_shape(680, 1200, 720, 14) == (51, 90)


def test_bad_sizes_raise():
    with pytest.raises(ValueError):
        resized_shape(0, 10, 720, 16)


def test_importing_the_package_does_not_import_torch():
    code = (
        "import sys\n"
        "import shared.perception.features, shared.perception.features.base\n"
        "heavy = [m for m in ('torch', 'timm', 'transformers', 'onnxruntime', 'onnx') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""
