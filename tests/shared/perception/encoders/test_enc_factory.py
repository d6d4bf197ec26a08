"""The encoder factory: light to import, and clear about bad backends."""

from __future__ import annotations

import subprocess
import sys

import pytest

from shared.perception.encoders import VL_ENCODERS, make_vl_encoder
from shared.perception.encoders.config import vl_config
from shared.perception.encoders.simulated_config import SimulatedVLConfig
from shared.registry import UnknownName


def test_importing_the_encoders_loads_no_heavy_library():
    heavy = ("torch", "open_clip", "onnxruntime", "sentence_transformers", "transformers")
    code = (
        "import sys\n"
        "import shared.perception.encoders, shared.perception.encoders.weights, shared.perception.encoders.crops\n"
        f"print(','.join(m for m in {heavy!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"heavy modules imported: {out.stdout.strip()}"


def test_every_backend_is_registered_with_its_own_model():
    assert VL_ENCODERS.names() == ("openclip", "clip_onnx", "simulated")
    for name, model in VL_ENCODERS.items():
        assert model.model_fields["backend"].default == name
        assert type(vl_config(backend=name)) is model


def test_unknown_backend_is_refused():
    with pytest.raises(UnknownName, match="unknown VL encoder backend 'simulatd' .did you mean 'simulated'"):
        vl_config(backend="simulatd")


def test_the_factory_builds_what_the_config_describes(tmp_path):
    with pytest.raises(FileNotFoundError):
        make_vl_encoder(SimulatedVLConfig(ground_truth=str(tmp_path / "nowhere")))
