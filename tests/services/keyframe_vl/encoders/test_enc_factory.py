"""The encoder factory: light to import, and clear about bad backends."""

from __future__ import annotations

import subprocess
import sys

import pytest

from services.keyframe_vl.encoders import BACKENDS, make_vl_encoder
from shared.config.keyframe_vl import VLEncoderConfig


def test_importing_the_encoders_loads_no_heavy_library():
    heavy = ("torch", "open_clip", "onnxruntime", "sentence_transformers", "transformers")
    code = (
        "import sys\n"
        "import services.keyframe_vl.encoders, services.keyframe_vl.encoders.weights, services.keyframe_vl.crops\n"
        f"print(','.join(m for m in {heavy!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"heavy modules imported: {out.stdout.strip()}"


def test_every_config_backend_is_known():
    assert set(BACKENDS) == set(VLEncoderConfig.model_fields["backend"].annotation.__args__)


def test_unknown_backend_is_refused():
    cfg = VLEncoderConfig.model_construct(backend="nope")
    with pytest.raises(ValueError, match="unknown VL encoder backend"):
        make_vl_encoder(cfg)
