"""A small synthetic sequence generated once for the tests that read one."""

from __future__ import annotations

import time
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def small_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, float]:
    """The ``small`` preset, seed 0: (folder, result, seconds)."""
    from shared.synth import generate

    out = tmp_path_factory.mktemp("synth") / "small0"
    t0 = time.perf_counter()
    result = generate("small", 0, out, progress=False)
    return out, result, time.perf_counter() - t0


def shrink_synth(monkeypatch: pytest.MonkeyPatch, overrides: dict) -> None:
    """``trackgraph synth`` renders its preset with ``overrides`` (a few small frames) in place
    of the whole sequence; the other arguments (drift, resolution) pass through."""
    import shared.synth

    real = shared.synth.run_synth

    def short(preset, seed, out, _overrides=None, **kw):
        return real(preset, seed, out, overrides, **kw)

    monkeypatch.setattr(shared.synth, "run_synth", short)
