"""The factory picks backends by name and importing the package stays light."""

from __future__ import annotations

import subprocess
import sys

import pytest
from seg_room import truth

from shared.perception.segmenters import SEGMENTERS, make_segmenter
from shared.perception.segmenters.config import segmenter_config
from shared.perception.segmenters.simulated import SimulatedSegmenter

LIGHT = [
    "shared.perception.segmenters",
    "shared.perception.segmenters.base",
    "shared.perception.segmenters.simulated",
    "shared.perception.segmenters.classical",
    "shared.perception.segmenters.yolo_post",
    "shared.perception.segmenters.fastsam",
    "shared.perception.segmenters.fastsam_onnx",
]


def test_importing_segmenters_loads_no_heavy_library():
    code = (
        "import sys\n"
        + "".join(f"import {m}\n" for m in LIGHT)
        + "print(','.join(m for m in ('torch', 'ultralytics', 'onnxruntime', 'cv2') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""


@pytest.mark.parametrize("backend", ["classical", "simulated"])
def test_weightless_backends(backend, room):
    if backend == "simulated":
        seg = SimulatedSegmenter(segmenter_config(backend=backend), truth(room))
    else:
        seg = make_segmenter(segmenter_config(backend=backend))
    assert seg.name == backend
    out = seg.segment(room)
    assert out.masks.shape[1:] == room.rgb.shape[:2] and len(out) > 0


def test_every_backend_is_registered_with_its_own_model():
    assert SEGMENTERS.names() == ("fastsam", "fastsam_onnx", "classical", "simulated")
    for name, model in SEGMENTERS.items():
        assert model.model_fields["backend"].default == name
        assert type(segmenter_config(backend=name)) is model
    with pytest.raises(ValueError, match="unknown segmenter backend 'fastsm' .did you mean 'fastsam'"):
        segmenter_config(backend="fastsm")


def test_bad_images_are_refused(room):
    seg = make_segmenter(segmenter_config(backend="classical"))
    import dataclasses

    with pytest.raises(ValueError, match="uint8"):
        seg.segment(dataclasses.replace(room, rgb=room.rgb.astype(float)))


def test_ultralytics_import_leaves_the_process_alone():
    """ultralytics patches PIL.Image.open, pins OMP_NUM_THREADS (leaving torch on one thread)
    and sets numpy print options on import; import_ultralytics avoids or undoes all of it."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    code = (
        "import os, numpy as np\n"
        "from PIL import Image\n"
        "before = (Image.open, np.get_printoptions(), 'OMP_NUM_THREADS' in os.environ)\n"
        "from shared.perception.segmenters.fastsam import import_ultralytics\n"
        "import_ultralytics()\n"
        "import torch\n"
        "after = (Image.open, np.get_printoptions(), 'OMP_NUM_THREADS' in os.environ)\n"
        "print(before == after, torch.get_num_threads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    plain = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.get_num_threads())"],
        capture_output=True, text=True, timeout=120, env=env,
    )
    # The first ultralytics import on a machine also prints that it created its settings file.
    assert out.stdout.strip().splitlines()[-1].split() == ["True", plain.stdout.strip().splitlines()[-1]]
