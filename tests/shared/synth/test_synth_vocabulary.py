"""Vocabulary, clutter ids, configuration and the light import of ``shared.synth``."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from shared.config.base import ConfigError
from shared.synth.config import PRESETS, SynthConfig, preset_config
from shared.synth.furniture import FURNITURE
from shared.synth.items import ITEMS
from shared.synth.vocabulary import STRUCTURAL, VOCABULARY, prompt_list, tiers
from shared.synth.world import clutter_ids


def test_at_least_25_object_categories():
    objects = [c for c in VOCABULARY if c not in STRUCTURAL]
    assert len(objects) >= 25
    for c in STRUCTURAL:
        assert c in VOCABULARY


def test_every_builder_category_has_labels():
    rng = np.random.default_rng(0)
    cats = {b(rng).category for b in FURNITURE.values()} | {b(rng).category for b in ITEMS.values()}
    assert cats <= set(VOCABULARY)
    assert len(cats) >= 30
    for c in VOCABULARY:
        assert VOCABULARY[c].synonyms[0] == c, "the first synonym is the category name"


def test_prompt_list_sorted_unique_and_complete():
    prompts = prompt_list()
    assert prompts == sorted(set(prompts))
    for t in VOCABULARY.values():
        assert set(t.synonyms) | set(t.depictions) | set(t.vis_sim) <= set(prompts)


def test_instance_depictions_are_added():
    t = tiers("cushion", ("stripes", "stripes"))
    assert t.depictions == ("stripes",)
    assert "cushion" in t.synonyms


def test_clutter_of_hand_built_boxes():
    lo = np.array([[0, 0, 0], [0.9, 0, 0], [5, 5, 5], [1.0, 1.0, 1.0]], float)
    hi = np.array([[1, 1, 1], [2, 1, 1], [6, 6, 6], [1.5, 1.5, 1.5]], float)
    # Box 3 only touches box 0's corner: overlapping once inflated, not before.
    got = clutter_ids(lo, hi, margin=0.02)
    assert got == [[1, 3], [0, 3], [], [0, 1]]
    assert clutter_ids(lo, hi, margin=0.0) == [[1], [0], [], []]
    for i, ids in enumerate(got):
        for j in ids:
            assert i in got[j]
    eligible = np.array([True, False, True, True])
    assert clutter_ids(lo, hi, 0.02, eligible) == [[3], [], [], [0]]


def test_presets_validate_and_differ():
    assert set(PRESETS) == {"small", "demo", "revisit", "building"}
    small, demo, revisit = (preset_config(p) for p in ("small", "demo", "revisit"))
    assert (small.camera.width, small.camera.height, small.camera.frames) == (320, 240, 120)
    assert (demo.camera.width, demo.camera.height, demo.camera.frames) == (640, 480, 900)
    assert demo.layout.kind == "suite" and demo.layout.rooms in (2, 3)
    assert revisit.layout.kind == "revisit"


def test_focal_from_field_of_view():
    cfg = preset_config("demo")
    hfov = 2 * np.degrees(np.arctan(cfg.camera.width / 2 / cfg.focal()))
    assert 70 <= hfov <= 80


def test_unknown_preset_and_bad_override_are_config_errors():
    with pytest.raises(ConfigError, match="unknown synth preset 'huge'"):
        preset_config("huge")
    with pytest.raises(ConfigError, match=r"camera\.framez: unknown key \(did you mean 'frames'\?\)"):
        preset_config("small", {"camera": {"framez": 3}})
    with pytest.raises(ConfigError, match="clearance"):
        preset_config("small", {"camera": {"clearance": 0.6}})
    assert preset_config("small", {"camera": {"frames": 7}}).camera.frames == 7


def test_extra_keys_forbidden_and_fields_documented():
    with pytest.raises(Exception, match="extra"):
        SynthConfig.model_validate({"colour": 1})
    for model in (SynthConfig, *[f.annotation for f in SynthConfig.model_fields.values()]):
        for name, field in model.model_fields.items():
            assert field.description, f"{model.__name__}.{name} has no docstring"


def test_importing_synth_is_light():
    code = "import sys, shared.synth; print(','.join(m for m in ('open3d', 'matplotlib', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""
