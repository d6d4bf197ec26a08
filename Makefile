# Two commands for a new user: `make test` and `make demo`. Both create .venv if absent.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
# torch first, pinned: a bare `torch` requirement pulls the newest multi-GB CUDA build.
# ultralytics, open_clip and timm need torchvision, and PyPI's torchvision only imports
# beside its matching torch, so both are pinned together (this pair runs on the CPU too).
TORCH  ?= torch==2.14.1 torchvision==0.29.1

.PHONY: test lint install clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --disable-pip-version-check $(TORCH)
	$(BIN)/python -m pip install -q --disable-pip-version-check -e ".[dev,all]"
	touch $@

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check .

test: $(STAMP) lint
	$(BIN)/python -m pytest -q --durations=30

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache benchmarks/out

# docs/wire.md and docs/schema/*.json from the message models; `make wire-docs` after changing a
# message, a key or the codec (tests/shared/messages/test_wiredoc.py fails until then).
.PHONY: wire-docs
wire-docs: $(STAMP)
	$(BIN)/python -m shared.messages.wiredoc

# The demo: the synthetic demo scene (three furnished rooms, 900 RGB-D frames with ground
# truth) through the whole distributed system (one process per service over loopback Zenoh),
# example queries through the live query service, then the report, renders and recordings.
# The paper's models are used when their weights are present, simulated perception otherwise;
# DEMO_CONFIG=FILE forces a config.
DEMO_OUT    ?= demo_out
DEMO_CONFIG ?=
.PHONY: demo
$(DEMO_OUT)/sequence/traj.txt: | $(STAMP)
	$(BIN)/trackgraph synth --preset demo --seed 0 --out $(DEMO_OUT)/sequence --overwrite

demo: $(STAMP) $(DEMO_OUT)/sequence/traj.txt
	$(BIN)/trackgraph demo --out $(DEMO_OUT) $(if $(DEMO_CONFIG),--config $(DEMO_CONFIG))

# Fusion (and what else runs Open3D: the synthetic renderer, the OpenLex3D voxel rule) against
# Open3D 0.18, the oldest release the `fusion` extra accepts, in a venv of its own; .venv has
# the newest. Open3D 0.18 has wheels up to CPython 3.11 only. torch (the CPU build) is there for
# the torch vote and the device tests.
O3D018_PYTHON ?= python3.11
O3D018_VENV   ?= .venv-o3d018
O3D018_TESTS  ?= tests/services/fusion tests/shared/synth tests/shared/eval/test_openlex3d_rules.py
.PHONY: test-open3d-0.18
$(O3D018_VENV)/.installed-stamp: pyproject.toml
	$(O3D018_PYTHON) -m venv $(O3D018_VENV)
	$(O3D018_VENV)/bin/python -m pip install -q --disable-pip-version-check -e ".[fusion,source]" \
		open3d-cpu==0.18.0 torch==2.13.0 pytest pytest-timeout hypothesis
	touch $@

test-open3d-0.18: $(O3D018_VENV)/.installed-stamp
	$(O3D018_VENV)/bin/python -c "import open3d; assert open3d.__version__.startswith('0.18.'), open3d.__version__"
	$(O3D018_VENV)/bin/python -m pytest -q -p no:cacheprovider $(O3D018_TESTS)
