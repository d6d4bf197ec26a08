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
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache benchmarks/out

# The demo: the synthetic demo scene (three furnished rooms, 900 RGB-D frames with ground
# truth), its pictures, and the OpenLex3D upper bound of a perfect map of it.
DEMO_OUT ?= demo_out
.PHONY: demo
demo: $(STAMP)
	$(BIN)/trackgraph synth --preset demo --seed 0 --out $(DEMO_OUT)/sequence --overwrite
	$(BIN)/trackgraph eval openlex3d --oracle --gt $(DEMO_OUT)/sequence
	@echo "demo scene:   $(DEMO_OUT)/sequence (Replica layout, ground truth in gt/)"
	@echo "pictures:     $(DEMO_OUT)/sequence/contact_sheet.png, $(DEMO_OUT)/sequence/topdown.png"
